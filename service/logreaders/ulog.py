"""PX4 ULog (.ulg) -> typed samples, with pyulog, across PX4 generations.

Each topic is read from its lowest logged instance (``multi_id``; the summary says when there are
more); each field by the names PX4 has used for it (first one present wins):

====================== ============================================ ==============================
topic (fallbacks)      fields                                       sample
====================== ============================================ ==============================
sensor_combined        gyro_rad[3] rad/s, accelerometer_m_s2[3]     ImuSample (time: timestamp;
                       m/s^2 (specific force: [0,0,-g] at rest)     a sample whose accelerometer_
 (no sensor_combined)  sensor_gyro + sensor_accel x,y,z, when       timestamp_relative is invalid
                       logged >= MIN_IMU_RATE_HZ (high-rate         has no accel: skipped)
                       profile): accel held onto the gyro times
vehicle_magnetometer   magnetometer_ga[3] gauss (calibrated, body)  ImuSample.mag_gauss, held from
 (else) sensor_mag     x, y, z gauss (uncalibrated: noted)          the last sample <= the IMU
 (old logs)            sensor_combined.magnetometer_ga[3] where     time and at most
                       magnetometer_timestamp_relative is valid     MAG_MAX_AGE_S old
vehicle_air_data       baro_pressure_pa Pa; temperature:            PressureSample (abs Pa, K;
                       baro_temp_celcius | ambient_temperature C    temperature None when the log
 (else) sensor_baro    pressure (Pa; mbar in old PX4: < 2000)       has none)
 (old logs)            sensor_combined.baro_alt_meter: pressure by
                       the ISA inverse PX4 used (QNH 1013.25)
differential_pressure  differential_pressure_filtered_pa |          PressureSample.press_diff_pa,
                       differential_pressure_pa |                   held (PRESS_DIFF_MAX_AGE_S)
                       differential_pressure_raw_pa Pa
airspeed               indicated_airspeed_m_s: q = rho0/2 IAS |IAS|  when differential_pressure
                       (rho0 = 1.225 kg/m^3, IAS's definition)       is logged below 5 Hz; noted
vehicle_attitude       q[4] Hamilton wxyz, q_nav_from_body (NED     FcAttitude (ZYX Euler; yaw
                       from FRD); rollspeed.. if logged             (-pi, pi]); rates: rollspeed..
                                                                    if logged, else the last gyro
estimator_status       solution_status_flags (MAVLink ESTIMATOR_     FcEkfStatus (attitude_ok = bit
                       STATUS flags); vel/pos/hgt/mag_test_ratio    0, horiz_pos_ok = bit 4); none
                                                                    when the flags are 0 throughout
                                                                    (PX4 versions that left them
                                                                    unset: noted)
vehicle_status         arming_state (2: armed, in every PX4)        FcFlightState (armed)
vehicle_land_detected  landed                                       FcFlightState (landed)
vehicle_gps_position / fix_type >= 3: lat, lon (1e-7 deg), alt      the site (first 3D fix)
sensor_gps             (mm) or latitude_deg, longitude_deg,
                       altitude_msl_m
home_position          lat, lon deg only when valid_hpos; alt when  the site (no GNSS fix logged)
                       valid_alt
====================== ============================================ ==============================

A log without an estimator status (``estimator_status`` None, noted) has its FC attitude judged
without one from the start (service/replay.py), as a live FC that sends none is after
estimators/reference_health's ``status_wait_s``.

Times are the FC's boot clock in microseconds (``timestamp_sample`` where the topic has it);
``time_rx_s`` = ``time_fc_s`` (there is no receive clock in a log). A ULog has no end marker: a
file whose last message is cut short is reported truncated (the messages are walked by their
size fields), damage pyulog finds is reported as corruption; what was read before is replayed.
"""
from __future__ import annotations

import contextlib
import io
import math
import struct
from pathlib import Path
from typing import Iterator

import numpy as np

from mavlink_io.imu_batch import IMU_RECORD, ImuBatch
from mavlink_io.samples import FcAttitude, FcEkfStatus, FcFlightState, ImuSample, PressureSample
from service.logreaders import (FcIdentity, FlightStateTrack, LogError, LogSite, LogSummary, decimal_year_from_unix,
                                one_line)

MAG_MAX_AGE_S = 0.5
"""A magnetometer sample older than this is not attached to an IMU sample (mag_gauss None)."""
PRESS_DIFF_MAX_AGE_S = 1.0
"""A differential pressure older than this is not attached to a baro sample."""
MIN_IMU_RATE_HZ = 20.0
"""sensor_gyro/sensor_accel below this rate (PX4's default profile logs them at 1 Hz) are no IMU."""
RHO0_KG_M3 = 1.225
"""Sea-level ISA density: IAS is defined by q = rho0/2 IAS^2."""
_REL_INVALID = 2147483647
"""PX4's RELATIVE_TIMESTAMP_INVALID (int32 max): that sensor is absent from sensor_combined."""
_ZERO_C_K = 273.15
_ARMING_STATE_ARMED = 2
"""vehicle_status.arming_state ARMED: 2 in every PX4 version (the others were renumbered)."""
_ULOG_MAGIC = b"ULog\x01\x12\x35"
_ULOG_HEADER_BYTES = 16

_TOPICS = ["sensor_combined", "sensor_gyro", "sensor_accel", "vehicle_magnetometer", "sensor_mag",
           "vehicle_air_data", "sensor_baro", "differential_pressure", "airspeed", "vehicle_attitude",
           "vehicle_gps_position", "sensor_gps", "home_position", "vehicle_status", "vehicle_land_detected",
           "estimator_status"]

# event kinds, in the order that ties are resolved (state, reference, pressure at the IMU time first)
_STATE, _STATUS, _ATT, _PRESS, _IMU = 0, 1, 2, 3, 4
_EST_ATTITUDE, _EST_POS_HORIZ_ABS = 1 << 0, 1 << 4
"""MAVLink ESTIMATOR_STATUS_FLAGS bits, which estimator_status.solution_status_flags uses."""


def _isa_pressure_pa(alt_m: np.ndarray) -> np.ndarray:
    """Inverse of PX4's ISA altitude (T0 288.15 K, L -0.0065 K/m, p0 101325 Pa)."""
    return 101325.0 * (1.0 - 0.0065 * alt_m / 288.15) ** (9.80665 / (287.05 * 0.0065))


def _first(d: dict, *names: str) -> str | None:
    """The first of ``names`` that topic ``d`` has (PX4 renamed fields between versions)."""
    return next((n for n in names if n in d), None)


def _vec(d: dict, fmt: str) -> np.ndarray:
    return np.column_stack([np.asarray(d[fmt.format(i)], np.float64) for i in range(3)])


def _rate_hz(t: np.ndarray) -> float:
    return (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0


def truncated_tail_bytes(data: bytes) -> int:
    """Bytes of a last ULog message cut short (0: the file ends on a message boundary).

    A ULog is a 16-byte header then messages ``uint16 size, uint8 type, payload[size]``; walking
    the sizes from the header either lands on the end of the file or passes it."""
    pos, n = _ULOG_HEADER_BYTES, len(data)
    unpack = struct.Struct("<H").unpack_from
    start = pos
    while pos + 3 <= n:
        start = pos
        pos += 3 + unpack(data, pos)[0]
    if pos == n:
        return 0
    return n - start if pos > n else n - pos  # a message cut short, or a header cut short


class UlogReader:
    """``items()`` yields ImuSample (``items(imu_batches=True)``: ImuBatch runs), PressureSample,
    FcAttitude, FcEkfStatus and FcFlightState in FC-time order."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.summary = LogSummary(kind="ulog", autopilot="px4")
        try:
            from pyulog import ULog
        except ImportError:
            raise LogError("reading .ulg needs pyulog: pip install pyulog") from None
        try:
            raw = self.path.read_bytes()
        except OSError as exc:
            raise LogError(f"{self.path}: cannot read ({exc.strerror})") from None
        if not raw.startswith(_ULOG_MAGIC):
            raise LogError(f"{self.path}: not a readable PX4 ULog (it does not start with the ULog magic)")
        said = io.StringIO()
        try:
            with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):  # pyulog prints
                self.ulog = ULog(str(self.path), _TOPICS)
        except Exception as exc:  # noqa: BLE001 - pyulog raises anything on a damaged file
            raise LogError(f"{self.path}: not a readable PX4 ULog ({one_line(exc)})") from None
        self._data: dict[str, dict] = {}
        instances: dict[str, list[int]] = {}
        for d in sorted(self.ulog.data_list, key=lambda d: (d.name, d.multi_id)):
            if len(d.data.get("timestamp", ())) == 0:
                continue
            instances.setdefault(d.name, []).append(d.multi_id)
            if d.name not in self._data:
                self._data[d.name] = d.data
        self._instances = instances
        self._done = 0
        self._total = 1
        self._takeoffs: list[float] | None = None
        tail = truncated_tail_bytes(raw)
        if tail:
            self.summary.notes.append(f"the last {tail} bytes are an incomplete message (truncated log)")
        if getattr(self.ulog, "file_corruption", False) or "corrupt" in said.getvalue().lower():
            self.summary.notes.append("pyulog reports file corruption: data after the damage may be missing")
        self._imu_check()
        self.summary.fc_identity = self._identity()
        self.summary.params = {str(k): float(v) for k, v in
                               (getattr(self.ulog, "initial_parameters", {}) or {}).items()
                               if isinstance(v, (int, float))}
        self._status_said = False
        self.estimator_status: str | None = "estimator_status" if self._status()[0] is not None else None
        """Where the FC's estimator status comes from, None when the log has none (said in the notes)."""

    def _identity(self) -> FcIdentity | None:
        """PX4's MAV_TYPE (its parameter, else vehicle_status.system_type) and its launch detection."""
        par = getattr(self.ulog, "initial_parameters", {}) or {}
        take = {"FW_LAUN_DETCN_ON": float(par["FW_LAUN_DETCN_ON"])} if "FW_LAUN_DETCN_ON" in par else {}
        if "MAV_TYPE" in par:
            return FcIdentity(int(par["MAV_TYPE"]), "px4", take, "parameter MAV_TYPE")
        vs = self._topic("vehicle_status")
        if vs is not None and len(vs.get("system_type", ())):
            return FcIdentity(int(vs["system_type"][0]), "px4", take, "vehicle_status.system_type")
        return None

    def _topic(self, name: str) -> dict | None:
        return self._data.get(name)

    def _instance_note(self, name: str) -> None:
        ids = self._instances.get(name, [])
        if len(ids) > 1:
            self.summary.notes.append(f"{name}: instance {ids[0]} used of {len(ids)} logged ({ids})")

    @staticmethod
    def _time_s(d: dict) -> np.ndarray:
        t = d["timestamp_sample"] if "timestamp_sample" in d else d["timestamp"]
        return np.asarray(t, dtype=np.float64) * 1e-6

    def _imu_check(self) -> None:
        """LogError now (before any replay) when the log has no usable IMU stream, saying why."""
        sc = self._topic("sensor_combined")
        if sc is not None:
            need = [f"{n}[{i}]" for n in ("gyro_rad", "accelerometer_m_s2") for i in range(3)]
            lacking = [n for n in need if n not in sc]
            if lacking:
                raise LogError(f"{self.path}: sensor_combined has no {', '.join(lacking)} (unknown layout)")
            return
        g, a = self._topic("sensor_gyro"), self._topic("sensor_accel")
        if g is None or a is None:
            raise LogError(f"{self.path}: no IMU in this ULog: no sensor_combined and no sensor_gyro + "
                           "sensor_accel topic")
        rate = min(_rate_hz(self._time_s(g)), _rate_hz(self._time_s(a)))
        if rate < MIN_IMU_RATE_HZ or not all(k in d for d in (g, a) for k in ("x", "y", "z")):
            raise LogError(f"{self.path}: no IMU in this ULog: no sensor_combined, and sensor_gyro/sensor_accel "
                           f"are logged at {rate:.1f} Hz only (< {MIN_IMU_RATE_HZ:.0f} Hz)")

    # --- site and date ---------------------------------------------------------------------------

    def site(self) -> LogSite | None:
        for name in ("vehicle_gps_position", "sensor_gps"):
            d = self._topic(name)
            if d is None or "fix_type" not in d:
                continue  # no fix type: the log does not say the position is valid
            fix = np.asarray(d["fix_type"])
            if "lat" in d and "lon" in d:
                lat, lon = np.asarray(d["lat"]) * 1e-7, np.asarray(d["lon"]) * 1e-7
                alt = np.asarray(d["alt"]) * 1e-3 if "alt" in d else np.zeros(len(lat))
            elif "latitude_deg" in d and "longitude_deg" in d:
                lat, lon = np.asarray(d["latitude_deg"], float), np.asarray(d["longitude_deg"], float)
                alt = np.asarray(d["altitude_msl_m"], float) if "altitude_msl_m" in d else np.zeros(len(lat))
            else:
                continue
            ok = np.nonzero((fix >= 3) & ((lat != 0) | (lon != 0)) & (np.abs(lat) <= 90) & (np.abs(lon) <= 180)
                            & np.isfinite(alt))[0]
            if ok.size:
                i = ok[0]
                return LogSite(float(lat[i]), float(lon[i]), float(alt[i]), f"{name} (fix type {int(fix[i])})")
        d = self._topic("home_position")
        if d is not None and "valid_hpos" in d and "lat" in d and "lon" in d:
            ok = np.nonzero(np.asarray(d["valid_hpos"]) != 0)[0]
            for i in ok:
                lat, lon = float(d["lat"][i]), float(d["lon"][i])
                if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
                    continue
                alt_ok = "valid_alt" in d and d["valid_alt"][i] != 0 and "alt" in d and math.isfinite(d["alt"][i])
                return LogSite(lat, lon, float(d["alt"][i]) if alt_ok else 0.0,
                               "home_position (valid_hpos)" + ("" if alt_ok else "; altitude not valid: 0 m"))
        return None

    def decimal_year(self) -> float | None:
        for name in ("vehicle_gps_position", "sensor_gps"):
            d = self._topic(name)
            if d is not None and "time_utc_usec" in d:
                t = np.asarray(d["time_utc_usec"], dtype=np.float64)
                t = t[t > 0]
                if t.size:
                    return decimal_year_from_unix(float(t[0]) * 1e-6)
        ref = self.ulog.msg_info_dict.get("time_ref_utc")
        if isinstance(ref, (int, float)) and ref > 0:
            return decimal_year_from_unix(float(ref))
        return None

    def progress(self) -> float:
        return min(1.0, self._done / self._total)

    # --- the FC's own flight state -------------------------------------------------------------

    def _flight_states(self) -> tuple[np.ndarray, list[tuple[bool | None, bool | None]], list[float]]:
        """(times s, [(armed, landed)] carried state per record, the log's take-off times s)."""
        recs: list[tuple[float, bool | None, bool | None]] = []
        vs = self._topic("vehicle_status")
        if vs is not None and "arming_state" in vs:
            recs += [(t, int(a) == _ARMING_STATE_ARMED, None)
                     for t, a in zip(self._time_s(vs).tolist(), vs["arming_state"])]
        ld = self._topic("vehicle_land_detected")
        if ld is not None and "landed" in ld:
            recs += [(t, None, bool(v)) for t, v in zip(self._time_s(ld).tolist(), ld["landed"])]
        recs.sort(key=lambda r: r[0])
        track = FlightStateTrack()
        states = [track.update(t, armed=a, landed=ll) for t, a, ll in recs]
        return np.array([r[0] for r in recs], np.float64), states, track.takeoffs_s

    def takeoff_times_s(self) -> list[float]:
        """The log's own take-offs (FC time s): vehicle_land_detected landed -> in air while armed.
        For scoring only; empty when the log has no land detector or no take-off."""
        if self._takeoffs is None:
            try:
                self._takeoffs = self._flight_states()[2]
            except (KeyError, IndexError, ValueError, TypeError) as exc:
                raise LogError(f"{self.path}: vehicle_status/vehicle_land_detected unreadable "
                               f"({one_line(exc)})") from None
        return list(self._takeoffs)

    # --- streams ---------------------------------------------------------------------------------

    def _imu(self):
        s = self.summary
        sc = self._topic("sensor_combined")
        if sc is not None:
            self._instance_note("sensor_combined")
            t_imu = self._time_s(sc)
            gyro, accel = _vec(sc, "gyro_rad[{}]"), _vec(sc, "accelerometer_m_s2[{}]")
            if "accelerometer_timestamp_relative" in sc:
                ok = np.asarray(sc["accelerometer_timestamp_relative"]) != _REL_INVALID
                if not ok.all():
                    s.notes.append(f"{int(np.sum(~ok))} sensor_combined samples without an accelerometer skipped")
                    t_imu, gyro, accel = t_imu[ok], gyro[ok], accel[ok]
            return t_imu, gyro, accel, "sensor_combined"
        g, a = self._topic("sensor_gyro"), self._topic("sensor_accel")
        self._instance_note("sensor_gyro")
        self._instance_note("sensor_accel")
        t_imu, t_a = self._time_s(g), self._time_s(a)
        gyro = np.column_stack([np.asarray(g[k], np.float64) for k in "xyz"])
        acc = np.column_stack([np.asarray(a[k], np.float64) for k in "xyz"])
        j = np.searchsorted(t_a, t_imu, side="right") - 1  # the last accel sample <= each gyro sample
        ok = j >= 0
        s.notes.append("IMU from sensor_gyro + sensor_accel (no sensor_combined): the last accelerometer "
                       "sample held onto each gyro sample")
        return t_imu[ok], gyro[ok], acc[j[ok]], "sensor_gyro"

    def _mag(self):
        s = self.summary
        vm = self._topic("vehicle_magnetometer")
        if vm is not None and "magnetometer_ga[0]" in vm:
            self._instance_note("vehicle_magnetometer")
            t, mag, name = self._time_s(vm), _vec(vm, "magnetometer_ga[{}]"), "vehicle_magnetometer"
        elif (sm := self._topic("sensor_mag")) is not None and all(k in sm for k in "xyz"):
            self._instance_note("sensor_mag")
            t = self._time_s(sm)
            mag, name = np.column_stack([np.asarray(sm[k], np.float64) for k in "xyz"]), "sensor_mag"
            s.notes.append("magnetometer from sensor_mag (uncalibrated: the FC's offsets are not applied)")
        elif (sc := self._topic("sensor_combined")) is not None and "magnetometer_ga[0]" in sc \
                and "magnetometer_timestamp_relative" in sc:
            rel = np.asarray(sc["magnetometer_timestamp_relative"])
            ok = rel != _REL_INVALID
            if not ok.any():
                return None, None
            t = (np.asarray(sc["timestamp"], np.float64)[ok] + rel[ok]) * 1e-6
            mag = _vec(sc, "magnetometer_ga[{}]")[ok]
            order = np.argsort(t, kind="stable")
            t, mag, name = t[order], mag[order], "sensor_combined.magnetometer_ga (old ULog)"
        else:
            return None, None
        rate = _rate_hz(t)
        s.notes.append(f"magnetometer: {name} at {rate:.1f} Hz" +
                       (f" (held at most {MAG_MAX_AGE_S:g} s: some IMU samples carry none)"
                        if 0 < rate < 2.0 / MAG_MAX_AGE_S else ""))
        return t, mag

    def _baro(self):
        s = self.summary
        ad = self._topic("vehicle_air_data")
        if ad is not None and "baro_pressure_pa" in ad:
            self._instance_note("vehicle_air_data")
            t, p = self._time_s(ad), np.asarray(ad["baro_pressure_pa"], np.float64)
            key = _first(ad, "baro_temp_celcius", "ambient_temperature", "baro_temp_celsius", "temperature")
            if key is None:
                s.notes.append("vehicle_air_data has no temperature field: temperature not given")
                return t, p, np.full(len(t), math.nan)
            return t, p, np.asarray(ad[key], np.float64) + _ZERO_C_K
        sb = self._topic("sensor_baro")
        if sb is not None and "pressure" in sb:
            self._instance_note("sensor_baro")
            t, p = self._time_s(sb), np.asarray(sb["pressure"], np.float64)
            fin = p[np.isfinite(p)]
            if fin.size and np.median(fin) < 2000.0:  # millibar in PX4 before v1.12
                p = p * 100.0
                s.notes.append("sensor_baro.pressure in millibar (old PX4): x100 to Pa")
            s.notes.append(f"barometer from sensor_baro at {_rate_hz(t):.1f} Hz (no vehicle_air_data)")
            temp = np.asarray(sb["temperature"], np.float64) + _ZERO_C_K if "temperature" in sb \
                else np.full(len(t), math.nan)
            return t, p, temp
        sc = self._topic("sensor_combined")
        if sc is not None and "baro_alt_meter" in sc and "baro_timestamp_relative" in sc:
            rel = np.asarray(sc["baro_timestamp_relative"])
            ok = rel != _REL_INVALID
            if ok.any():
                t = (np.asarray(sc["timestamp"], np.float64)[ok] + rel[ok]) * 1e-6
                p = _isa_pressure_pa(np.asarray(sc["baro_alt_meter"], np.float64)[ok])
                key = _first(sc, "baro_temp_celcius", "baro_temp_celsius")
                temp = (np.asarray(sc[key], np.float64)[ok] + _ZERO_C_K) if key else np.full(len(t), math.nan)
                s.notes.append("barometric pressure from sensor_combined.baro_alt_meter by the ISA "
                               "inverse (old ULog: PX4 logged altitude, not pressure)")
                return t, p, temp
        return None, None, None

    def _diff_pressure(self):
        s = self.summary
        dpt, asp = self._topic("differential_pressure"), self._topic("airspeed")
        if asp is not None and "indicated_airspeed_m_s" not in asp:
            asp = None
        if dpt is not None:
            key = _first(dpt, "differential_pressure_filtered_pa", "differential_pressure_pa",
                         "differential_pressure_raw_pa")
            if key is not None:
                t = self._time_s(dpt)
                rate = _rate_hz(t)
                if rate >= 5.0 or asp is None:
                    self._instance_note("differential_pressure")
                    return t, np.asarray(dpt[key], np.float64)
                s.notes.append(f"differential_pressure is logged at {rate:.1f} Hz only: using airspeed instead")
        if asp is not None:
            ias = np.asarray(asp["indicated_airspeed_m_s"], np.float64)
            s.notes.append("differential pressure from airspeed.indicated_airspeed_m_s: q = rho0/2 IAS|IAS|")
            return self._time_s(asp), 0.5 * RHO0_KG_M3 * ias * np.abs(ias)
        return None, None

    def _attitude(self):
        va = self._topic("vehicle_attitude")
        if va is None or not all(f"q[{i}]" in va for i in range(4)):
            return None, None, None
        q = np.column_stack([np.asarray(va[f"q[{i}]"], np.float64) for i in range(4)])
        rates = None
        if all(k in va for k in ("rollspeed", "pitchspeed", "yawspeed")):
            rates = np.column_stack([va["rollspeed"], va["pitchspeed"], va["yawspeed"]]).astype(np.float64)
        return self._time_s(va), q, rates

    def _status(self):
        """estimator_status: times, solution status flags, test ratios (vel, pos, hgt, mag; NaN where not
        logged); Nones when the log has no usable status."""
        es = self._topic("estimator_status")
        flags = None if es is None else es.get("solution_status_flags")
        said, self._status_said = self._status_said, True
        if flags is None or not len(flags) or not np.any(np.asarray(flags) != 0):
            if not said:
                self.summary.notes.append("no estimator status in the log (estimator_status.solution_status_flags "
                                          + ("absent" if flags is None or not len(flags) else "0 throughout")
                                          + "): the FC's attitude is judged without one")
            return None, None, None
        if not said:
            self._instance_note("estimator_status")
        n = len(flags)
        ratios = np.column_stack([np.asarray(es[k], np.float64) if k in es else np.full(n, math.nan)
                                  for k in ("vel_test_ratio", "pos_test_ratio", "hgt_test_ratio", "mag_test_ratio")])
        return self._time_s(es), np.asarray(flags, np.int64), ratios

    def items(self, imu_batches: bool = False) -> Iterator:
        """The samples in FC-time order. ``imu_batches``: each run of IMU samples between two other
        items as one ImuBatch (IMU_RECORD rows, decoded for the whole log at once), else one
        ImuSample each (the same values)."""
        if not imu_batches:
            for item in self.items(imu_batches=True):
                if type(item) is ImuBatch:
                    yield from item.samples()
                else:
                    yield item
            return
        try:
            streams = (*self._imu(), *self._mag(), *self._baro(), *self._diff_pressure(), *self._attitude(),
                       *self._status(), *self._flight_states())
        except (KeyError, IndexError, ValueError, TypeError) as exc:
            raise LogError(f"{self.path}: a topic has an unexpected layout ({one_line(exc)})") from None
        self._takeoffs = streams[-1]
        yield from self._merge(*streams[:-1])

    def _merge(self, t_imu, gyro, accel, imu_src, t_mag, mag, t_baro, p_abs, temp_k, t_dp, dp, t_att, q, rates,
               t_es, es_flags, es_ratios, t_st, states) -> Iterator:
        from estimators.rotations import euler_from_quat
        s = self.summary
        n_imu = len(t_imu)
        # magnetometer held onto the IMU samples (the last one <= t, if not older than MAG_MAX_AGE_S)
        mag_idx = np.full(n_imu, -1)
        if t_mag is not None and len(t_mag):
            j = np.searchsorted(t_mag, t_imu, side="right") - 1
            ok = (j >= 0) & (t_imu - t_mag[np.maximum(j, 0)] <= MAG_MAX_AGE_S) \
                & np.all(np.isfinite(mag[np.maximum(j, 0)]), axis=1)
            mag_idx = np.where(ok, j, -1)
        dp_idx = None
        if t_baro is not None and t_dp is not None and len(t_dp):
            j = np.searchsorted(t_dp, t_baro, side="right") - 1
            ok = (j >= 0) & (t_baro - t_dp[np.maximum(j, 0)] <= PRESS_DIFF_MAX_AGE_S)
            dp_idx = np.where(ok, j, -1)
        # one merged, stable time order of all events
        parts = [(t_imu, _IMU)] + [(t, k) for t, k in ((t_baro, _PRESS), (t_att, _ATT), (t_es, _STATUS),
                                                        (t_st, _STATE))
                                   if t is not None and len(t)]
        all_t = np.concatenate([p[0] for p in parts])
        all_k = np.concatenate([np.full(len(p[0]), p[1], np.int8) for p in parts])
        all_i = np.concatenate([np.arange(len(p[0])) for p in parts])
        order = np.lexsort((all_k, all_t))
        self._total = len(order)
        kinds, idx = all_k[order], all_i[order]
        # the IMU samples in merged order, the finite ones as IMU_RECORD rows (NaN magnetometer: none held)
        is_imu = kinds == _IMU
        pos = idx[is_imu]
        finite = (np.all(np.isfinite(gyro), axis=1) & np.all(np.isfinite(accel), axis=1))[pos]
        pos_ok = pos[finite]
        rows = np.zeros(len(pos_ok), dtype=IMU_RECORD)
        f8 = rows.view(np.float64).reshape(len(pos_ok), IMU_RECORD.itemsize // 8)
        f8[:, 0] = f8[:, 1] = t_imu[pos_ok]
        f8[:, 2:5] = gyro[pos_ok]
        f8[:, 5:8] = accel[pos_ok]
        held = mag_idx[pos_ok]
        with_mag = held >= 0
        f8[:, 8:11] = np.nan
        if with_mag.any():
            f8[with_mag, 8:11] = mag[held[with_mag]]
        # an IMU run at merged positions [a, b) is rows[ok_before[imu_before[a]] : ok_before[imu_before[b]]]
        imu_before = np.concatenate(([0], np.cumsum(is_imu))).tolist()
        ok_before = np.concatenate(([0], np.cumsum(finite))).tolist()
        cuts = (np.flatnonzero(kinds[1:] != kinds[:-1]) + 1).tolist()
        last_gyro = None
        counts = {"imu": len(pos_ok), "imu_with_mag": int(np.count_nonzero(with_mag)), "pressure": 0,
                  "pressure_with_diff": 0, "attitude": 0, "flight_state": 0, "estimator_status": 0}
        bad = len(pos) - len(pos_ok)
        kinds_l, idx_l = kinds.tolist(), idx.tolist()
        for a, b in zip([0] + cuts, cuts + [len(order)]) if len(order) else ():
            self._done = a
            if kinds_l[a] == _IMU:
                r0, r1 = ok_before[imu_before[a]], ok_before[imu_before[b]]
                if r1 > r0:
                    last_gyro = gyro[pos_ok[r1 - 1]]
                    yield ImuBatch(rows[r0:r1], imu_src)
                continue
            for n in range(a, b):
                self._done = n
                kind, i = kinds_l[n], idx_l[n]
                if kind == _PRESS:
                    t, pa = float(t_baro[i]), float(p_abs[i])
                    if not (math.isfinite(pa) and pa > 0.0):
                        continue
                    diff = None
                    if dp_idx is not None and dp_idx[i] >= 0 and math.isfinite(dp[dp_idx[i]]):
                        diff = float(dp[dp_idx[i]])
                    counts["pressure"] += 1
                    counts["pressure_with_diff"] += diff is not None
                    tk = float(temp_k[i])
                    yield PressureSample(t, t, pa, diff, tk if math.isfinite(tk) else None, "vehicle_air_data")
                elif kind == _ATT:
                    qi = q[i]
                    if not np.all(np.isfinite(qi)) or not qi @ qi > 0.5:
                        continue
                    roll, pitch, yaw = euler_from_quat(qi / math.sqrt(qi @ qi))
                    yaw = math.remainder(yaw, 2 * math.pi)
                    if rates is not None:
                        w = rates[i]
                    elif last_gyro is not None:
                        w = last_gyro
                    else:
                        w = np.full(3, math.nan)
                    counts["attitude"] += 1
                    t = float(t_att[i])
                    yield FcAttitude(t, t, roll, pitch, yaw, w)
                elif kind == _STATUS:
                    f = int(es_flags[i])
                    t = float(t_es[i])
                    counts["estimator_status"] += 1
                    yield FcEkfStatus(t, bool(f & _EST_ATTITUDE), bool(f & _EST_POS_HORIZ_ABS), f, "estimator_status",
                                      t, *(float(r) for r in es_ratios[i]))
                else:
                    armed, landed = states[i]
                    counts["flight_state"] += 1
                    t = float(t_st[i])
                    yield FcFlightState(t, t, armed, landed, "vehicle_status/vehicle_land_detected")
        self._done = self._total
        s.counts = counts
        if bad:
            s.notes.append(f"{bad} IMU samples with non-finite values skipped")
