"""ArduPilot DataFlash logs (.bin) -> typed samples, across ArduPilot generations.

Records are walked by service.logreaders.dataflash_format (tolerant of damage and truncation).
One sensor of each kind is used, the same for the whole log, and the summary says which:

- the first instance: field ``I`` == the lowest instance logged where the message has ``I``
  (ArduPilot >= 3.7 for MAG/BARO/ARSP, 4.1 for IMU), else the unnumbered message of old logs
  (IMU, not IMU2/IMU3; MAG, not MAG2; BARO, not BAR2; ARSP, not ASP2);
- time: ``TimeUS`` (us), or ``TimeMS`` (ms) in old logs, on the FC's boot clock.

====== ============================================= =============================================
msg    fields                                        sample
====== ============================================= =============================================
IMU    GyrX/Y/Z rad/s, AccX/Y/Z m/s^2                ImuSample (specific force: [0,0,-g] at rest)
MAG    MagX/Y/Z milligauss (calibrated: offsets      ImuSample.mag_gauss (x 1e-3), held from the
       applied, as RAW_IMU's)                        last MAG <= the IMU time, at most
                                                     MAG_MAX_AGE_S old
BARO   Press Pa, Temp degC                           PressureSample (abs Pa, K)
ARSP   DiffPress Pa                                  PressureSample.press_diff_pa, held
ATT    Roll, Pitch, Yaw deg (Yaw 0..360)             FcAttitude (rad; yaw (-pi, pi]; rates: the
                                                     last IMU gyro, as ATTITUDE's are)
EV     Id: 10 armed, 11 disarmed, 18 land complete,  FcFlightState (armed, landed) and the log's
       28 not landed (ArduPilot's LogEvent ids)      take-off times
ARM    ArmState (1 armed, 0 disarmed)                FcFlightState (armed)
STAT   isFlying, Armed (ArduPlane)                   FcFlightState (landed = not isFlying, armed)
GPS    Status >= 3 (3D fix): Lat, Lng deg, Alt m;    the site (first 3D fix) and the date
       GWk/GMS (old: Week/TimeMS) GPS week and ms
XKF4   SS: the EKF's solution status (nav_filter_    FcEkfStatus (attitude_ok = SS bit 0, the
(NKF4) status bits); SV, SP, SH, SM test ratios;     attitude bit; horiz_pos_ok = bit 4); what
       C: the core (EKF3; EKF2's NKF4 is core 0)     EKF_STATUS_REPORT says on a live link
====== ============================================= =============================================

The estimator status is the EKF that ArduPilot's AHRS used (``AHRS_EKF_TYPE`` 3: XKF4, 2: NKF4;
unset: the one logged), its lowest core. A log without one (``estimator_status`` None, said in the
summary) has its FC attitude judged without a status from the start (service/replay.py), as a live
FC that never sends one is after estimators/reference_health's ``status_wait_s``.

Records come in file order; ArduPilot writes them in time order per message type. An IMU sample
whose time does not increase is passed on (the Pipeline rejects and counts it).

EV and ARM are written on a change only, so a log that starts in flight (logging started or
rotated in the air) says nothing until the vehicle lands. A change implies the state before it:
when the log's first armed-saying EV/ARM record is a disarm, the FC was armed from the log's
start; when its first landed-saying EV is a landing (land complete) with no take-off before it,
the FC was in the air. That state is given as one FcFlightState at the first sample (and said in
the summary's notes), as the FC's HEARTBEAT gives it on a live link. STAT is written
continuously and needs no inference.
"""
from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Iterator

import numpy as np

from mavlink_io.samples import FcAttitude, FcEkfStatus, FcFlightState, ImuSample, PressureSample
from service.logreaders import (GPS_EPOCH_UNIX_S, GPS_LEAP_S, FcIdentity, FlightStateTrack, LogError, LogSite,
                                LogSummary, decimal_year_from_unix, one_line)
from service.logreaders.dataflash_format import WalkStats, walk

MAG_MAX_AGE_S = 0.5
PRESS_DIFF_MAX_AGE_S = 1.0
MGAUSS_TO_GAUSS = 1e-3
_ZERO_C_K = 273.15
# each sensor kind: message names, numbered ones (old logs) after the unnumbered one
_KINDS = {"IMU": ("IMU", "IMU2", "IMU3"), "MAG": ("MAG", "MAG2", "MAG3"), "BARO": ("BARO", "BAR2", "BAR3"),
          "ARSP": ("ARSP", "ASP2"), "GPS": ("GPS", "GPS2")}
_NEEDS = {"IMU": ("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ"), "MAG": ("MagX", "MagY", "MagZ"),
          "BARO": ("Press",), "ARSP": ("DiffPress",), "GPS": ("Status", "Lat", "Lng"), "ATT": ("Roll", "Pitch", "Yaw")}
_STATE_MSGS = {"EV", "ARM", "STAT"}
_EKF_MSGS = {3: "XKF4", 2: "NKF4"}
"""AHRS_EKF_TYPE -> the EKF's status record (solution status SS and innovation test ratios)."""
_SS_ATTITUDE, _SS_HORIZ_POS_ABS = 1 << 0, 1 << 4
"""ArduPilot's nav_filter_status bits (the same places as MAVLink's EKF_STATUS_FLAGS)."""
# ArduPilot's LogEvent ids (AP_Logger): what each says about the armed / landed state
_EV_ARMED, _EV_DISARMED, _EV_LAND_COMPLETE, _EV_NOT_LANDED = 10, 11, 18, 28


def _time_s(rec: dict) -> float | None:
    if "TimeUS" in rec:
        return rec["TimeUS"] * 1e-6
    if "TimeMS" in rec:
        return rec["TimeMS"] * 1e-3
    return None


def _f(rec: dict, key: str) -> float:
    v = rec.get(key)
    return float(v) if isinstance(v, (int, float)) else math.nan


_FIRMWARE_MAV_TYPE = {"ArduPlane": 1, "ArduCopter": 2, "ArduHeli": 4, "ArduRover": 10, "ArduSub": 12,
                      "Blimp": 7}
"""The firmware named by the log's first MSG (e.g. "ArduPlane V4.5.7") -> a HEARTBEAT MAV_TYPE."""


def _identity(firmware: str | None, params: dict) -> FcIdentity | None:
    """The FC's MAV_TYPE from its firmware message, else from a parameter only that firmware has
    (Q_ENABLE: ArduPlane; FRAME_CLASS: ArduCopter, 6 = helicopter); the take-off parameters with it."""
    take = {n: params[n] for n in ("Q_ENABLE", "TKOFF_THR_MINACC") if n in params}
    if firmware is not None:
        mav_type, src = _FIRMWARE_MAV_TYPE[firmware], f"MSG {firmware}"
        if firmware == "ArduCopter" and params.get("FRAME_CLASS") == 6.0:
            mav_type = 4
    elif "Q_ENABLE" in params:
        mav_type, src = 1, "PARM Q_ENABLE (ArduPlane)"
    elif "FRAME_CLASS" in params:
        mav_type, src = (4 if params["FRAME_CLASS"] == 6.0 else 2), f"PARM FRAME_CLASS {params['FRAME_CLASS']:g} (ArduCopter)"
    else:
        return None
    return FcIdentity(mav_type, "ardupilot", take, src)


class DataflashReader:
    """``items()`` yields ImuSample, PressureSample, FcAttitude and FcFlightState in log order."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.summary = LogSummary(kind="dataflash", autopilot="ardupilot")
        try:
            self._data = self.path.read_bytes()
        except OSError as exc:
            raise LogError(f"{self.path}: cannot read ({exc.strerror})") from None
        if len(self._data) < 3 or self._data[0] != 0xA3 or self._data[1] != 0x95:
            raise LogError(f"{self.path}: not an ArduPilot DataFlash log (it does not start with the "
                           "record header 0xA3 0x95)")
        self._site: LogSite | None = None
        self._gps_unix_s: float | None = None
        self._takeoffs: list[float] = []
        self.estimator_status: str | None = None
        """The record the FC's estimator status comes from ("XKF4", "NKF4"), None when the log has none."""
        self._ekf: tuple[str, int | None] | None = None
        self._start_state: tuple[bool | None, bool | None] = (None, None)
        """(armed, landed) the FC had at the log's start, implied by its first EV/ARM changes."""
        self._offset = 0
        self._scan()

    # --- the first pass: formats, instances, site, date, the log's own flight state --------------

    def _scan(self) -> None:
        st = WalkStats()
        wanted = ({n for names in _KINDS.values() for n in names} | _STATE_MSGS | set(_EKF_MSGS.values())
                  | {"ATT", "MSG", "PARM"})  # ATT: times as items()
        firmware: str | None = None
        params: dict[str, float] = {}
        instances: dict[str, set] = {}
        track = FlightStateTrack()
        last_t = 0.0
        first_change: dict[str, tuple[bool, float]] = {}   # "armed"/"landed": (its first EV/ARM value, time)
        try:
            for name, rec, _ in walk(self._data, wanted, st):
                t = _time_s(rec) if not name.startswith("GPS") else None  # old GPS: TimeMS of the GPS week
                last_t = t if t is not None else last_t
                if "I" in rec:
                    instances.setdefault(name, set()).add(rec["I"])
                elif "C" in rec and name in _EKF_MSGS.values():
                    instances.setdefault(name, set()).add(rec["C"])
                if name in _STATE_MSGS:
                    before = (track.armed, track.landed)
                    self._state_update(track, name, rec, last_t)
                    if name != "STAT":
                        for key, old, new in (("armed", before[0], track.armed), ("landed", before[1], track.landed)):
                            if old is None and new is not None:
                                first_change.setdefault(key, (new, last_t))
                elif name == "GPS" and self._site is None:
                    self._gps(rec)
                elif name == "MSG" and firmware is None:
                    m = str(rec.get("Message", ""))
                    firmware = next((fw for fw in _FIRMWARE_MAV_TYPE if m.startswith(fw)), None)
                elif name == "PARM":
                    try:
                        params[str(rec["Name"])] = float(rec["Value"])
                    except (KeyError, TypeError, ValueError):
                        pass
        except (struct.error, ValueError, TypeError, KeyError) as exc:
            raise LogError(f"{self.path}: unreadable DataFlash records ({one_line(exc)})") from None
        self._stats = st
        self._takeoffs = track.takeoffs_s
        self.summary.fc_identity = _identity(firmware, params)
        self.summary.params = params
        self._infer_start_state(first_change)
        names = st.names()
        self._use: dict[str, tuple[str, int | None]] = {}
        for kind, msgs in _KINDS.items():
            present = [m for m in msgs if m in names and st.counts.get(m)]
            if not present:
                continue
            msg = present[0]
            fmt = next(f for f in st.formats.values() if f.name == msg)
            lacking = [c for c in _NEEDS[kind] if c not in fmt.columns]
            if lacking:
                if kind == "IMU":
                    raise LogError(f"{self.path}: the IMU records have no {', '.join(lacking)} (columns: "
                                   f"{', '.join(fmt.columns)})")
                self.summary.notes.append(f"{msg} records have no {', '.join(lacking)}: {kind} not used")
                continue
            inst = min(instances[msg]) if msg in instances else None
            self._use[kind] = (msg, inst)
            others = sorted(instances.get(msg, ())) if inst is not None else present
            if len(others) > 1:
                self.summary.notes.append(f"{kind}: {msg}" + (f" instance {inst}" if inst is not None else "")
                                          + f" used of {', '.join(map(str, others))}")
        if "IMU" not in self._use:
            raise LogError(f"{self.path}: no IMU records in this DataFlash log"
                           + (" (truncated before the first)" if st.tail_bytes else ""))
        if "ATT" in names:
            fmt = next(f for f in st.formats.values() if f.name == "ATT")
            lacking = [c for c in _NEEDS["ATT"] if c not in fmt.columns]
            if lacking:
                self.summary.notes.append(f"ATT records have no {', '.join(lacking)}: no reference attitude")
            else:
                self._use["ATT"] = ("ATT", None)
        self._choose_ekf(st, names, params, instances)
        imu_cols = next(f for f in st.formats.values() if f.name == self._use["IMU"][0]).columns
        if "TimeUS" not in imu_cols and "TimeMS" not in imu_cols:
            raise LogError(f"{self.path}: the IMU records carry no time (no TimeUS or TimeMS column)")
        if "TimeUS" not in imu_cols:
            self.summary.notes.append("old DataFlash log: times from TimeMS (milliseconds)")
        if st.tail_bytes:
            self.summary.notes.append(f"the last {st.tail_bytes} bytes are an incomplete record (truncated log)")
        if st.skipped_bytes or st.bad_formats:
            self.summary.notes.append(f"{st.skipped_bytes} damaged bytes skipped"
                                      + (f", {st.bad_formats} unusable FMT records" if st.bad_formats else "")
                                      + " (corrupt log): records there are lost")

    def _choose_ekf(self, st: WalkStats, names, params: dict, instances: dict) -> None:
        """The status record of the EKF the AHRS used (module docstring), or a note that there is none."""
        logged = [m for m in _EKF_MSGS.values() if m in names and st.counts.get(m)]
        want = _EKF_MSGS.get(int(params["AHRS_EKF_TYPE"])) if "AHRS_EKF_TYPE" in params else None
        msg = want if want in logged else (logged[0] if logged and want is None else None)
        if msg is not None:
            fmt = next(f for f in st.formats.values() if f.name == msg)
            if "SS" not in fmt.columns:
                msg = None
        if msg is None:
            self.summary.notes.append("no EKF solution status in the log (XKF4/NKF4 SS)" + (
                f" for AHRS_EKF_TYPE {int(params['AHRS_EKF_TYPE'])}" if want is not None else "")
                + ": the FC's attitude is judged without one")
            return
        core = min(instances[msg]) if msg in instances else None
        self._ekf = (msg, core)
        self.estimator_status = msg

    def _infer_start_state(self, first_change: dict[str, tuple[bool, float]]) -> None:
        """The state before the log's first EV/ARM changes (module docstring): a first disarm means
        armed from the start; a first landing means in the air from the start."""
        armed = first_change.get("armed")
        landed = first_change.get("landed")
        start_armed = True if armed is not None and armed[0] is False else None
        start_landed = False if landed is not None and landed[0] is True else None
        if start_armed is None and start_landed is None:
            return
        self._start_state = (start_armed, start_landed)
        said = [f"{'disarmed' if k == 'armed' else 'landed'} at {v[1]:.1f} s" for k, v in first_change.items()
                if (k == "armed" and start_armed) or (k == "landed" and start_landed is False)]
        self.summary.notes.append(
            "the log starts " + " and ".join(x for x, on in (("armed", start_armed), ("in the air", start_landed is False))
                                             if on)
            + f": its first state records are {' and '.join(said)} with no arming or take-off before them")

    def _gps(self, rec: dict) -> None:
        if "I" in rec and rec["I"] != 0:
            return
        lat, lon, status = _f(rec, "Lat"), _f(rec, "Lng"), _f(rec, "Status")
        if not status >= 3 or not (math.isfinite(lat) and math.isfinite(lon)):
            return
        if (lat == 0.0 and lon == 0.0) or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            return
        alt = _f(rec, "Alt")
        self._site = LogSite(lat, lon, alt if math.isfinite(alt) else 0.0, f"GPS (status {int(status)})")
        wk = rec.get("GWk", rec.get("Week"))
        ms = rec.get("GMS", rec.get("TimeMS") if "Week" in rec else None)
        if wk and ms is not None:
            self._gps_unix_s = GPS_EPOCH_UNIX_S + wk * 604800 + ms * 1e-3 - GPS_LEAP_S

    @staticmethod
    def _state_update(track: FlightStateTrack, name: str, rec: dict, t: float):
        """What one EV/ARM/STAT record says, into ``track``; (armed, landed) or None if it says nothing."""
        if name == "EV":
            ev = rec.get("Id")
            if ev == _EV_ARMED:
                return track.update(t, armed=True, arming_event=True)
            if ev == _EV_DISARMED:
                return track.update(t, armed=False)
            if ev == _EV_LAND_COMPLETE:
                return track.update(t, landed=True)
            if ev == _EV_NOT_LANDED:
                return track.update(t, landed=False)
            return None
        if name == "ARM" and "ArmState" in rec:
            armed = bool(rec["ArmState"])
            return track.update(t, armed=armed, arming_event=armed)
        if name == "STAT" and "isFlying" in rec:
            before = (track.armed, track.landed)
            now = track.update(t, armed=bool(rec["Armed"]) if "Armed" in rec else None,
                               landed=not rec["isFlying"])
            return now if now != before else None
        return None

    def site(self) -> LogSite | None:
        return self._site

    def decimal_year(self) -> float | None:
        return None if self._gps_unix_s is None else decimal_year_from_unix(self._gps_unix_s)

    def takeoff_times_s(self) -> list[float]:
        """The log's own take-offs (FC time s) from EV/ARM/STAT: for scoring only."""
        return list(self._takeoffs)

    def progress(self) -> float:
        return min(1.0, self._offset / len(self._data)) if self._data else 1.0

    # --- the second pass: the samples --------------------------------------------------------------

    def items(self, imu_batches: bool = False) -> Iterator:
        """The samples in log order; one ImuSample per IMU record, ``imu_batches`` or not (the records
        are walked one by one: a run of them as an ImuBatch would save nothing)."""
        s = self.summary
        use = self._use
        by_msg = {msg: (kind, inst) for kind, (msg, inst) in use.items() if kind != "GPS"}
        wanted = set(by_msg) | _STATE_MSGS | ({self._ekf[0]} if self._ekf else set())
        mag = None
        mag_t = -math.inf
        dp = None
        dp_t = -math.inf
        last_gyro = None
        last_t = 0.0
        track = FlightStateTrack()
        counts = {"imu": 0, "imu_with_mag": 0, "pressure": 0, "pressure_with_diff": 0, "attitude": 0,
                  "flight_state": 0, "estimator_status": 0}
        start_state = self._start_state if self._start_state != (None, None) else None
        for name, rec, pos in walk(self._data, wanted):
            self._offset = pos
            t = _time_s(rec)
            if t is None or not math.isfinite(t):
                t = last_t  # an old EV has no time: the last record's
            last_t = t
            if start_state is not None:   # the state the log starts in, before its first sample
                armed0, landed0 = track.update(t, armed=start_state[0], landed=start_state[1])
                start_state = None
                counts["flight_state"] += 1
                yield FcFlightState(t, t, armed0, landed0, "EV")
            if name in _STATE_MSGS:
                st = self._state_update(track, name, rec, t)
                if st is not None:
                    counts["flight_state"] += 1
                    yield FcFlightState(t, t, st[0], st[1], name)
                continue
            if self._ekf is not None and name == self._ekf[0]:
                if self._ekf[1] is not None and rec.get("C") != self._ekf[1]:
                    continue
                ss = rec.get("SS")
                if isinstance(ss, int):
                    counts["estimator_status"] += 1
                    yield FcEkfStatus(t, bool(ss & _SS_ATTITUDE), bool(ss & _SS_HORIZ_POS_ABS), ss, name, t,
                                      _f(rec, "SV"), _f(rec, "SP"), _f(rec, "SH"), _f(rec, "SM"))
                continue
            kind, inst = by_msg[name]
            if inst is not None and rec.get("I") != inst:
                continue
            if kind == "IMU":
                g = np.array([rec["GyrX"], rec["GyrY"], rec["GyrZ"]], dtype=float)
                a = np.array([rec["AccX"], rec["AccY"], rec["AccZ"]], dtype=float)
                mg = mag if (mag is not None and 0.0 <= t - mag_t <= MAG_MAX_AGE_S) else None
                counts["imu"] += 1
                counts["imu_with_mag"] += mg is not None
                last_gyro = g
                yield ImuSample(t, t, g, a, mg, "IMU", 0)
            elif kind == "MAG":
                v = np.array([rec["MagX"], rec["MagY"], rec["MagZ"]], dtype=float) * MGAUSS_TO_GAUSS
                if np.all(np.isfinite(v)) and np.any(v != 0.0):
                    mag, mag_t = v, t
            elif kind == "ARSP":
                v = _f(rec, "DiffPress")
                if math.isfinite(v):
                    dp, dp_t = v, t
            elif kind == "BARO":
                press = _f(rec, "Press")
                if not math.isfinite(press) or press <= 0.0:
                    continue
                diff = dp if (dp is not None and 0.0 <= t - dp_t <= PRESS_DIFF_MAX_AGE_S) else None
                temp = _f(rec, "Temp")
                counts["pressure"] += 1
                counts["pressure_with_diff"] += diff is not None
                yield PressureSample(t, t, press, diff, temp + _ZERO_C_K if math.isfinite(temp) else None, "BARO")
            elif kind == "ATT":
                roll, pitch, yaw = (math.radians(_f(rec, k)) for k in ("Roll", "Pitch", "Yaw"))
                if not (math.isfinite(roll) and math.isfinite(pitch) and math.isfinite(yaw)):
                    continue
                w = last_gyro if last_gyro is not None else np.full(3, math.nan)
                counts["attitude"] += 1
                yield FcAttitude(t, t, roll, pitch, math.remainder(yaw, 2 * math.pi), w)
        self._offset = len(self._data)
        s.counts = counts
        if counts["imu"] == 0:
            raise LogError(f"{self.path}: no IMU records in this DataFlash log")
