"""ArduPilot DataFlash logs (.bin) -> typed samples, with pymavlink's DFReader.

Messages (instance 0: field ``I`` == 0 where the log has it; first IMU/BARO/MAG of old logs) and
units as ArduPilot logs them (body frame FRD after AHRS_ORIENTATION, like RAW_IMU):

====== ============================================= =============================================
msg    fields                                        sample
====== ============================================= =============================================
IMU    TimeUS us, GyrX/Y/Z rad/s, AccX/Y/Z m/s^2     ImuSample (specific force: [0,0,-g] at rest)
MAG    TimeUS, MagX/Y/Z milligauss (calibrated:      ImuSample.mag_gauss (x 1e-3), held from the
       offsets applied, as RAW_IMU's)                last MAG <= the IMU time, at most
                                                     MAG_MAX_AGE_S old
BARO   TimeUS, Press Pa, Temp degC                   PressureSample (abs Pa, K)
ARSP   TimeUS, DiffPress Pa                          PressureSample.press_diff_pa, held
ATT    TimeUS, Roll, Pitch, Yaw deg (Yaw 0..360)     FcAttitude (rad; yaw (-pi, pi]; rates: the
                                                     last IMU gyro, as ATTITUDE's are)
GPS    Status >= 3: Lat, Lng deg, Alt m; GWk, GMS    the site (first 3D fix) and the date
====== ============================================= =============================================

Records come in file order; ArduPilot writes them in time order per message type. An IMU sample
whose TimeUS does not increase is passed on (the Pipeline rejects and counts it).
"""
from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path
from typing import Iterator

import numpy as np

from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from service.logreaders import (GPS_EPOCH_UNIX_S, GPS_LEAP_S, LogError, LogSite, LogSummary,
                                decimal_year_from_unix)

MAG_MAX_AGE_S = 0.5
PRESS_DIFF_MAX_AGE_S = 1.0
MGAUSS_TO_GAUSS = 1e-3
_ZERO_C_K = 273.15
_TYPES = ["IMU", "MAG", "BARO", "ARSP", "ATT"]


def _instance0(m) -> bool:
    i = getattr(m, "I", None)
    return i is None or int(i) == 0


class DataflashReader:
    """``items()`` yields ImuSample, PressureSample and FcAttitude in log order."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.summary = LogSummary(kind="dataflash", autopilot="ardupilot")
        with open(self.path, "rb") as f:
            head = f.read(3)
        if len(head) < 3 or head[0] != 0xA3 or head[1] != 0x95:
            raise LogError(f"{self.path}: not an ArduPilot DataFlash log (it does not start with the "
                           "record header 0xA3 0x95)")
        self._stderr = io.StringIO()
        try:
            from pymavlink import DFReader
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(self._stderr):
                self.df = DFReader.DFReader_binary(str(self.path), zero_time_base=True)
        except Exception as exc:  # noqa: BLE001 - DFReader raises anything on a corrupt file
            raise LogError(f"{self.path}: not a readable DataFlash log ({type(exc).__name__}: {exc})") from None
        names = {f.name for f in self.df.formats.values()}
        if "IMU" not in names:
            raise LogError(f"{self.path}: no IMU message format in this DataFlash log")
        self._site: LogSite | None = None
        self._gps_unix_s: float | None = None
        self._scanned = False

    def _scan(self) -> None:
        if self._scanned:
            return
        self._scanned = True
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(self._stderr):
            self.df.rewind()
            while True:
                m = self.df.recv_match(type="GPS")
                if m is None:
                    break
                if not _instance0(m) or int(getattr(m, "Status", 0)) < 3:
                    continue
                lat, lon = float(m.Lat), float(m.Lng)
                if (lat == 0.0 and lon == 0.0) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
                    continue
                self._site = LogSite(lat, lon, float(getattr(m, "Alt", 0.0)), f"GPS (status {int(m.Status)})")
                wk, ms = getattr(m, "GWk", 0), getattr(m, "GMS", 0)
                if wk:
                    self._gps_unix_s = GPS_EPOCH_UNIX_S + wk * 604800 + ms * 1e-3 - GPS_LEAP_S
                break
            self.df.rewind()

    def site(self) -> LogSite | None:
        self._scan()
        return self._site

    def decimal_year(self) -> float | None:
        self._scan()
        return None if self._gps_unix_s is None else decimal_year_from_unix(self._gps_unix_s)

    def progress(self) -> float:
        return min(1.0, self.df.offset / self.df.data_len) if self.df.data_len else 1.0

    def items(self) -> Iterator:
        s = self.summary
        df = self.df
        df.rewind()
        mag = None
        mag_t = -math.inf
        dp = None
        dp_t = -math.inf
        last_gyro = None
        counts = {"imu": 0, "imu_with_mag": 0, "pressure": 0, "pressure_with_diff": 0, "attitude": 0}
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(self._stderr):
            while True:
                m = df.recv_match(type=_TYPES)
                if m is None:
                    break
                if not _instance0(m):
                    continue
                name = m.get_type()
                t = m.TimeUS * 1e-6
                if name == "IMU":
                    g = np.array([m.GyrX, m.GyrY, m.GyrZ], dtype=float)
                    a = np.array([m.AccX, m.AccY, m.AccZ], dtype=float)
                    mg = mag if (mag is not None and 0.0 <= t - mag_t <= MAG_MAX_AGE_S) else None
                    counts["imu"] += 1
                    counts["imu_with_mag"] += mg is not None
                    last_gyro = g
                    yield ImuSample(t, t, g, a, mg, "IMU", 0)
                elif name == "MAG":
                    v = np.array([m.MagX, m.MagY, m.MagZ], dtype=float) * MGAUSS_TO_GAUSS
                    if np.all(np.isfinite(v)) and np.any(v != 0.0):
                        mag, mag_t = v, t
                elif name == "ARSP":
                    v = float(m.DiffPress)
                    if math.isfinite(v):
                        dp, dp_t = v, t
                elif name == "BARO":
                    press = float(m.Press)
                    if not math.isfinite(press) or press <= 0.0:
                        continue
                    diff = dp if (dp is not None and 0.0 <= t - dp_t <= PRESS_DIFF_MAX_AGE_S) else None
                    temp = float(getattr(m, "Temp", math.nan))
                    counts["pressure"] += 1
                    counts["pressure_with_diff"] += diff is not None
                    yield PressureSample(t, t, press, diff, temp + _ZERO_C_K if math.isfinite(temp) else None, "BARO")
                elif name == "ATT":
                    roll, pitch, yaw = (math.radians(float(v)) for v in (m.Roll, m.Pitch, m.Yaw))
                    w = last_gyro if last_gyro is not None else np.full(3, math.nan)
                    counts["attitude"] += 1
                    yield FcAttitude(t, t, roll, pitch, math.remainder(yaw, 2 * math.pi), w)
        s.counts = counts
        if counts["imu"] == 0:
            raise LogError(f"{self.path}: no IMU records (instance 0) in this DataFlash log")
        skipped = [ln for ln in self._stderr.getvalue().splitlines() if ln.startswith("Skipped")]
        if skipped:
            s.notes.append(f"DFReader skipped damaged bytes {len(skipped)} time(s) (corrupt log)")
