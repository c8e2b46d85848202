"""MavlinkLink: one connection to the flight controller, polled from the daemon's loop.

Usage::

    link = MavlinkLink(LinkConfig(url="udpin:0.0.0.0:14550"))
    while running:
        for item in link.poll(timeout_s=0.005):
            ...  # ImuSample | PressureSample | FcAttitude | FcHeartbeat | FcEkfStatus |
                 # FcSysStatus | CommandAck | IncomingCommand | LinkEvent
    link.send(link.mav.attitude_encode(...))  # outputs, from our identity; never raises
    link.close()

What ``poll()`` does, in order, without ever raising on bad input:
1. (re)open the transport if it is down and its backoff has expired (tcp/serial/udp alike);
2. wait up to ``timeout_s`` for bytes (less if a timer is due), read everything available;
3. parse with pymavlink (MAVLink 2 out, 1 or 2 in, ardupilotmega dialect); bad CRC / framing /
   unknown ids are counted in :class:`~mavlink_io.stats.LinkStats`;
4. MAVLink 2 signing (with ``signing_key``): a signed frame is verified by
   :mod:`mavlink_io.signing` (signature first, then the timestamp; pymavlink never checks incoming
   signatures: its check lets one forged far-future frame block a stream) and dropped when it
   fails; unsigned frames are dropped by the ``require_signed`` policy;
   commands (COMMAND_LONG/INT) addressed exactly to our component, from any source, become
   IncomingCommand (broadcast ones are counted, not yielded: the FC acts on them);
   then keep only the autopilot's messages (its system id, its component; our own echoes and other
   components are counted and ignored), learn the autopilot from its HEARTBEAT;
5. decode into the typed samples of :mod:`mavlink_io.samples` (SI units, FC time via
   :mod:`mavlink_io.timebase`: unwrap, reboot, gap), rejecting non-finite values; one IMU
   stream and one pressure stream are chosen (``imu_source``);
6. timers: our HEARTBEAT (1 Hz), the SET_MESSAGE_INTERVAL round (mavlink_io.rates, fallback
   REQUEST_DATA_STREAM), link timeout, re-requests of streams that went silent.

Rates are (re)requested when the autopilot is first seen, after an FC reboot, when the link
comes back, and when a requested stream stays silent. LinkEvent kinds: autopilot_detected,
rates_requested, rates_acked, fc_reboot, time_gap, time_wrap, link_lost, link_restored,
reconnect, transport_error (a port that cannot be opened or died; retried with backoff),
signature_rejected and unsigned_command_rejected (the first, then at most one per 10 s per kind
with the count in between; they name source, message type and reason, never key or signature bytes).

Signing, outgoing: ``self.mav`` (the sending MAVLink object) signs with pymavlink's own signer;
its timestamp starts above max(signing_timestamp_floor, wall clock), is pulled up to the wall clock
about once a second and to the newest verified incoming timestamp (a board without a real-time
clock follows the FC), never goes back; ``signing_timestamp`` exposes it for persistence.

Identity: HEARTBEAT type MAV_TYPE_ONBOARD_CONTROLLER, autopilot MAV_AUTOPILOT_INVALID, component
``component_id`` (191), system id = the vehicle's (configured, or learned from the autopilot's
heartbeat; 1 until then). MAVLink 2 framing. ``time_rx_s`` is the link clock (time.monotonic by
default) when a read returned, shared by the messages of that read.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before the first pymavlink import (mavutil reads it at import)

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import decode as dec
from mavlink_io.params import ParamReader
from mavlink_io.rates import DATA_STREAM_OF, Finished, RateRequester, SendInterval, data_stream_requests
from mavlink_io.samples import (CommandAck, FcAttitude, FcEkfStatus, FcHeartbeat, FcSysStatus,
                                ImuSample, IncomingCommand, PressureSample)
from mavlink_io.signing import IFLAG_SIGNED, TIMESTAMP_MAX, SignatureVerifier, check_key, timestamp_from_unix_s
from mavlink_io.stats import LinkStats
from mavlink_io.timebase import FcTimebase, TimebaseParams
from mavlink_io.transport import UDP_RCVBUF_BYTES_DEFAULT, Transport, TransportDead, make_transport
from mavlink_io.url import Endpoint, parse_url

LINK_EVENT_KINDS = ("autopilot_detected", "rates_requested", "rates_acked", "rates_limited", "fc_reboot",
                    "time_gap", "time_wrap", "link_lost", "link_restored", "reconnect", "transport_error",
                    "signature_rejected", "unsigned_command_rejected", "udp_split_frames", "params_read",
                    "input_backlog")

REQUIRE_SIGNED = ("commands", "all", "none")
COMMAND_TYPES = ("COMMAND_LONG", "COMMAND_INT")
SECURITY_REPORT_PERIOD_S = 10.0
"""signature_rejected / unsigned_command_rejected: the first one, then at most one per this period
per kind, with the count since the last report (a flood of forged frames is not a log flood)."""
SIGNING_REFRESH_S = 1.0
"""How often the outgoing signing timestamp is pulled up to the wall clock and the transport's
kernel drop counter is read (poll's timers)."""
_MAGIC_BYTES = (0xFD, 0xFE)

DEFAULT_STREAM_RATES_HZ = {"RAW_IMU": 200.0, "SCALED_PRESSURE": 50.0, "ATTITUDE": 50.0,
                           "EKF_STATUS_REPORT": 2.0, "SYS_STATUS": 2.0, "HIGHRES_IMU": 200.0,
                           "EXTENDED_SYS_STATE": 2.0}

def _fc_stamp_s(msg) -> float | None:
    """A message's FC time stamp in seconds (time_usec, else time_boot_ms), None when it has none:
    the link's rates are measured in the sender's clock (stats.FcRateWindow)."""
    us = getattr(msg, "time_usec", None)
    if isinstance(us, int) and us > 0:
        return us * 1e-6
    ms = getattr(msg, "time_boot_ms", None)
    if isinstance(ms, int) and ms > 0:
        return ms * 1e-3
    return None


IMU_SOURCES = ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU")
_IMU_PRIORITY = {"ardupilot": ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU"),
                 None: ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU")}
_PRESSURE_PRIORITY = ("SCALED_PRESSURE", "HIGHRES_IMU")

# messages an autopilot family does not send: not requested from it
_NOT_SENT_BY = {"ardupilot": {"ESTIMATOR_STATUS"},
                "px4": {"RAW_IMU", "EKF_STATUS_REPORT"}}

_MAX_SILENT_REQUESTS = 3
RATE_CHECK_DELAY_S = 5.0
"""After a rate round, the achieved rates are measured over the link's rate window this much later."""
RATE_HONOURED_FRACTION = 0.5
"""An accepted stream measured below this fraction of its granted rate is not honoured: the legacy
REQUEST_DATA_STREAM is sent for its group."""
ARDUPILOT_RATE_PER_LOOP = 0.8
"""ArduPilot's SET_MESSAGE_INTERVAL refuses an interval below 1/(0.8 x SCHED_LOOP_RATE) (SITL,
SCHED_LOOP_RATE 50: RAW_IMU 50 Hz denied, 25 Hz accepted): the loop rate to advise."""
SCHED_LOOP_RATES_HZ = (50, 100, 200, 300, 400)
ARDUPILOT_STREAM_PARAM = {1: "RAW_SENS", 2: "EXT_STAT", 6: "POSITION", 10: "EXTRA1", 12: "EXTRA3"}
"""REQUEST_DATA_STREAM group -> the suffix of ArduPilot's stream-rate parameter (MAVn_ since 4.7,
SRn_ before)."""
_PLACEHOLDER_SYSID = 1
"""Our system id before the vehicle's is known (the ArduPilot/PX4 default SYSID)."""
_NOT_VEHICLE_TYPES = {mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_TYPE_GIMBAL,
                      mavlink2.MAV_TYPE_ADSB, mavlink2.MAV_TYPE_CAMERA}


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """Something the daemon should know about the link or the FC clock.

    kind: one of LINK_EVENT_KINDS; detail: human-readable, names the values; time_rx_s: local
    monotonic time (the link's clock)."""
    kind: str
    detail: str
    time_rx_s: float


@dataclass(frozen=True)
class LinkConfig:
    """Link settings; validated on construction (ValueError naming the field)."""
    url: str
    component_id: int = 191
    """Our MAVLink component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)."""
    system_id: int | None = None
    """The vehicle's system id; None = learn it from the autopilot's HEARTBEAT."""
    heartbeat_hz: float = 1.0
    link_timeout_s: float = 2.0
    """No message from the autopilot for this long -> link_lost."""
    imu_gap_s: float = 0.5
    """IMU samples further apart than this (FC time) -> time_gap event."""
    stream_rates_hz: dict = field(default_factory=lambda: dict(DEFAULT_STREAM_RATES_HZ))
    """Message name -> requested rate, Hz. Names the autopilot does not send are skipped (PX4: RAW_IMU,
    EKF_STATUS_REPORT; on PX4, EKF_STATUS_REPORT's rate is used for ESTIMATOR_STATUS; ArduPilot:
    ESTIMATOR_STATUS, and HIGHRES_IMU when RAW_IMU is requested)."""
    autopilot_component_id: int | None = None
    """The autopilot's component id; None = learn it from its HEARTBEAT (normally 1)."""
    imu_source: str = "auto"
    """"auto" (ArduPilot: RAW_IMU > HIGHRES_IMU > SCALED_IMU; others: HIGHRES_IMU first) or one name."""
    imu_id: int = 0
    """Which IMU instance (RAW_IMU/HIGHRES_IMU ``id``) to use."""
    reboot_jump_s: float = 1.0
    """FC time going back by more than this is a reboot; less is a reordered packet (dropped)."""
    ack_timeout_s: float = 0.5
    request_tries: int = 3
    stream_recheck_s: float = 5.0
    """A requested stream silent for link_timeout_s is re-requested, at most this often; 0 = never."""
    reconnect_backoff_s: float = 0.5
    reconnect_backoff_max_s: float = 5.0
    rate_window_s: float = 2.0
    rate_floor_hz: float | None = 1.0
    """A refused stream rate is asked again at half the rate while that is >= this (Hz); None = a
    refusal is final."""
    signing_key: bytes | None = field(default=None, repr=False, compare=False)
    """MAVLink 2 signing secret key, exactly 32 bytes; None = no signing (everything accepted as
    unsigned, nothing signed). Never shown in repr/str or in any error message."""
    sign_outgoing: bool = True
    """With a key: sign what we send."""
    require_signed: str = "commands"
    """With a key: which unsigned frames are dropped. "commands": COMMAND_LONG/COMMAND_INT addressed
    to us (our system or 0, our component or 0); "all": every unsigned frame (MAVLink 1 included);
    "none": none. A signed frame that fails verification is always dropped."""
    signing_link_id: int = 0
    """Our link id in the signature block (0..255)."""
    signing_timestamp_floor: int = 0
    """Our outgoing signing timestamps start above max(this, the wall clock), in 10 us units since
    2015-01-01 UTC (persist ``link.signing_timestamp`` and pass it back here after a restart)."""
    udp_rcvbuf_bytes: int = UDP_RCVBUF_BYTES_DEFAULT
    """UDP receive buffer asked for (SO_RCVBUF; the kernel caps it at net.core.rmem_max)."""

    def __post_init__(self) -> None:
        _check_int("udp_rcvbuf_bytes", self.udp_rcvbuf_bytes, 4096, 2**31 - 1)
        parse_url(self.url)  # ValueError naming the URL
        _check_int("component_id", self.component_id, 1, 255)
        if self.system_id is not None:
            _check_int("system_id", self.system_id, 1, 255)
        if self.autopilot_component_id is not None:
            _check_int("autopilot_component_id", self.autopilot_component_id, 1, 255)
        _check_int("imu_id", self.imu_id, 0, 255)
        _check_int("request_tries", self.request_tries, 1, 20)
        for name, lo, hi in (("heartbeat_hz", 0.0, 50.0), ("link_timeout_s", 0.0, 3600.0),
                             ("imu_gap_s", 0.0, 3600.0), ("reboot_jump_s", 0.0, 3600.0),
                             ("ack_timeout_s", 0.0, 60.0), ("reconnect_backoff_s", 0.0, 60.0),
                             ("reconnect_backoff_max_s", 0.0, 3600.0), ("rate_window_s", 0.0, 60.0)):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not lo < v <= hi:
                raise ValueError(f"LinkConfig.{name} must be in ({lo:g}, {hi:g}], got {v!r}")
        if self.rate_floor_hz is not None and (not isinstance(self.rate_floor_hz, (int, float))
                                               or not 0 < self.rate_floor_hz <= 1000):
            raise ValueError(f"LinkConfig.rate_floor_hz must be None or in (0, 1000] Hz, got {self.rate_floor_hz!r}")
        if not isinstance(self.stream_recheck_s, (int, float)) or not 0 <= self.stream_recheck_s <= 3600:
            raise ValueError(f"LinkConfig.stream_recheck_s must be in [0, 3600], got {self.stream_recheck_s!r}")
        if self.reconnect_backoff_max_s < self.reconnect_backoff_s:
            raise ValueError("LinkConfig.reconnect_backoff_max_s must be >= reconnect_backoff_s, got "
                             f"{self.reconnect_backoff_max_s} < {self.reconnect_backoff_s}")
        if self.imu_source != "auto" and self.imu_source not in IMU_SOURCES:
            raise ValueError(f"LinkConfig.imu_source must be 'auto' or one of {', '.join(IMU_SOURCES)}, "
                             f"got {self.imu_source!r}")
        if self.signing_key is not None:
            check_key(self.signing_key, "LinkConfig.signing_key")
        if not isinstance(self.sign_outgoing, bool):
            raise ValueError(f"LinkConfig.sign_outgoing must be true or false, got {self.sign_outgoing!r}")
        if self.require_signed not in REQUIRE_SIGNED:
            raise ValueError(f"LinkConfig.require_signed must be one of {', '.join(REQUIRE_SIGNED)}, "
                             f"got {self.require_signed!r}")
        _check_int("signing_link_id", self.signing_link_id, 0, 255)
        _check_int("signing_timestamp_floor", self.signing_timestamp_floor, 0, TIMESTAMP_MAX - 1)
        if not isinstance(self.stream_rates_hz, dict):
            raise ValueError(f"LinkConfig.stream_rates_hz must be a dict name -> Hz, got {type(self.stream_rates_hz).__name__}")
        for name, rate in self.stream_rates_hz.items():
            if message_id(name) is None:
                raise ValueError(f"LinkConfig.stream_rates_hz: unknown MAVLink message {name!r}")
            if not isinstance(rate, (int, float)) or not 0 < rate <= 1000:
                raise ValueError(f"LinkConfig.stream_rates_hz[{name!r}] must be in (0, 1000] Hz, got {rate!r}")


def _check_int(name: str, v, lo: int, hi: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"LinkConfig.{name} must be an integer in [{lo}, {hi}], got {v!r}")


def message_id(name: str) -> int | None:
    """MAVLink message name -> id in the ardupilotmega dialect (None if unknown)."""
    return getattr(mavlink2, f"MAVLINK_MSG_ID_{name}", None) if isinstance(name, str) else None


class _Writer:
    """The 'file' pymavlink's MAVLink object writes to: forwards to the link, never raises."""

    def __init__(self, link: "MavlinkLink"):
        self._link = link

    def write(self, buf) -> None:
        self._link._write(bytes(buf))


Item = (ImuSample | PressureSample | FcAttitude | FcHeartbeat | FcEkfStatus | FcSysStatus | CommandAck
        | IncomingCommand | LinkEvent | dec.FcStatusText | dec.FcParam)


class _ReportLimiter:
    """The first report of a kind, then at most one per ``period_s``, carrying the count of the
    ones held back since the previous report; ``due()`` flushes a held-back count once the period
    has passed even if nothing new arrives."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self._last_s: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._held_detail: dict[str, str] = {}

    def report(self, kind: str, detail: str, now: float) -> str | None:
        last = self._last_s.get(kind)
        if last is not None and now - last < self.period_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            self._held_detail[kind] = detail
            return None
        self._last_s[kind] = now
        n = self._held.pop(kind, 0)
        self._held_detail.pop(kind, None)
        return detail + (f" ({n} more since the last report)" if n else "")

    def due(self, now: float) -> list[tuple[str, str]]:
        out = []
        for kind, n in list(self._held.items()):
            if now - self._last_s[kind] >= self.period_s:
                out.append((kind, f"{n} more in {now - self._last_s[kind]:.0f} s, the last: "
                                  f"{self._held_detail.pop(kind)}"))
                del self._held[kind]
                self._last_s[kind] = now
        return out


class MavlinkLink:
    """The FC connection. Single-threaded: call ``poll()`` from one loop.

    Public state: ``fc_autopilot`` ("ardupilot" | "px4" | "other" | None), ``target_system``,
    ``target_component`` (None until learned), ``connected``, ``stats`` (LinkStats), ``mav`` (the
    pymavlink MAVLink object: encoders, our srcSystem/srcComponent, sequence numbers).
    """

    def __init__(self, cfg: LinkConfig, clock: Callable[[], float] = time.monotonic,
                 transport: Transport | None = None, wall_clock: Callable[[], float] = time.time):
        """cfg: LinkConfig; clock: monotonic seconds (injectable for tests and replay);
        transport: override the transport made from cfg.url (e.g. NullTransport for replay);
        wall_clock: Unix time, s (only for the outgoing signing timestamp).
        Never raises for an unreachable port or device (it is retried with backoff and reported
        as a "transport_error" LinkEvent); raises ValueError only for a bad configuration."""
        self.cfg = cfg
        self.clock = clock
        self.endpoint: Endpoint = parse_url(cfg.url)
        self.stats = LinkStats(rate_window_s=cfg.rate_window_s)
        self.mav = mavlink2.MAVLink(_Writer(self), srcSystem=cfg.system_id or _PLACEHOLDER_SYSID,
                                    srcComponent=cfg.component_id)
        # parsing has its own MAVLink object WITHOUT a key: pymavlink's own signature check records
        # a stream's timestamp before comparing the signature (one forged far-future frame blocks the
        # genuine stream); incoming signatures are verified by mavlink_io.signing instead
        self._rx_mav = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)
        self._rx_mav.robust_parsing = True
        self.wall_clock = wall_clock
        self._verifier: SignatureVerifier | None = None
        if cfg.signing_key is not None:
            self._verifier = SignatureVerifier(cfg.signing_key)
            sg = self.mav.signing
            sg.secret_key = bytes(cfg.signing_key)
            sg.link_id = cfg.signing_link_id
            sg.sign_outgoing = cfg.sign_outgoing
            sg.timestamp = max(cfg.signing_timestamp_floor, self._wall_timestamp()) + 1
        self._security_reports = _ReportLimiter(SECURITY_REPORT_PERIOD_S)
        self.target_system: int | None = cfg.system_id
        self.target_component: int | None = cfg.autopilot_component_id
        self.fc_autopilot: str | None = None
        self.connected = False
        self.last_error: str | None = None
        self._ever_connected = False
        self._last_fc_rx_s: float | None = None
        self._timebase = FcTimebase(TimebaseParams(reboot_jump_s=cfg.reboot_jump_s))
        self._rates = RateRequester(ack_timeout_s=cfg.ack_timeout_s, max_tries=cfg.request_tries,
                                    floor_hz=cfg.rate_floor_hz)
        self._rate_check_at_s: float | None = None
        self._data_stream_sent: set[int] = set()
        self.rate_refusal_text: str | None = None
        """The FC's last STATUSTEXT refusing a rate (ArduPilot: "... too fast. Increase SCHED_LOOP_RATE")."""
        self.rate_advice: str | None = None
        """The last rates_limited advice (which FC parameter to change), None while every rate is met."""
        self._statustext = dec.StatusTextAssembler()
        self._params = ParamReader(timeout_s=max(cfg.ack_timeout_s, 1.0), max_tries=cfg.request_tries)
        self._params_reported = False
        self._wanted: list[tuple[str, int, float]] = []
        self._last_request_s: dict[str, float] = {}
        self._silent_requests: dict[str, int] = {}
        self._seq: dict[tuple[int, int], int] = {}
        self._seq_back: dict[tuple[int, int], int] = {}
        self._source_seen_s: dict[str, float] = {}
        self._pending: list[Item] = []
        self._subscribers: list[Callable] = []
        self._closed = False
        now = clock()
        self._next_heartbeat_s = now
        self._next_signing_refresh_s = now + SIGNING_REFRESH_S
        self._transport: Transport = (transport if transport is not None
                                      else make_transport(self.endpoint, rcvbuf_bytes=cfg.udp_rcvbuf_bytes))
        self._open_ok = False
        self._udp_split_sender = False
        """A datagram transport whose sender splits frames across datagrams: no per-datagram reset."""
        self._split_seen = False
        self._kernel_drops_closed = 0
        self._kernel_drops_socket = 0
        self._ever_opened = False
        self._announce_reconnect = False
        self._had_peer = False
        self._backoff_s = cfg.reconnect_backoff_s
        self._reopen_at_s = now
        self._try_open(now)

    # --- public API -------------------------------------------------------------------------

    @property
    def local_address(self) -> tuple | None:
        """The bound address of a listening transport (udpin/tcpin; useful with port 0)."""
        return self._transport.local_address if self._open_ok else None

    @property
    def udp_rcvbuf_bytes_granted(self) -> int | None:
        """What the kernel granted for the UDP receive buffer (Linux reports twice the effective
        request); None for other transports or while closed."""
        return getattr(self._transport, "rcvbuf_bytes_granted", None) if self._open_ok else None

    @property
    def signing_timestamp(self) -> int | None:
        """Our current outgoing signing timestamp (10 us units since 2015-01-01 UTC), None without
        a key. Persist it and pass it back as ``signing_timestamp_floor`` after a restart."""
        return self.mav.signing.timestamp if self._verifier is not None else None

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
        rates = self.stats.rates_hz()
        out = {}
        for name, _mid, rate in self._wanted:
            out[name] = {"asked_hz": rate, "granted_hz": self._rates.granted_hz.get(name),
                         "achieved_hz": float(rates.get(name, 0.0)),
                         "result": self.stats.rate_results.get(name, "requested")}
        return out

    def subscribe(self, callback: Callable) -> None:
        """Call ``callback(msg)`` with every accepted raw pymavlink message from the autopilot
        (for the command protocol and tools that need messages the link does not decode)."""
        self._subscribers.append(callback)

    def send(self, msg) -> bool:
        """Send an already-built pymavlink message from our identity. Never raises: a dead link
        or a message that cannot be packed is counted in stats.send_errors; returns success."""
        if self._closed:
            self.stats.send_errors += 1
            return False
        before = self.stats.messages_sent
        try:
            self.mav.send(msg)
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
            datagram = bool(getattr(self._transport, "datagram", False))
        for msg in self._parse_chunk(data, datagram, rx, items):
            self._handle(msg, peer, rx, items)
        items.extend(self._pending)
        self._pending = []
        return items

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._bank_kernel_drops()
            self._transport.close()
            self._open_ok = False

    def poll(self, timeout_s: float = 0.0) -> list[Item]:
        """Wait up to ``timeout_s`` for data, process it and the timers, return what happened."""
        if self._closed:
            return []
        items: list[Item] = self._pending
        self._pending = []
        now = self.clock()
        if not self._open_ok and now >= self._reopen_at_s:
            self._try_open(now, items)
        if now >= self._next_heartbeat_s:
            self._send_heartbeat_due(now)
        if self._open_ok:
            wait_s = timeout_s
            due = self._next_due_s()
            if due is not None:
                wait_s = min(wait_s, max(0.0, due - now))
            if items:
                wait_s = 0.0
            try:
                self._transport.wait(wait_s)
                chunks = self._transport.read()
            except TransportDead as exc:
                self._transport_dead(str(exc), self.clock(), items)
                chunks = []
            except OSError as exc:
                self._transport_dead(f"read failed: {exc}", self.clock(), items)
                chunks = []
            if self._open_ok:
                try:
                    self._transport.flush()  # queued output of a slow stream transport
                except TransportDead as exc:
                    self._transport_dead(str(exc), self.clock(), items)
            if self._announce_reconnect and self._open_ok:
                self._check_up(self.clock(), items)
            if chunks:
                rx_s = self.clock()
                datagram = bool(getattr(self._transport, "datagram", False))
                for data, peer in chunks:
                    self.stats.bytes_received += len(data)
                    for msg in self._parse_chunk(data, datagram, rx_s, items):
                        self._handle(msg, peer, rx_s, items)
            has_peer = self._open_ok and self._transport.has_peer
            if has_peer and not self._had_peer:
                # a listener just got its peer (udpin: the FC talked; tcpin: a client connected):
                # introduce ourselves now rather than at the next 1 Hz tick
                self._next_heartbeat_s = self.clock()
            self._had_peer = has_peer
        elif timeout_s > 0:
            time.sleep(min(timeout_s, max(0.0, self._reopen_at_s - now)))
        now = self.clock()
        self._service_timers(now, items)
        items.extend(self._pending)
        self._pending = []
        return items

    # --- transport ----------------------------------------------------------------------------

    def _try_open(self, now: float, items: list | None = None) -> None:
        try:
            self._transport.open()
        except OSError as exc:
            self.stats.transport_errors += 1
            err = f"cannot open {self.endpoint.url}: {exc}"
            if err != self.last_error:
                self._event("transport_error", f"{err}; retrying every <= {self.cfg.reconnect_backoff_max_s:g} s",
                            now, items)
            self.last_error = err
            self._reopen_at_s = now + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2.0, self.cfg.reconnect_backoff_max_s)
            return
        self._open_ok = True
        self._reset_parser()
        self._udp_split_sender = False  # a new socket may have a new sender: learn again
        self._announce_reconnect = self._ever_opened
        self._ever_opened = True
        self._check_up(now, items)

    def _check_up(self, now: float, items: list | None) -> None:
        """Once the reopened transport is really up (TCP connect done): reset the backoff and
        report the reconnection."""
        if not self._transport.connected:
            return
        self._backoff_s = self.cfg.reconnect_backoff_s
        if self._announce_reconnect:
            self._announce_reconnect = False
            self.stats.reconnects += 1
            self._event("reconnect", f"{self.endpoint.url} reopened", now, items)
        self.last_error = None

    def _transport_dead(self, reason: str, now: float, items: list | None) -> None:
        self._bank_kernel_drops()
        self._transport.close()
        self._open_ok = False
        self.stats.transport_errors += 1
        err = f"{self.endpoint.url}: {reason}"
        if err != self.last_error:  # report each new failure once, not every retry
            self._event("transport_error", f"{err}; reopening with backoff (<= "
                                           f"{self.cfg.reconnect_backoff_max_s:g} s)", now, items)
        self.last_error = err
        self._reopen_at_s = now + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2.0, self.cfg.reconnect_backoff_max_s)
        if self.connected:
            self._lose_link(now, f"transport down ({reason})", items)

    def _write(self, buf: bytes) -> None:
        if not self._open_ok:
            self.stats.send_errors += 1
            return
        if not self._transport.has_peer:
            self.stats.send_no_peer += 1  # udpin/tcpin before anyone talked: nothing to send to
            return
        try:
            ok = self._transport.write(buf)
        except TransportDead as exc:
            self.stats.send_errors += 1
            self._transport_dead(str(exc), self.clock(), None)
            return
        except OSError as exc:
            self.stats.send_errors += 1
            self.last_error = f"{self.endpoint.url}: send failed: {exc}"
            return
        if ok:
            self.stats.messages_sent += 1
        else:
            self.stats.send_errors += 1

    def _reset_parser(self) -> None:
        # a new byte stream: drop any half frame of the old one (pymavlink has no reset method)
        rx = self._rx_mav
        rx.buf = bytearray()
        rx.buf_index = 0
        rx.expected_length = mavlink2.HEADER_LEN_V1 + 2
        rx.have_prefix_error = False

    def _parse_chunk(self, data: bytes, datagram: bool, rx_s: float, items: list) -> list:
        """Parse one read. On a datagram transport a datagram normally holds whole frames (ArduPilot,
        PX4, mavlink-router, pymavlink), so a partial frame left by the previous datagram is a
        damaged frame whose length byte lies: if this datagram starts with a magic byte, the parser
        is reset first, so the damaged frame cannot swallow this datagram's intact frames. A sender
        that splits frames across datagrams (a serial-to-UDP bridge: socat, ser2net) shows itself
        when a datagram that does not start with a magic byte completes a held frame that decodes
        (CRC with CRC_EXTRA): from then on this link parses UDP as a byte stream (no resets) until
        the transport is reopened."""
        held = self._rx_mav.buf_len()
        if not datagram or held == 0:
            return self._parse(data)
        if not self._udp_split_sender and data[:1] and data[0] in _MAGIC_BYTES:
            self._reset_parser()
            self.stats.datagram_resets += 1
            return self._parse(data)
        out = self._parse(data, held=held)
        if self._split_seen and not self._udp_split_sender:
            self._udp_split_sender = True
            self._event("udp_split_frames", "the UDP sender splits MAVLink frames across datagrams (a serial-to-UDP "
                                            "bridge?): no parser reset per datagram on this link until it is reopened",
                        rx_s, items)
        return out

    def _parse(self, data: bytes, held: int = 0) -> list:
        """All messages in the parser after adding ``data``. ``held``: bytes the parser held before
        (a partial frame): a frame that decodes and began in them sets ``_split_seen``."""
        out = []
        self._split_seen = False
        rx = self._rx_mav
        total = held + len(data)
        try:
            m = rx.parse_char(data)
            while m is not None:
                out.append(m)
                if held:
                    end = total - rx.buf_len()  # offset after m, counted from the held bytes' start
                    if end - len(getattr(m, "_msgbuf", b"")) < held:
                        mtype = m.get_type()
                        if mtype != "BAD_DATA" and not mtype.startswith("UNKNOWN_"):
                            self.stats.udp_split_frames_seen += 1
                            self._split_seen = True
                    else:
                        held = 0  # past the boundary
                m = rx.parse_char(b"")
        except Exception as exc:  # noqa: BLE001 - the transport never dies on bad bytes
            self.stats.parser_errors += 1
            self.last_error = f"parser: {exc}"
            self._reset_parser()
        return out

    # --- events and timers ------------------------------------------------------------------

    def _event(self, kind: str, detail: str, now: float, items: list | None) -> None:
        ev = LinkEvent(kind, detail, now)
        (items if items is not None else self._pending).append(ev)

    def _next_due_s(self) -> float | None:
        dues = [self._next_heartbeat_s]
        for d in (self._rates.next_due_s(), self._params.next_due_s(), self._rate_check_at_s):
            if d is not None:
                dues.append(d)
        if self.connected and self._last_fc_rx_s is not None:
            dues.append(self._last_fc_rx_s + self.cfg.link_timeout_s)
        return min(dues)

    def _service_timers(self, now: float, items: list) -> None:
        self.stats.set_now(now)
        if now >= self._next_signing_refresh_s:
            self._next_signing_refresh_s = now + SIGNING_REFRESH_S
            self._refresh_signing_timestamp()
            self._read_kernel_drops()
        for kind, detail in self._security_reports.due(now):
            self._event(kind, detail, now, items)
        if now >= self._next_heartbeat_s:
            self._send_heartbeat_due(now)
        self._run_rate_actions(self._rates.poll(now), now, items)
        self._send_param_requests(self._params.poll(now))
        self._report_params(now, items)
        if self._rate_check_at_s is not None and now >= self._rate_check_at_s:
            self._rate_check_at_s = None
            self._check_achieved_rates(now, items)
        if self.connected and now - self._last_fc_rx_s > self.cfg.link_timeout_s:
            self._lose_link(now, f"no message from the autopilot for {now - self._last_fc_rx_s:.2f} s "
                                 f"(> {self.cfg.link_timeout_s:g} s)", items)
        self._check_silent_streams(now, items)

    def _send_heartbeat_due(self, now: float) -> None:
        self._send_heartbeat()
        period = 1.0 / self.cfg.heartbeat_hz
        self._next_heartbeat_s += period
        if self._next_heartbeat_s <= now:
            self._next_heartbeat_s = now + period

    def heartbeat_message(self):
        """Our HEARTBEAT (onboard controller, no autopilot, active): for this link and for any other
        port that announces the same component (extra outputs, MAV_CMD_REQUEST_MESSAGE)."""
        return self.mav.heartbeat_encode(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID,
                                         0, 0, mavlink2.MAV_STATE_ACTIVE)

    def _send_heartbeat(self) -> None:
        if not self._open_ok:
            return
        before = self.stats.messages_sent
        self.send(self.heartbeat_message())
        if self.stats.messages_sent > before:
            self.stats.heartbeats_sent += 1

    def _lose_link(self, now: float, why: str, items: list) -> None:
        self.connected = False
        self.stats.link_losses += 1
        self._event("link_lost", why, now, items)

    # --- rate requests ----------------------------------------------------------------------

    def _wanted_rates(self) -> list[tuple[str, int, float]]:
        rates = dict(self.cfg.stream_rates_hz)
        if self.fc_autopilot == "px4" and "EKF_STATUS_REPORT" in rates and "ESTIMATOR_STATUS" not in rates:
            rates["ESTIMATOR_STATUS"] = rates["EKF_STATUS_REPORT"]
        skip = set(_NOT_SENT_BY.get(self.fc_autopilot, set()))
        if self.cfg.imu_source != "auto":
            skip |= set(IMU_SOURCES) - {self.cfg.imu_source}  # only the IMU stream we use
        elif self.fc_autopilot == "ardupilot" and "RAW_IMU" in rates:
            skip.add("HIGHRES_IMU")  # one IMU stream is enough: RAW_IMU is ArduPilot's native one
        return [(n, message_id(n), float(r)) for n, r in rates.items() if n not in skip]

    def _request_rates(self, now: float, reason: str, items: list,
                       only: list[tuple[str, int, float]] | None = None) -> None:
        if self.target_system is None or self.target_component is None:
            return
        if only is None:
            self._wanted = self._wanted_rates()
            self._silent_requests.clear()
            self._data_stream_sent.clear()
            self._rate_check_at_s = None
        batch = self._wanted if only is None else only
        if not batch:
            return
        for n, _i, _r in batch:
            self._last_request_s[n] = now
        listing = ", ".join(f"{n} {r:g} Hz" for n, _i, r in batch)
        self._event("rates_requested", f"{reason}: SET_MESSAGE_INTERVAL {listing}", now, items)
        self._run_rate_actions(self._rates.start(batch, now), now, items)

    def _run_rate_actions(self, actions: list, now: float, items: list) -> None:
        for act in actions:
            if isinstance(act, SendInterval):
                msg = self.mav.command_long_encode(self.target_system, self.target_component,
                                                   mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, act.confirmation,
                                                   float(act.msg_id), float(act.interval_us), 0, 0, 0, 0, 0)
                self.send(msg)
                self.stats.rate_requests_sent += 1
            elif isinstance(act, Finished):
                self._rates_finished(act.results, now, items)

    def _rates_finished(self, results: dict, now: float, items: list) -> None:
        self.stats.rate_results.update(results)
        if self._rate_check_at_s is None:  # a re-request of a silent stream does not postpone it
            self._rate_check_at_s = now + max(RATE_CHECK_DELAY_S, self.cfg.rate_window_s)
        summary = ", ".join(f"{n}={r}" + (f" at {self._rates.granted_hz[n]:g} Hz" if n in self._rates.granted_hz
                                          and self._rates.granted_hz[n] != self._rates.asked_hz.get(n) else "")
                            for n, r in results.items())
        if any(r == "accepted" for r in results.values()):
            self._event("rates_acked", summary, now, items)
            return
        # nothing accepted (no ACK at all, or SET_MESSAGE_INTERVAL unsupported): legacy streams
        batch = [w for w in self._wanted if w[0] in results]
        streams = data_stream_requests(batch)
        for sid, hz in streams.items():
            self.send(self.mav.request_data_stream_encode(self.target_system, self.target_component, sid, hz, 1))
            self.stats.rate_requests_sent += 1
        for n, _i, _r in batch:
            if n in DATA_STREAM_OF and results.get(n) in ("no_ack", "unsupported", "not_tried"):
                self.stats.rate_results[n] = "data_stream"
        self._event("rates_requested", f"SET_MESSAGE_INTERVAL not accepted ({summary}); fallback "
                                       "REQUEST_DATA_STREAM " + ", ".join(f"stream {s} at {hz} Hz"
                                                                         for s, hz in streams.items()),
                    now, items)

    def _send_param_requests(self, names: list[str]) -> None:
        if self.target_system is None or self.target_component is None:
            return
        for name in names:
            self.send(self.mav.param_request_read_encode(self.target_system, self.target_component,
                                                         name.encode("ascii"), -1))

    def _report_params(self, now: float, items: list) -> None:
        if self._params.done and not self._params_reported:
            self._params_reported = True
            vals = ", ".join(f"{n} {v:g}" for n, v in sorted(self._params.values.items()))
            miss = sorted(self._params.missing)
            self._event("params_read", vals + (f"; no answer for {', '.join(miss)}" if miss else ""), now, items)

    def _check_achieved_rates(self, now: float, items: list) -> None:
        """After a rate round: what each stream gives, measured. A stream the FC accepted but does not
        deliver at half its granted rate gets the legacy REQUEST_DATA_STREAM for its group (once per
        round); every shortfall is told in one ``rates_limited`` event that names the FC parameter to
        change (SCHED_LOOP_RATE for a refused rate, the stream-rate parameter for one not honoured)."""
        report = self.stream_report()
        short, groups = [], {}
        for name, r in report.items():
            granted, asked, got = r["granted_hz"], r["asked_hz"], r["achieved_hz"]
            expected = granted if granted is not None else asked
            honoured = got >= RATE_HONOURED_FRACTION * expected
            if granted is not None and granted >= asked and honoured:
                continue
            sid = DATA_STREAM_OF.get(name)
            if not honoured and sid is not None and sid not in self._data_stream_sent:
                groups[sid] = max(groups.get(sid, 0), max(1, int(round(expected))))
            short.append(f"{name} asked {asked:g} Hz, " + (f"granted {granted:g} Hz, " if granted is not None
                                                           else f"{r['result']}, ") + f"measured {got:.1f} Hz")
        for sid, hz in groups.items():
            self._data_stream_sent.add(sid)
            self.send(self.mav.request_data_stream_encode(self.target_system, self.target_component, sid, hz, 1))
            self.stats.rate_requests_sent += 1
        if not short:
            self.rate_advice = None
            return
        self.rate_advice = self._rate_advice(report, groups)
        self._event("rates_limited", "; ".join(short) + (f" (FC said: \"{self.rate_refusal_text}\")"
                                                         if self.rate_refusal_text else "") + ". " + self.rate_advice,
                    now, items)

    def _rate_advice(self, report: dict, groups: dict) -> str:
        """Which FC parameter to change, in one sentence."""
        refused = [n for n, r in report.items() if (r["granted_hz"] is not None and r["granted_hz"] < r["asked_hz"])
                   or r["result"] in ("denied", "failed")]
        parts = []
        if refused and self.fc_autopilot == "ardupilot":
            need = max(report[n]["asked_hz"] for n in refused) / ARDUPILOT_RATE_PER_LOOP
            loop = next((r for r in SCHED_LOOP_RATES_HZ if r >= need), SCHED_LOOP_RATES_HZ[-1])
            parts.append(f"set SCHED_LOOP_RATE >= {loop} on the FC (it refuses a stream faster than about "
                         f"{ARDUPILOT_RATE_PER_LOOP:g} x its loop rate), or lower [mavlink] imu_rate_hz/"
                         "attitude_rate_hz/pressure_rate_hz to what it grants")
        elif refused:
            parts.append("the FC refused the rate: raise its stream limits or lower the [mavlink] rates")
        if groups and self.fc_autopilot == "ardupilot":
            names = sorted({ARDUPILOT_STREAM_PARAM[s] for s in groups if s in ARDUPILOT_STREAM_PARAM})
            parts.append("streams not delivered at the accepted rate: REQUEST_DATA_STREAM sent; set the port's "
                         + ", ".join(f"MAVn_{p}" for p in names) + " (SRn_ before ArduPilot 4.7) to the rate")
        elif groups:
            parts.append("streams not delivered at the accepted rate: REQUEST_DATA_STREAM sent")
        return "; ".join(parts) if parts else "the FC gives less than asked"

    def _check_silent_streams(self, now: float, items: list) -> None:
        """Re-request a requested stream that has gone silent (the FC dropped our interval, e.g.
        after a reboot we did not see). At most every stream_recheck_s, and at most
        _MAX_SILENT_REQUESTS times in a row for a stream that never comes."""
        if (self.cfg.stream_recheck_s <= 0 or not self.connected or self._rates.active
                or not self._wanted):
            return
        silent = []
        for name, msg_id, rate in self._wanted:
            if self.stats.rate_results.get(name) in ("denied", "unsupported", "failed"):
                continue
            if now - self._last_request_s.get(name, now) < max(self.cfg.stream_recheck_s, self.cfg.link_timeout_s):
                continue
            seen_s = self._source_seen_s.get(name)
            if seen_s is not None and now - seen_s <= self.cfg.link_timeout_s:
                self._silent_requests.pop(name, None)
                continue
            if self._silent_requests.get(name, 0) >= _MAX_SILENT_REQUESTS:
                continue
            self._silent_requests[name] = self._silent_requests.get(name, 0) + 1
            silent.append((name, msg_id, rate))
        if silent:
            self._request_rates(now, f"stream(s) silent: {', '.join(n for n, _i, _r in silent)}", items,
                                only=silent)

    # --- receive path -----------------------------------------------------------------------

    def _is_vehicle_heartbeat(self, msg) -> bool:
        if msg.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or msg.type in _NOT_VEHICLE_TYPES:
            return False
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if self.target_system is not None and src_sys != self.target_system:
            return False
        if self.target_component is not None and src_comp != self.target_component:
            return False
        return True

    def _learn_autopilot(self, msg, rx_s: float, items: list) -> None:
        name = dec.autopilot_name(msg.autopilot)
        first = self.fc_autopilot is None
        if not first and name == self.fc_autopilot and self.target_system is not None \
                and self.target_component is not None:
            return
        self.target_system = msg.get_srcSystem()
        self.target_component = msg.get_srcComponent()
        if self.cfg.system_id is None:
            self.mav.srcSystem = self.target_system
        self.fc_autopilot = name
        self._event("autopilot_detected", f"{name} (autopilot {msg.autopilot}, vehicle type {msg.type}) "
                                          f"system {self.target_system} component {self.target_component}",
                    rx_s, items)
        self._mark_alive(rx_s, items, restored_requests=False)
        self._request_rates(rx_s, "autopilot detected", items)

    def _mark_alive(self, rx_s: float, items: list, restored_requests: bool = True) -> None:
        self._last_fc_rx_s = rx_s
        if self.connected:
            return
        self.connected = True
        if self._ever_connected:
            self._event("link_restored", "autopilot messages are back", rx_s, items)
            if restored_requests:
                self._request_rates(rx_s, "link restored", items)
        self._ever_connected = True

    def _track_seq(self, src: tuple[int, int], seq: int) -> None:
        """Lost packets from MAVLink sequence gaps: a jump of 1..127 counts as lost packets; a step
        back is a duplicate or a reordered packet (not lost). Three steps back in a row mean the
        sender restarted its counter (FC reboot): resynchronise."""
        last = self._seq.get(src)
        if last is not None:
            diff = (seq - last - 1) % 256
            if diff >= 128:
                self._seq_back[src] = self._seq_back.get(src, 0) + 1
                if self._seq_back[src] < 3:
                    if diff == 255:
                        self.stats.seq_duplicates += 1
                    else:
                        self.stats.seq_reordered += 1
                    return
                diff = 0
            self.stats.seq_lost += diff
        self._seq_back[src] = 0
        self._seq[src] = seq

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
        signed = self._signing_policy(msg, mtype, src, rx_s, items)
        if signed is None:
            return
        from_fc = self.target_system is not None and self.target_component is not None \
            and src == (self.target_system, self.target_component)
        if mtype in COMMAND_TYPES and self._command_in(msg, mtype, src, signed, rx_s, items) and not from_fc:
            return
        if mtype == "HEARTBEAT" and self._is_vehicle_heartbeat(msg):
            self._learn_autopilot(msg, rx_s, items)
        if self.target_system is None or self.target_component is None \
                or src != (self.target_system, self.target_component):
            self.stats.foreign_messages += 1
            return
        self._track_seq(src, msg.get_seq())
        self._transport.set_peer(peer)
        self._mark_alive(rx_s, items)
        self.stats.count_message(mtype, rx_s, _fc_stamp_s(msg))
        self._source_seen_s[mtype] = rx_s
        try:
            self._decode(mtype, msg, rx_s, items)
        except dec.NonFiniteField:
            self.stats.count_non_finite(mtype)
        except (AttributeError, TypeError, ValueError) as exc:
            # a field of the wrong type from a buggy sender: count, never raise
            self.stats.count_non_finite(mtype)
            self.last_error = f"decode {mtype}: {exc}"
        for cb in self._subscribers:
            try:
                cb(msg)
            except Exception as exc:  # noqa: BLE001 - a subscriber's bug must not stop the link
                self.stats.subscriber_errors += 1
                self.last_error = f"subscriber {getattr(cb, '__qualname__', cb)!s} on {mtype}: {exc!r}"

    # --- signing and incoming commands ---------------------------------------------------------

    def _wall_timestamp(self) -> int:
        try:
            return timestamp_from_unix_s(float(self.wall_clock()))
        except (TypeError, ValueError, OverflowError):  # a broken wall clock: keep our own count
            return 0

    def _read_kernel_drops(self) -> None:
        """stats.kernel_rx_drops from the transport (UDP: datagrams the kernel dropped, our receive
        buffer full), summed over reopened sockets (the transport's count is per socket); None
        while the transport cannot tell."""
        fn = getattr(self._transport, "kernel_rx_drops", None)
        if fn is None or not self._open_ok:
            return
        try:
            n = fn()
        except OSError:
            return
        if n is not None:
            self._kernel_drops_socket = int(n)
            self.stats.kernel_rx_drops = self._kernel_drops_closed + self._kernel_drops_socket

    def _bank_kernel_drops(self) -> None:
        """The socket is about to close: keep its last count in the total."""
        self._read_kernel_drops()
        self._kernel_drops_closed += self._kernel_drops_socket
        self._kernel_drops_socket = 0

    def _refresh_signing_timestamp(self) -> None:
        """Outgoing timestamp = max(current, wall clock): never back (pymavlink adds 1 per frame)."""
        if self._verifier is not None:
            sg = self.mav.signing
            sg.timestamp = min(max(sg.timestamp, self._wall_timestamp()), TIMESTAMP_MAX)

    def _to_us(self, msg, mtype: str) -> bool:
        """A command whose target is us: our system or broadcast, our component or broadcast."""
        return (mtype in COMMAND_TYPES and msg.target_system in (0, self.mav.srcSystem)
                and msg.target_component in (0, self.cfg.component_id))

    def _security_event(self, kind: str, detail: str, now: float, items: list) -> None:
        detail = self._security_reports.report(kind, detail, now)
        if detail is not None:
            self._event(kind, detail, now, items)

    def _signing_policy(self, msg, mtype: str, src: tuple[int, int], rx_s: float, items: list) -> bool | None:
        """None: drop the frame (counted, reported); else whether it carried a signature that
        verified with our key. Without a key everything passes as unsigned (False)."""
        if self._verifier is None:
            return False
        header = getattr(msg, "_header", None)
        frame = getattr(msg, "_msgbuf", None)
        if header is not None and frame is not None and header.incompat_flags & IFLAG_SIGNED:
            v = self._verifier.verify(frame, src[0], src[1], self.mav.signing.timestamp)
            if v.ok:
                self.stats.signed_accepted += 1
                # the spec's clock rule: our timestamp is at least the newest valid one seen (a
                # companion without a real-time clock follows the FC's)
                sg = self.mav.signing
                sg.timestamp = max(sg.timestamp, v.timestamp)
                return True
            if v.replay:
                self.stats.signature_replay += 1
                why = ("timestamp not after the last one of its stream (replay)" if v.reason == "old_timestamp"
                       else "new stream more than 60 s behind our timestamp (replay)")
            else:
                self.stats.signature_bad += 1
                why = "signature does not match our key" if v.reason == "bad_signature" else "malformed signature block"
            self._security_event("signature_rejected", f"{mtype} from system {src[0]} component {src[1]} "
                                                       f"(link id {v.link_id}) dropped: {why}", rx_s, items)
            return None
        policy = self.cfg.require_signed
        is_cmd_to_us = self._to_us(msg, mtype)
        if policy == "all" or (policy == "commands" and is_cmd_to_us):
            self.stats.unsigned_rejected += 1
            if is_cmd_to_us:
                self.stats.unsigned_commands_rejected += 1
                self._security_event("unsigned_command_rejected",
                                     f"unsigned {mtype} (command {msg.command}) from system {src[0]} "
                                     f"component {src[1]} to {msg.target_system}/{msg.target_component} "
                                     f"dropped: require_signed={policy}", rx_s, items)
            return None
        return False

    def _command_in(self, msg, mtype: str, src: tuple[int, int], signed: bool, rx_s: float,
                    items: list) -> bool:
        """Yield an IncomingCommand for a command addressed exactly to our component; count a
        broadcast one (the FC acts on it; we must not act twice). True when it was for us."""
        if not self._to_us(msg, mtype):
            return False
        if msg.target_system != self.mav.srcSystem or msg.target_component != self.cfg.component_id:
            self.stats.commands_broadcast_ignored += 1
            return True
        if mtype == "COMMAND_LONG":
            params = tuple(float(getattr(msg, f"param{i}")) for i in range(1, 8))
            frame, confirmation, is_int = None, int(msg.confirmation), False
        else:
            params = (*(float(getattr(msg, f"param{i}")) for i in range(1, 5)), int(msg.x), int(msg.y), float(msg.z))
            frame, confirmation, is_int = int(msg.frame), 0, True
        self.stats.commands_received += 1
        items.append(IncomingCommand(time_rx_s=rx_s, command=int(msg.command), params=params, is_int=is_int,
                                     frame=frame, confirmation=confirmation, source_system=src[0],
                                     source_component=src[1], target_system=int(msg.target_system),
                                     target_component=int(msg.target_component), signed=signed))
        return True

    def _fc_time(self, stream: str, mtype: str, msg, rx_s: float, items: list,
                 gap_s: float | None = None) -> float | None:
        fname, unit = dec.TIME_FIELD[mtype]
        t, events = self._timebase.feed(stream, int(getattr(msg, fname)), unit, rx_s, gap_s)
        for ev in events:
            self._event(ev.kind, ev.detail, rx_s, items)
            if ev.kind == "fc_reboot":
                self.stats.fc_reboots += 1
                self._request_rates(rx_s, "FC rebooted", items)
            elif ev.kind == "time_gap":
                self.stats.time_gaps += 1
            elif ev.kind == "time_wrap":
                self.stats.time_wraps += 1
            elif ev.kind == "input_backlog":  # FC time lags, its clock did not restart: no reboot
                self.stats.input_backlogs += 1
        if t is None:
            self.stats.stale_time_drops += 1
        return t

    def _preferred(self, source: str, priority: tuple[str, ...], rx_s: float) -> bool:
        """True if no higher-priority source of the same kind was seen within link_timeout_s."""
        for other in priority:
            if other == source:
                return True
            seen = self._source_seen_s.get(other)
            if seen is not None and rx_s - seen <= self.cfg.link_timeout_s:
                return False
        return True

    def _imu_wanted(self, source: str, imu_id: int, rx_s: float) -> bool:
        if imu_id != self.cfg.imu_id:
            return False
        if self.cfg.imu_source != "auto":
            return source == self.cfg.imu_source
        prio = _IMU_PRIORITY["ardupilot" if self.fc_autopilot == "ardupilot" else None]
        return self._preferred(source, prio, rx_s)

    def _decode(self, mtype: str, msg, rx_s: float, items: list) -> None:
        nan = float("nan")
        if mtype in ("RAW_IMU", "SCALED_IMU"):
            fn = dec.decode_raw_imu if mtype == "RAW_IMU" else dec.decode_scaled_imu
            imu = fn(msg, nan, rx_s)
            if self._imu_wanted(mtype, imu.imu_id, rx_s):
                self._emit_imu(imu, mtype, msg, rx_s, items)
        elif mtype == "HIGHRES_IMU":
            opt = dec.OptionalFieldCounter()
            imu, press = dec.decode_highres_imu(msg, nan, rx_s, opt)
            self.stats.non_finite_optional += opt.count
            if self._imu_wanted(mtype, imu.imu_id, rx_s):
                self._emit_imu(imu, mtype, msg, rx_s, items)
            if press is not None and imu.imu_id == self.cfg.imu_id \
                    and self._preferred("HIGHRES_IMU", _PRESSURE_PRIORITY, rx_s):
                t = self._fc_time("PRESSURE", mtype, msg, rx_s, items)
                if t is not None:
                    items.append(dataclasses.replace(press, time_fc_s=t))
        elif mtype == "SCALED_PRESSURE":
            opt = dec.OptionalFieldCounter()
            press = dec.decode_scaled_pressure(msg, nan, rx_s, opt)
            self.stats.non_finite_optional += opt.count
            t = self._fc_time("PRESSURE", mtype, msg, rx_s, items)
            if t is not None:
                items.append(dataclasses.replace(press, time_fc_s=t))
        elif mtype == "ATTITUDE":
            att = dec.decode_attitude(msg, nan, rx_s)
            t = self._fc_time("ATTITUDE", mtype, msg, rx_s, items)
            if t is not None:
                items.append(dataclasses.replace(att, time_fc_s=t))
        elif mtype == "HEARTBEAT":
            items.append(dec.decode_heartbeat(msg, rx_s))
        elif mtype == "EXTENDED_SYS_STATE":  # the FC's land detector: phase evidence
            items.append(dec.decode_extended_sys_state(msg, rx_s))
        elif mtype == "EKF_STATUS_REPORT":
            opt = dec.OptionalFieldCounter()
            items.append(dec.decode_ekf_status_report(msg, rx_s, opt))
            self.stats.non_finite_optional += opt.count
        elif mtype == "ESTIMATOR_STATUS":
            opt = dec.OptionalFieldCounter()
            st = dec.decode_estimator_status(msg, nan, rx_s, opt)
            self.stats.non_finite_optional += opt.count
            t = self._fc_time("ESTIMATOR_STATUS", mtype, msg, rx_s, items)
            if t is not None:
                items.append(dataclasses.replace(st, time_fc_s=t))
        elif mtype == "SYS_STATUS":
            items.append(dec.decode_sys_status(msg, rx_s))
        elif mtype == "STATUSTEXT":
            st = dec.decode_statustext(msg, self._statustext, rx_s)
            if st is not None:
                if "too fast" in st.text and "SCHED_LOOP_RATE" in st.text:
                    self.rate_refusal_text = st.text
                items.append(st)
        elif mtype == "PARAM_VALUE":
            prm = dec.decode_param_value(msg, rx_s, bytewise=self.fc_autopilot == "px4")
            self._params.on_value(prm.name, prm.value)
            items.append(prm)
            self._report_params(rx_s, items)
        elif mtype == "COMMAND_ACK":
            ack = dec.decode_command_ack(msg, rx_s)
            if ack.target_system in (0, self.mav.srcSystem) and ack.target_component in (0, self.mav.srcComponent):
                self._run_rate_actions(self._rates.on_ack(ack.command, ack.result, rx_s), rx_s, items)
                items.append(ack)

    def _emit_imu(self, imu: ImuSample, mtype: str, msg, rx_s: float, items: list) -> None:
        t = self._fc_time("IMU", mtype, msg, rx_s, items, gap_s=self.cfg.imu_gap_s)
        if t is not None:
            items.append(dataclasses.replace(imu, time_fc_s=t))
