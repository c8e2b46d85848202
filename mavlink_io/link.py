"""MavlinkLink: one connection to the flight controller, polled from the daemon's loop.

Usage::

    link = MavlinkLink(LinkConfig(url="udpin:0.0.0.0:14550"))
    while running:
        for item in link.poll(timeout_s=0.1):  # returns on input or at the link's next timer
            ...  # ImuSample (ImuBatch with LinkConfig.imu_batch) | PressureSample | FcAttitude |
                 # FcHeartbeat | FcEkfStatus | FcSysStatus | CommandAck | IncomingCommand | LinkEvent
    link.send(link.mav.attitude_encode(...))  # outputs, from our identity; never raises
    link.close()

What ``poll()`` does, in order, without ever raising on bad input (each step is its own module;
this class only wires them):
1. (re)open the transport if it is down and its backoff has expired (:mod:`mavlink_io.session`);
2. wait up to ``timeout_s`` for bytes (less if a timer is due), read everything available;
3. parse with pymavlink (MAVLink 2 out, 1 or 2 in, ardupilotmega dialect; :mod:`mavlink_io.framing`);
   bad CRC / framing / unknown ids are counted in :class:`~mavlink_io.stats.LinkStats`; without a
   signing key, CRC-checked unsigned RAW_IMU frames are set apart first (:mod:`mavlink_io.frame_scan`,
   fastcrc; or its compiled copy given as ``frame_scan``: service/link_core.py) and decoded without
   pymavlink (:mod:`mavlink_io.imu_batch`: the same checks, counters and events per frame; each its
   ImuSample, or with ``imu_batch`` one ImuBatch per run of consecutive samples);
4. signing policy and commands to us (:mod:`mavlink_io.security`): a signed frame that fails
   verification is dropped, unsigned frames by ``require_signed``; COMMAND_LONG/INT addressed
   exactly to our component become IncomingCommand; then keep only the autopilot's messages (its
   system id, its component; our own echoes and other components are counted and ignored), learn
   the autopilot from its HEARTBEAT;
5. decode into the typed samples of :mod:`mavlink_io.samples` (:mod:`mavlink_io.sample_decoder`:
   SI units, FC time via :mod:`mavlink_io.timebase`, one IMU and one pressure stream);
6. timers: our HEARTBEAT and the link timeout (session), the SET_MESSAGE_INTERVAL round and the
   achieved-rate and silent-stream checks (:mod:`mavlink_io.stream_rates`), parameter reads
   (:mod:`mavlink_io.params`), the signing timestamp and the kernel drop counter once a second.

LinkEvent kinds (LINK_EVENT_KINDS): autopilot_detected, rates_requested, rates_acked, rates_limited,
fc_reboot, time_gap, time_wrap, link_lost, link_restored, reconnect, transport_error (a port that
cannot be opened or died; retried with backoff), signature_rejected and unsigned_command_rejected
(rate-limited; never key or signature bytes), udp_split_frames, params_read, input_backlog.

Identity: HEARTBEAT type MAV_TYPE_ONBOARD_CONTROLLER, autopilot MAV_AUTOPILOT_INVALID, component
``component_id`` (191), system id = the vehicle's (configured, or learned from the autopilot's
heartbeat; 1 until then). MAVLink 2 framing. ``time_rx_s`` is the link clock (time.monotonic by
default) when a read returned, shared by the messages of that read.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before the first pymavlink import (mavutil reads it at import)

import time
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import decode as dec, frame_pack
from mavlink_io.frame_scan import RawImuFrame
from mavlink_io.framing import FrameParser, SeqTracker
from mavlink_io.imu_batch import BatchBuilder, ImuBatch, raw_imu_sample
from mavlink_io.link_config import (DEFAULT_STREAM_RATES_HZ, IMU_SOURCES, LINK_EVENT_KINDS,  # noqa: F401 - re-exported
                                    REQUIRE_SIGNED, FcPeer, LinkConfig, LinkEvent, message_id)
from mavlink_io.params import ParamReader
from mavlink_io.sample_decoder import SampleDecoder, fc_stamp_s
from mavlink_io.samples import (CommandAck, FcAttitude, FcEkfStatus, FcHeartbeat, FcSysStatus,
                                ImuSample, IncomingCommand, PressureSample)
from mavlink_io.security import COMMAND_TYPES, LinkSecurity
from mavlink_io.session import Session
from mavlink_io.stats import LinkStats
from mavlink_io.stream_rates import StreamRates
from mavlink_io.transport import Transport, make_transport
from mavlink_io.url import Endpoint, parse_url

SIGNING_REFRESH_S = 1.0
"""How often the outgoing signing timestamp is pulled up to the wall clock and the transport's
kernel drop counter is read (poll's timers)."""
_PLACEHOLDER_SYSID = 1
"""Our system id before the vehicle's is known (the ArduPilot/PX4 default SYSID)."""
_NOT_VEHICLE_TYPES = {mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_TYPE_GIMBAL,
                      mavlink2.MAV_TYPE_ADSB, mavlink2.MAV_TYPE_CAMERA}

Item = (ImuSample | ImuBatch | PressureSample | FcAttitude | FcHeartbeat | FcEkfStatus | FcSysStatus | CommandAck
        | IncomingCommand | LinkEvent | dec.FcStatusText | dec.FcParam)


class _Writer:
    """The 'file' pymavlink's MAVLink object writes to: forwards to the session, never raises."""

    def __init__(self, link: "MavlinkLink"):
        self._link = link

    def write(self, buf) -> None:
        self._link._session.write(bytes(buf))


class MavlinkLink:
    """The FC connection. Single-threaded: call ``poll()`` from one loop.

    Public state: ``fc_autopilot`` ("ardupilot" | "px4" | "other" | None), ``target_system``,
    ``target_component`` (None until learned), ``connected``, ``stats`` (LinkStats), ``mav`` (the
    pymavlink MAVLink object: encoders, our srcSystem/srcComponent, sequence numbers).
    """

    def __init__(self, cfg: LinkConfig, clock: Callable[[], float] = time.monotonic,
                 transport: Transport | None = None, wall_clock: Callable[[], float] = time.time,
                 frame_scan: Callable | None = None):
        """cfg: LinkConfig; clock: monotonic seconds (injectable for tests and replay);
        transport: override the transport made from cfg.url (e.g. NullTransport for replay);
        wall_clock: Unix time, s (only for the outgoing signing timestamp);
        frame_scan: a copy of frame_scan.split_raw_imu to use instead (the compiled core's: the service
        passes it, service/link_core.py; mavlink_io imports nothing above it).
        Never raises for an unreachable port or device (it is retried with backoff and reported
        as a "transport_error" LinkEvent); raises ValueError only for a bad configuration."""
        self.cfg = cfg
        self.clock = clock
        self.endpoint: Endpoint = parse_url(cfg.url)
        self.stats = LinkStats(rate_window_s=cfg.rate_window_s)
        self.mav = mavlink2.MAVLink(_Writer(self), srcSystem=cfg.system_id or _PLACEHOLDER_SYSID,
                                    srcComponent=cfg.component_id)
        self.wall_clock = wall_clock
        self._fc = FcPeer(cfg.system_id, cfg.autopilot_component_id)
        self._source_seen_s: dict[str, float] = {}
        self._pending: list[Item] = []
        self._subscribers: list[tuple[Callable, frozenset | None]] = []
        self._closed = False
        self._security = LinkSecurity(cfg, self.mav, self.stats, wall_clock, self._event)
        self._parser = FrameParser(self.stats, self._split_sender_found, self._set_error)
        # unsigned RAW_IMU frames without pymavlink (frame_scan, fastcrc) on both paths: a read's samples
        # as one ImuBatch (imu_batch), else each its ImuSample; a key sends every frame to pymavlink
        self._parser.split_imu = self._security.verifier is None
        if frame_scan is not None:
            self._parser.scan = frame_scan
        self._batch = BatchBuilder()
        self._seq = SeqTracker(self.stats)
        self._rates = StreamRates(cfg, self.stats, self._fc, self._source_seen_s, self.mav, self.send, self._event)
        self._decoder = SampleDecoder(cfg, self.stats, self._fc, self._source_seen_s, self._event,
                                      self._on_fc_reboot)
        self._params = ParamReader(timeout_s=max(cfg.ack_timeout_s, 1.0), max_tries=cfg.request_tries)
        self._params_reported = False
        now = clock()
        self._next_signing_refresh_s = now + SIGNING_REFRESH_S
        self._session = Session(cfg, self.endpoint,
                                transport if transport is not None
                                else make_transport(self.endpoint, rcvbuf_bytes=cfg.udp_rcvbuf_bytes),
                                self.stats, self.mav, clock, self.send, self._event, self._parser.new_stream)
        self._session.try_open(now)

    # --- public state ---------------------------------------------------------------------------

    @property
    def fc_autopilot(self) -> str | None:
        return self._fc.autopilot

    @property
    def target_system(self) -> int | None:
        return self._fc.system

    @property
    def target_component(self) -> int | None:
        return self._fc.component

    @property
    def connected(self) -> bool:
        return self._session.connected

    @property
    def last_error(self) -> str | None:
        return self._session.last_error

    @last_error.setter
    def last_error(self, text: str | None) -> None:
        self._session.last_error = text

    def _set_error(self, text: str) -> None:
        self._session.last_error = text

    @property
    def rate_refusal_text(self) -> str | None:
        """The FC's last STATUSTEXT refusing a rate (ArduPilot: "... too fast. Increase SCHED_LOOP_RATE")."""
        return self._rates.rate_refusal_text

    @property
    def rate_advice(self) -> str | None:
        """The last rates_limited advice (which FC parameter to change), None while every rate is met."""
        return self._rates.rate_advice

    @property
    def local_address(self) -> tuple | None:
        """The bound address of a listening transport (udpin/tcpin; useful with port 0)."""
        s = self._session
        return s.transport.local_address if s.open_ok else None

    @property
    def udp_rcvbuf_bytes_granted(self) -> int | None:
        """What the kernel granted for the UDP receive buffer (Linux reports twice the effective
        request); None for other transports or while closed."""
        s = self._session
        return getattr(s.transport, "rcvbuf_bytes_granted", None) if s.open_ok else None

    @property
    def signing_timestamp(self) -> int | None:
        """Our current outgoing signing timestamp (10 us units since 2015-01-01 UTC), None without
        a key. Persist it and pass it back as ``signing_timestamp_floor`` after a restart."""
        return self._security.timestamp

    @property
    def _verifier(self):
        return self._security.verifier

    @property
    def _udp_split_sender(self) -> bool:
        return self._parser.udp_split_sender

    def _reset_parser(self) -> None:
        self._parser.reset()

    # --- public API -------------------------------------------------------------------------

    def read_params(self, names) -> None:
        """Ask the FC for these parameters (PARAM_REQUEST_READ, resent for the unanswered); every
        PARAM_VALUE comes out of poll() as an FcParam, and a ``params_read`` LinkEvent says when all
        were answered or which never were. ``fc_params`` holds the values."""
        self._params_reported = False
        self._send_param_requests(self._params.start(names, self.clock()))

    @property
    def fc_params(self) -> dict:
        """Watched FC parameter name -> value (the ones read so far)."""
        return dict(self._params.values)

    @property
    def fc_params_missing(self) -> set:
        """Watched parameters the FC never answered (unknown to this firmware, or the link lost them)."""
        return set(self._params.missing)

    def stream_report(self) -> dict[str, dict]:
        """Per requested stream: ``asked_hz`` (what we wanted), ``granted_hz`` (what the FC accepted
        after any retries lower; None if nothing was), ``achieved_hz`` (measured over the rate
        window), ``result`` (accepted, denied, data_stream, no_ack...)."""
        return self._rates.report()

    def subscribe(self, callback: Callable, types: tuple[str, ...] | None = None) -> None:
        """Call ``callback(msg)`` with every accepted raw pymavlink message from the autopilot, or
        only those of ``types`` (for the command protocol and tools that need messages the link
        does not decode). A subscriber to every message turns the IMU batch path off: a RAW_IMU
        taken by it has no pymavlink message."""
        self._subscribers.append((callback, None if types is None else frozenset(types)))
        if types is None or "RAW_IMU" in types:
            self._parser.split_imu = False

    def heartbeat_message(self):
        """Our HEARTBEAT (onboard controller, no autopilot, active): for this link and for any other
        port that announces the same component (extra outputs, MAV_CMD_REQUEST_MESSAGE)."""
        return self._session.heartbeat_message()

    def send(self, msg) -> bool:
        """Send an already-built pymavlink message from our identity. Never raises: a dead link
        or a message that cannot be packed is counted in stats.send_errors; returns success."""
        if self._closed:
            self.stats.send_errors += 1
            return False
        before = self.stats.messages_sent
        try:
            frame_pack.send(self.mav, msg)   # the outputs packed without pymavlink's objects, else mav.send
        except Exception as exc:  # noqa: BLE001 - packing user data (struct.error, TypeError...)
            self.stats.send_errors += 1
            self.last_error = f"send {getattr(msg, 'get_type', lambda: '?')()}: {exc}"
            return False
        return self.stats.messages_sent > before

    def feed(self, data: bytes, rx_s: float | None = None, peer: object = None,
             datagram: bool | None = None) -> list[Item]:
        """Process bytes as if they had just been received (rx_s: receive time, default the clock).

        The receive path of poll() without the transport: for replaying recorded streams (tlog)
        and for tests. ``datagram``: treat ``data`` as one UDP datagram (parser reset rules of
        poll(); None = as the link's transport). Timers (heartbeat, link timeout, rate retries)
        run in poll(), not here."""
        items: list[Item] = []
        if self._closed:
            return items
        rx = self.clock() if rx_s is None else rx_s
        self.stats.bytes_received += len(data)
        if datagram is None:
            datagram = bool(getattr(self._session.transport, "datagram", False))
        for msg in self._parser.parse_chunk(data, datagram, rx, items):
            if type(msg) is RawImuFrame:
                self._handle_imu_frame(msg, peer, rx, items)
            else:
                self._handle(msg, peer, rx, items)
        self._batch.finish(items, rx)
        items.extend(self._pending)
        self._pending = []
        return items

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._session.close()

    def poll(self, timeout_s: float = 0.0) -> list[Item]:
        """Wait up to ``timeout_s`` for data, process it and the timers, return what happened."""
        if self._closed:
            return []
        items: list[Item] = self._pending
        self._pending = []
        session = self._session
        now = self.clock()
        if not session.open_ok and now >= session.reopen_at_s:
            session.try_open(now, items)
        session.heartbeat_due(now)
        if session.open_ok:
            wait_s = timeout_s
            due = self._next_due_s()
            if due is not None:
                wait_s = min(wait_s, max(0.0, due - now))
            if items:
                wait_s = 0.0
            chunks = session.read(wait_s, items)
            if chunks:
                rx_s = self.clock()
                datagram = bool(getattr(session.transport, "datagram", False))
                for data, peer in chunks:
                    self.stats.bytes_received += len(data)
                    for msg in self._parser.parse_chunk(data, datagram, rx_s, items):
                        if type(msg) is RawImuFrame:
                            self._handle_imu_frame(msg, peer, rx_s, items)
                        else:
                            self._handle(msg, peer, rx_s, items)
                self._batch.finish(items, rx_s)
            session.track_peer()
        else:
            session.sleep_closed(timeout_s, now)
        now = self.clock()
        self._service_timers(now, items)
        items.extend(self._pending)
        self._pending = []
        return items

    # --- events and timers ------------------------------------------------------------------

    def _event(self, kind: str, detail: str, now: float, items: list | None) -> None:
        ev = LinkEvent(kind, detail, now)
        (items if items is not None else self._pending).append(ev)

    def _split_sender_found(self, rx_s: float, items: list) -> None:
        self._event("udp_split_frames", "the UDP sender splits MAVLink frames across datagrams (a serial-to-UDP "
                                        "bridge?): no parser reset per datagram on this link until it is reopened",
                    rx_s, items)

    def _next_due_s(self) -> float | None:
        due = self._session.next_due_s()   # once per wake-up: no list, no min()
        d = self._rates.next_due_s()
        if d is not None and d < due:
            due = d
        d = self._params.next_due_s()
        if d is not None and d < due:
            due = d
        return due

    def _service_timers(self, now: float, items: list) -> None:
        self.stats.set_now(now)
        if now >= self._next_signing_refresh_s:
            self._next_signing_refresh_s = now + SIGNING_REFRESH_S
            self._security.refresh_timestamp()
            self._session.read_kernel_drops()
        self._security.reports_due(now, items)
        self._session.heartbeat_due(now)
        self._rates.poll_due(now, items)
        self._send_param_requests(self._params.poll(now))
        self._report_params(now, items)
        self._rates.check_achieved_due(now, items)
        self._session.check_timeout(now, items)
        self._rates.check_silent(now, items, self._session.connected)

    def _on_fc_reboot(self, rx_s: float, items: list) -> None:
        self._rates.request(rx_s, "FC rebooted", items)

    def _send_param_requests(self, names: list[str]) -> None:
        if not self._fc.known:
            return
        for name in names:
            self.send(self.mav.param_request_read_encode(self._fc.system, self._fc.component,
                                                         name.encode("ascii"), -1))

    def _report_params(self, now: float, items: list) -> None:
        if self._params.done and not self._params_reported:
            self._params_reported = True
            vals = ", ".join(f"{n} {v:g}" for n, v in sorted(self._params.values.items()))
            miss = sorted(self._params.missing)
            self._event("params_read", vals + (f"; no answer for {', '.join(miss)}" if miss else ""), now, items)

    # --- receive path -----------------------------------------------------------------------

    def _is_vehicle_heartbeat(self, msg) -> bool:
        if msg.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or msg.type in _NOT_VEHICLE_TYPES:
            return False
        fc = self._fc
        if fc.system is not None and msg.get_srcSystem() != fc.system:
            return False
        if fc.component is not None and msg.get_srcComponent() != fc.component:
            return False
        return True

    def _learn_autopilot(self, msg, rx_s: float, items: list) -> None:
        fc = self._fc
        name = dec.autopilot_name(msg.autopilot)
        first = fc.autopilot is None
        if not first and name == fc.autopilot and fc.known:
            return
        fc.system = msg.get_srcSystem()
        fc.component = msg.get_srcComponent()
        if self.cfg.system_id is None:
            self.mav.srcSystem = fc.system
        fc.autopilot = name
        self._event("autopilot_detected", f"{name} (autopilot {msg.autopilot}, vehicle type {msg.type}) "
                                          f"system {fc.system} component {fc.component}", rx_s, items)
        self._session.mark_alive(rx_s, items)  # a link restored here is requested just below
        self._rates.request(rx_s, "autopilot detected", items)

    def _handle(self, msg, peer, rx_s: float, items: list) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            if "CRC" in str(getattr(msg, "reason", "")):
                self.stats.crc_errors += 1
            else:
                self.stats.framing_errors += 1
            return
        self.stats.messages_received += 1
        if mtype.startswith("UNKNOWN_"):
            self.stats.unknown_ids += 1
            try:
                self.stats.unknown_id_set.add(int(mtype[8:]))
            except ValueError:
                pass
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.mav.srcSystem, self.mav.srcComponent):
            self.stats.own_echoes += 1
            return
        signed = self._security.admit(msg, mtype, src, rx_s, items)
        if signed is None:
            return
        fc = self._fc
        from_fc = fc.known and src == (fc.system, fc.component)
        if mtype in COMMAND_TYPES and self._security.command_in(msg, mtype, src, signed, rx_s, items) \
                and not from_fc:
            return
        if mtype == "HEARTBEAT" and self._is_vehicle_heartbeat(msg):
            self._learn_autopilot(msg, rx_s, items)
        if not fc.known or src != (fc.system, fc.component):
            self.stats.foreign_messages += 1
            return
        self._seq.track(src, msg.get_seq())
        self._session.transport.set_peer(peer)
        if self._session.mark_alive(rx_s, items):
            self._rates.request(rx_s, "link restored", items)
        self.stats.count_message(mtype, rx_s, fc_stamp_s(msg))
        self._source_seen_s[mtype] = rx_s
        try:
            out = self._decoder.decode(mtype, msg, rx_s, items)
            if out is not None:
                self._act_on(mtype, out, rx_s, items)
        except dec.NonFiniteField:
            self.stats.count_non_finite(mtype)
        except (AttributeError, TypeError, ValueError) as exc:
            # a field of the wrong type from a buggy sender: count, never raise
            self.stats.count_non_finite(mtype)
            self.last_error = f"decode {mtype}: {exc}"
        for cb, types in self._subscribers:
            if types is not None and mtype not in types:
                continue
            try:
                cb(msg)
            except Exception as exc:  # noqa: BLE001 - a subscriber's bug must not stop the link
                self.stats.subscriber_errors += 1
                self.last_error = f"subscriber {getattr(cb, '__qualname__', cb)!s} on {mtype}: {exc!r}"

    def _handle_imu_frame(self, f: RawImuFrame, peer, rx_s: float, items: list) -> None:
        """``_handle`` for a RAW_IMU frame set apart by frame_scan: the same counters, checks and events
        in the same order (without a key, security passes every frame as unsigned; RAW_IMU is no
        command and no HEARTBEAT); a stamped sample joins the read's batch (``imu_batch``) or is
        handed on as the ImuSample pymavlink's decode gives (imu_batch.raw_imu_sample)."""
        self.stats.messages_received += 1
        src = (f.src_system, f.src_component)
        if src == (self.mav.srcSystem, self.mav.srcComponent):
            self.stats.own_echoes += 1
            return
        fc = self._fc
        if not fc.known or src != (fc.system, fc.component):
            self.stats.foreign_messages += 1
            return
        self._seq.track(src, f.seq)
        self._session.transport.set_peer(peer)
        if self._session.mark_alive(rx_s, items):
            self._rates.request(rx_s, "link restored", items)
        p = f.payload
        time_usec = f.time_usec
        self.stats.count_message("RAW_IMU", rx_s, time_usec * 1e-6 if time_usec > 0 else None)
        self._source_seen_s["RAW_IMU"] = rx_s
        t = self._decoder.stamp_raw_imu(time_usec, f.imu_id, rx_s, items)
        if t is not None:
            if self.cfg.imu_batch:
                self._batch.add(p, t, items)
            else:
                items.append(raw_imu_sample(p, t, rx_s))

    def _act_on(self, mtype: str, out, rx_s: float, items: list) -> None:
        """What the link itself does with a STATUSTEXT, a PARAM_VALUE or a COMMAND_ACK, before
        passing it on."""
        if mtype == "STATUSTEXT":
            self._rates.on_statustext(out.text)
            items.append(out)
        elif mtype == "PARAM_VALUE":
            self._params.on_value(out.name, out.value)
            items.append(out)
            self._report_params(rx_s, items)
        elif mtype == "COMMAND_ACK":
            if out.target_system in (0, self.mav.srcSystem) and out.target_component in (0, self.mav.srcComponent):
                self._rates.on_ack(out.command, out.result, rx_s, items)
                items.append(out)
