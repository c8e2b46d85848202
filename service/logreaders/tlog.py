"""MAVLink telemetry logs (.tlog) through the daemon's own receive path.

The frames go through :meth:`mavlink_io.link.MavlinkLink.feed` on a NullTransport whose clock is
the log's receive time (as ``mavlink_io.tlog.replay_tlog`` does), so the samples are exactly those
the daemon would have decoded live: same IMU source choice (RAW_IMU > HIGHRES_IMU > SCALED_IMU on
ArduPilot), same units, same FC-clock unwrap, reboot and gap events. ``time_rx_s`` is the log's
receive time (Unix seconds). Nothing is decoded a second time here except the few GNSS messages
the site comes from and the FC's EXTENDED_SYS_STATE, which the link ignores:

- the site: the first GPS_RAW_INT with fix_type >= 3 (3D); GLOBAL_POSITION_INT / HOME_POSITION
  only once such a fix was seen (without a fix they hold whatever the FC initialised them to);
- ``FcFlightState`` from the FC's EXTENDED_SYS_STATE.landed_state (1 on ground; 2 in air,
  3 taking off, 4 landing: in the air; 0 undefined: not said), armed from its last HEARTBEAT;
  its FC time is the last IMU sample's plus the receive time since (when the link decodes
  EXTENDED_SYS_STATE itself, its FcFlightState is passed on instead, as the daemon gets it).
  ``takeoff_times_s()`` comes from the same records (a log without EXTENDED_SYS_STATE has none).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

from service.logreaders import FlightStateTrack, LogError, LogSite, LogSummary, decimal_year_from_unix

_MSG_HEARTBEAT, _MSG_EXTENDED_SYS_STATE = 0, 245
_LANDED = {1: True, 2: False, 3: False, 4: False}
"""MAV_LANDED_STATE -> landed (UNDEFINED 0: not said)."""

_SITE_MESSAGES = ("GPS_RAW_INT", "GLOBAL_POSITION_INT", "HOME_POSITION")
_ROTORCRAFT = {2, 3, 4, 13, 14, 15, 29, 35}
"""MAV_TYPE quadrotor, coaxial, helicopter, hexa, octo, tricopter, dodeca, decarotor."""


class TlogLogReader:
    """``items()`` yields the link's items (samples, FcAttitude, LinkEvent, ...) in log order."""

    def __init__(self, path: Path, imu_gap_s: float = 0.5):
        from mavlink_io.tlog import TlogReader
        self.path = Path(path)
        self.imu_gap_s = imu_gap_s
        try:
            self._data = self.path.read_bytes()
        except OSError as exc:
            raise LogError(f"{self.path}: cannot read ({exc.strerror})") from None
        self._size = len(self._data)
        self._consumed = 0
        self.summary = LogSummary(kind="tlog")
        self.link = None
        self._site: LogSite | None = None
        self._first_t_s: float | None = None
        self._scanned = False
        self._takeoffs: list[float] | None = None
        # a tlog must start with a record: 8-byte timestamp + MAVLink magic within the first few
        first = next(iter(TlogReader(self._data[:4096])), None)
        if first is None:
            raise LogError(f"{self.path}: not a MAVLink telemetry log (no timestamped MAVLink frame "
                           "in its first 4 KiB)")
        self._first_t_s = first[0]  # the whole log's first record too (TlogReader stops at a cut one)

    # --- site: a pre-scan that stops at the first GNSS fix; date: the first record ---------------

    def _scan(self) -> None:
        if self._scanned:
            return
        self._scanned = True
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2
        from mavlink_io.tlog import TlogReader
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        fix_seen = [False]
        for _t_s, frame in TlogReader(self._data):
            if _msgid(frame) not in _SITE_IDS:
                continue
            try:
                msgs = parser.parse_buffer(frame) or []
            except Exception:  # noqa: BLE001 - pymavlink raises bare exceptions on bad frames
                continue
            for m in msgs:
                site = _site_from_msg(m, fix_seen)
                if site is not None:
                    self._site = site
                    return

    def site(self) -> LogSite | None:
        self._scan()
        return self._site

    def decimal_year(self) -> float | None:
        """The date of the log's first record (read when the reader was opened: a replay told its site
        never scans the log for one)."""
        return None if self._first_t_s is None else decimal_year_from_unix(self._first_t_s)

    # --- replay --------------------------------------------------------------------------------

    def progress(self) -> float:
        return min(1.0, self._consumed / self._size) if self._size else 1.0

    def items(self, imu_batches: bool = False) -> Iterator:
        """The link's items in log order. ``imu_batches``: each frame's IMU samples as the link's
        ImuBatch (a replay feeds them to the Pipeline as rows), else one ImuSample each."""
        from mavlink_io.imu_batch import ImuBatch
        from mavlink_io.link import LinkConfig, MavlinkLink
        from mavlink_io.samples import FcFlightState, FcHeartbeat, ImuSample
        from mavlink_io.tlog import TlogReader
        from mavlink_io.transport import NullTransport
        from service import link_core

        self._vehicle_type = None

        clock_s = [0.0]
        # never opened; RAW_IMU through the batch path as the daemon reads it (the same samples,
        # tests/test_mavlink_imu_batch_daemon.py), without pymavlink's message objects
        cfg = LinkConfig(url="udpin:127.0.0.1:0", imu_gap_s=self.imu_gap_s, imu_batch=True)
        # the daemon's RAW_IMU frame scan (the compiled core's when built: service/link_core.py)
        self.link = link = MavlinkLink(cfg, clock=lambda: clock_s[0], transport=NullTransport(None),
                                       frame_scan=link_core.frame_scan())
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        reader = TlogReader(self._data)
        record_bytes = 0
        track = FlightStateTrack()
        link_states = False  # the link decodes EXTENDED_SYS_STATE itself: no second copy from here
        last_imu = None
        """(time_fc_s, time_rx_s) of the last IMU sample."""
        n_states = 0
        for t_s, frame in reader:
            clock_s[0] = t_s
            record_bytes += 8 + len(frame)
            self._consumed = record_bytes + reader.skipped_bytes
            for item in link.feed(frame, t_s):
                cls = type(item)
                if cls is ImuBatch:
                    if not len(item):
                        continue
                    last_imu = item.records[-1:].tolist()[0][:2]
                    if imu_batches:
                        yield item
                    else:
                        yield from item.samples()
                    continue
                if cls is FcHeartbeat:
                    self._vehicle_type = item.vehicle_type
                    if (item.system_id, item.component_id) == (link.target_system, link.target_component):
                        track.update(self._fc_time(last_imu, t_s), armed=bool(item.armed))
                elif cls is ImuSample:
                    last_imu = (item.time_fc_s, item.time_rx_s)
                elif cls is FcFlightState:
                    link_states = True
                    if item.landed is not None:
                        track.update(self._fc_time(last_imu, t_s), landed=item.landed)
                yield item
            if not link_states and _msgid(frame) == _MSG_EXTENDED_SYS_STATE \
                    and _src(frame) == (link.target_system, link.target_component):
                landed = _landed(parser, frame)
                if landed is not None:
                    t_fc = self._fc_time(last_imu, t_s)
                    armed, landed = track.update(t_fc, landed=landed)
                    n_states += 1
                    yield FcFlightState(t_fc, t_s, armed, landed, "EXTENDED_SYS_STATE")
            yield from link.poll(0.0)  # timers: link timeout etc. (sent nowhere)
        self._consumed = self._size
        self._takeoffs = track.takeoffs_s
        s = self.summary
        if not n_states and not link_states:
            s.notes.append("no EXTENDED_SYS_STATE from the FC: the log does not say when it was on the ground")
        s.autopilot = link.fc_autopilot
        s.counts = dict(link.stats.messages_by_type)
        st = link.stats.as_dict()
        if reader.records == 0:
            raise LogError(f"{self.path}: no MAVLink records")
        if reader.skipped_bytes:
            s.notes.append(f"{reader.skipped_bytes} bytes between records could not be read (damaged log)")
        tail = self._size - record_bytes - reader.skipped_bytes
        if tail > 0:
            s.notes.append(f"the last {tail} bytes are an incomplete record (truncated log)")
        if st.get("crc_errors"):
            s.notes.append(f"{st['crc_errors']} frames with bad CRC dropped (radio link)")
        if link.fc_autopilot == "ardupilot" and self._vehicle_type in _ROTORCRAFT:
            s.notes.append("SCALED_PRESSURE.press_diff of an ArduPilot rotorcraft: older ArduPilot sent the "
                           "barometric pressure minus the ground pressure there, not a pitot pressure; it "
                           "is handed on as the link decodes it")
        if link.fc_autopilot is None:
            s.notes.append("no autopilot HEARTBEAT in the log: the link kept no vehicle's messages")

    @staticmethod
    def _fc_time(last_imu, t_rx_s: float) -> float | None:
        """FC time at receive time ``t_rx_s``: the last IMU sample's FC time plus the receive time since."""
        return None if last_imu is None else last_imu[0] + (t_rx_s - last_imu[1])

    def takeoff_times_s(self) -> list[float]:
        """The log's own take-offs (FC time s) from EXTENDED_SYS_STATE and HEARTBEAT: for scoring only.
        Replays the log through the link once if ``items()`` has not run yet."""
        if self._takeoffs is None:
            for _ in self.items():
                pass
        return [t for t in self._takeoffs if t is not None]

    def __repr__(self) -> str:
        return f"TlogLogReader({str(self.path)!r})"


_SITE_IDS = {24, 33, 242}
"""GPS_RAW_INT, GLOBAL_POSITION_INT, HOME_POSITION."""


def _msgid(frame: bytes) -> int | None:
    """The message id of a MAVLink v1 (0xFE) or v2 (0xFD) frame."""
    if len(frame) >= 6 and frame[0] == 0xFE:
        return frame[5]
    if len(frame) >= 10 and frame[0] == 0xFD:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    return None


def _src(frame: bytes) -> tuple[int, int]:
    return (frame[3], frame[4]) if frame[0] == 0xFE else (frame[5], frame[6])


def _landed(parser, frame: bytes) -> bool | None:
    try:
        msgs = parser.parse_buffer(frame) or []
    except Exception:  # noqa: BLE001 - pymavlink raises bare exceptions on bad frames
        return None
    for m in msgs:
        if m.get_type() == "EXTENDED_SYS_STATE":
            return _LANDED.get(int(m.landed_state))
    return None


def _site_from_msg(m, fix_seen: list) -> LogSite | None:
    """A site from a GNSS message only where the log says the position is valid: GPS_RAW_INT
    with a 3D fix; GLOBAL_POSITION_INT / HOME_POSITION once such a fix was seen."""
    t = m.get_type()
    if t not in _SITE_MESSAGES:
        return None
    if t == "GPS_RAW_INT" and m.fix_type >= 3:
        fix_seen[0] = True
    elif t == "GPS_RAW_INT" or not fix_seen[0]:
        return None
    lat, lon = m.lat * 1e-7, m.lon * 1e-7
    if lat == 0.0 and lon == 0.0 or not (-90 <= lat <= 90 and -180 <= lon <= 180):
        return None
    if t == "GPS_RAW_INT":
        return LogSite(lat, lon, m.alt * 1e-3, f"GPS_RAW_INT (fix type {m.fix_type})")
    return LogSite(lat, lon, m.alt * 1e-3, f"{t} (after a 3D fix)")
