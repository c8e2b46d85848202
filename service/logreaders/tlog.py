"""MAVLink telemetry logs (.tlog) through the daemon's own receive path.

The frames go through :meth:`mavlink_io.link.MavlinkLink.feed` on a NullTransport whose clock is
the log's receive time (as ``mavlink_io.tlog.replay_tlog`` does), so the samples are exactly those
the daemon would have decoded live: same IMU source choice (RAW_IMU > HIGHRES_IMU > SCALED_IMU on
ArduPilot), same units, same FC-clock unwrap, reboot and gap events. ``time_rx_s`` is the log's
receive time (Unix seconds). Nothing is decoded a second time here except the few GNSS messages
the site comes from (GPS_RAW_INT / GLOBAL_POSITION_INT / HOME_POSITION, which the link ignores).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

from service.logreaders import LogError, LogSite, LogSummary, decimal_year_from_unix

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
        # a tlog must start with a record: 8-byte timestamp + MAVLink magic within the first few
        first = next(iter(TlogReader(self._data[:4096])), None)
        if first is None:
            raise LogError(f"{self.path}: not a MAVLink telemetry log (no timestamped MAVLink frame "
                           "in its first 4 KiB)")

    # --- site and date: a pre-scan that stops at the first GNSS fix -----------------------------

    def _scan(self) -> None:
        if self._scanned:
            return
        self._scanned = True
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2
        from mavlink_io.tlog import TlogReader
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        for t_s, frame in TlogReader(self._data):
            if self._first_t_s is None:
                self._first_t_s = t_s
            try:
                msgs = parser.parse_buffer(frame) or []
            except Exception:  # noqa: BLE001 - pymavlink raises bare exceptions on bad frames
                continue
            for m in msgs:
                site = _site_from_msg(m)
                if site is not None:
                    self._site = site
                    return

    def site(self) -> LogSite | None:
        self._scan()
        return self._site

    def decimal_year(self) -> float | None:
        self._scan()
        return None if self._first_t_s is None else decimal_year_from_unix(self._first_t_s)

    # --- replay --------------------------------------------------------------------------------

    def progress(self) -> float:
        return min(1.0, self._consumed / self._size) if self._size else 1.0

    def items(self) -> Iterator:
        from mavlink_io.link import LinkConfig, MavlinkLink
        from mavlink_io.samples import FcHeartbeat
        from mavlink_io.tlog import TlogReader
        from mavlink_io.transport import NullTransport

        self._vehicle_type = None

        clock_s = [0.0]
        cfg = LinkConfig(url="udpin:127.0.0.1:0", imu_gap_s=self.imu_gap_s)  # never opened
        self.link = link = MavlinkLink(cfg, clock=lambda: clock_s[0], transport=NullTransport(None))
        reader = TlogReader(self._data)
        record_bytes = 0
        for t_s, frame in reader:
            clock_s[0] = t_s
            record_bytes += 8 + len(frame)
            self._consumed = record_bytes + reader.skipped_bytes
            for item in link.feed(frame, t_s):
                if type(item) is FcHeartbeat:
                    self._vehicle_type = item.vehicle_type
                yield item
            yield from link.poll(0.0)  # timers: link timeout etc. (sent nowhere)
        self._consumed = self._size
        s = self.summary
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

    def __repr__(self) -> str:
        return f"TlogLogReader({str(self.path)!r})"


def _site_from_msg(m) -> LogSite | None:
    t = m.get_type()
    if t not in _SITE_MESSAGES:
        return None
    lat, lon = m.lat * 1e-7, m.lon * 1e-7
    if lat == 0.0 and lon == 0.0 or not (-90 <= lat <= 90 and -180 <= lon <= 180):
        return None
    if t == "GPS_RAW_INT":
        if m.fix_type < 3:
            return None
        return LogSite(lat, lon, m.alt * 1e-3, f"GPS_RAW_INT (fix type {m.fix_type})")
    return LogSite(lat, lon, m.alt * 1e-3, t)
