"""PX4 ULog (.ulg) -> typed samples, with pyulog.

Topics (instance 0) and what they become (PX4 uORB units; body frame FRD, NED):

====================== ========================================== ==============================
topic                  fields                                     sample
====================== ========================================== ==============================
sensor_combined        gyro_rad[3] rad/s, accelerometer_m_s2[3]   ImuSample (time: timestamp;
                       m/s^2 (specific force: [0,0,-g] at rest)   the accel at +accelerometer_
                                                                  timestamp_relative is the same
                                                                  sample, as PX4 pairs them)
vehicle_magnetometer   magnetometer_ga[3] gauss (calibrated,      ImuSample.mag_gauss, held from
                       rotated to the body)                       the last sample <= the IMU time
 (old logs)            sensor_combined.magnetometer_ga[3] when     and at most MAG_MAX_AGE_S old
                       its *_timestamp_relative is valid
vehicle_air_data       baro_pressure_pa Pa, baro_temp_celcius C   PressureSample (abs Pa, K)
 (old logs)            sensor_combined.baro_alt_meter: pressure    PressureSample; noted
                       by the ISA inverse PX4 used (QNH 1013.25)
differential_pressure  differential_pressure_filtered_pa (or      PressureSample.press_diff_pa,
                       differential_pressure_pa) Pa               held (PRESS_DIFF_MAX_AGE_S)
airspeed               indicated_airspeed_m_s: q = rho0/2 IAS |IAS|  when differential_pressure
                       (rho0 = 1.225 kg/m^3, IAS's definition)       is logged below 5 Hz; noted
vehicle_attitude       q[4] Hamilton wxyz, q_nav_from_body (NED    FcAttitude (ZYX Euler; yaw
                       from FRD); rollspeed.. if logged            (-pi, pi]); rates: rollspeed..
                                                                   if logged, else the last gyro
vehicle_gps_position / fix_type >= 3: lat, lon (1e-7 deg), alt     the site (first fix)
sensor_gps / home_position                                          (mm)
====================== ========================================== ==============================

Times are the FC's boot clock in microseconds (``timestamp_sample`` where the topic has it);
``time_rx_s`` = ``time_fc_s`` (there is no receive clock in a log).
"""
from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path
from typing import Iterator

import numpy as np

from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from service.logreaders import LogError, LogSite, LogSummary, decimal_year_from_unix

MAG_MAX_AGE_S = 0.5
"""A magnetometer sample older than this is not attached to an IMU sample (mag_gauss None)."""
PRESS_DIFF_MAX_AGE_S = 1.0
"""A differential pressure older than this is not attached to a baro sample."""
RHO0_KG_M3 = 1.225
"""Sea-level ISA density: IAS is defined by q = rho0/2 IAS^2."""
_REL_INVALID = 2147483647
"""PX4's RELATIVE_TIMESTAMP_INVALID (int32 max): that sensor is absent from sensor_combined."""
_ZERO_C_K = 273.15

_TOPICS = ["sensor_combined", "vehicle_magnetometer", "vehicle_air_data", "differential_pressure",
           "airspeed", "vehicle_attitude", "vehicle_gps_position", "sensor_gps", "home_position"]

# event kinds, in the order that ties are resolved (a reference/pressure at the IMU time first)
_ATT, _PRESS, _IMU = 0, 1, 2


def _isa_pressure_pa(alt_m: np.ndarray) -> np.ndarray:
    """Inverse of PX4's ISA altitude (T0 288.15 K, L -0.0065 K/m, p0 101325 Pa)."""
    return 101325.0 * (1.0 - 0.0065 * alt_m / 288.15) ** (9.80665 / (287.05 * 0.0065))


class UlogReader:
    """``items()`` yields ImuSample, PressureSample and FcAttitude in FC-time order."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.summary = LogSummary(kind="ulog", autopilot="px4")
        try:
            from pyulog import ULog
        except ImportError:
            raise LogError("reading .ulg needs pyulog: pip install pyulog") from None
        said = io.StringIO()
        try:
            with contextlib.redirect_stdout(said):  # pyulog prints its warnings
                self.ulog = ULog(str(self.path), _TOPICS)
        except Exception as exc:  # noqa: BLE001 - pyulog raises anything on a corrupt file
            raise LogError(f"{self.path}: not a readable PX4 ULog ({type(exc).__name__}: {exc})") from None
        self._data = {}
        for d in self.ulog.data_list:
            if d.multi_id == 0 and d.name not in self._data:
                self._data[d.name] = d.data
        self._done = 0
        self._total = 1
        if "sensor_combined" not in self._data or len(self._data["sensor_combined"]["timestamp"]) == 0:
            raise LogError(f"{self.path}: no sensor_combined topic (no IMU data) in this ULog")
        if getattr(self.ulog, "file_corruption", False) or "corrupt" in said.getvalue().lower():
            self.summary.notes.append("pyulog reports file corruption: data after the damage may be missing")

    def _topic(self, name: str) -> dict | None:
        d = self._data.get(name)
        if d is None or len(d.get("timestamp", ())) == 0:
            return None
        return d

    @staticmethod
    def _time_s(d: dict) -> np.ndarray:
        t = d.get("timestamp_sample", d["timestamp"])
        return np.asarray(t, dtype=np.float64) * 1e-6

    # --- site and date ---------------------------------------------------------------------------

    def site(self) -> LogSite | None:
        for name in ("vehicle_gps_position", "sensor_gps"):
            d = self._topic(name)
            if d is None:
                continue
            fix = np.asarray(d.get("fix_type", np.zeros(1)))
            if "lat" in d:
                lat, lon, alt = np.asarray(d["lat"]) * 1e-7, np.asarray(d["lon"]) * 1e-7, np.asarray(d["alt"]) * 1e-3
            elif "latitude_deg" in d:
                lat, lon, alt = (np.asarray(d["latitude_deg"]), np.asarray(d["longitude_deg"]),
                                 np.asarray(d["altitude_msl_m"]))
            else:
                continue
            ok = np.nonzero((fix >= 3) & ((lat != 0) | (lon != 0)))[0]
            if ok.size:
                i = ok[0]
                return LogSite(float(lat[i]), float(lon[i]), float(alt[i]), f"{name} (fix type {int(fix[i])})")
        d = self._topic("home_position")
        if d is not None and "lat" in d:
            return LogSite(float(d["lat"][0]), float(d["lon"][0]), float(d["alt"][0]), "home_position")
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

    # --- streams ---------------------------------------------------------------------------------

    def _streams(self):
        s = self.summary
        sc = self._data["sensor_combined"]
        t_imu = self._time_s(sc)
        gyro = np.column_stack([sc[f"gyro_rad[{i}]"] for i in range(3)]).astype(np.float64)
        accel = np.column_stack([sc[f"accelerometer_m_s2[{i}]"] for i in range(3)]).astype(np.float64)

        # magnetometer
        t_mag = mag = None
        vm = self._topic("vehicle_magnetometer")
        if vm is not None:
            t_mag = self._time_s(vm)
            mag = np.column_stack([vm[f"magnetometer_ga[{i}]"] for i in range(3)]).astype(np.float64)
        elif "magnetometer_ga[0]" in sc:
            rel = np.asarray(sc["magnetometer_timestamp_relative"])
            ok = rel != _REL_INVALID
            if ok.any():
                t_mag = (np.asarray(sc["timestamp"], np.float64)[ok] + rel[ok]) * 1e-6
                mag = np.column_stack([sc[f"magnetometer_ga[{i}]"] for i in range(3)]).astype(np.float64)[ok]
                order = np.argsort(t_mag, kind="stable")
                t_mag, mag = t_mag[order], mag[order]
                s.notes.append("magnetometer from sensor_combined.magnetometer_ga (old ULog)")

        # barometer
        t_baro = p_abs = temp_k = None
        ad = self._topic("vehicle_air_data")
        if ad is not None:
            t_baro = self._time_s(ad)
            p_abs = np.asarray(ad["baro_pressure_pa"], np.float64)
            temp_k = np.asarray(ad["baro_temp_celcius"], np.float64) + _ZERO_C_K
        elif "baro_alt_meter" in sc:
            rel = np.asarray(sc["baro_timestamp_relative"])
            ok = rel != _REL_INVALID
            if ok.any():
                t_baro = (np.asarray(sc["timestamp"], np.float64)[ok] + rel[ok]) * 1e-6
                p_abs = _isa_pressure_pa(np.asarray(sc["baro_alt_meter"], np.float64)[ok])
                temp_k = np.asarray(sc["baro_temp_celcius"], np.float64)[ok] + _ZERO_C_K
                s.notes.append("barometric pressure from sensor_combined.baro_alt_meter by the ISA "
                               "inverse (old ULog: PX4 logged altitude, not pressure)")

        # differential pressure (airspeed sensor)
        t_dp = dp = None
        dpt = self._topic("differential_pressure")
        asp = self._topic("airspeed")
        if dpt is not None:
            t = self._time_s(dpt)
            rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
            key = "differential_pressure_filtered_pa" if "differential_pressure_filtered_pa" in dpt \
                else "differential_pressure_pa"
            if rate >= 5.0 or asp is None:
                t_dp, dp = t, np.asarray(dpt[key], np.float64)
            else:
                s.notes.append(f"differential_pressure is logged at {rate:.1f} Hz only: using airspeed instead")
        if t_dp is None and asp is not None:
            t_dp = self._time_s(asp)
            ias = np.asarray(asp["indicated_airspeed_m_s"], np.float64)
            dp = 0.5 * RHO0_KG_M3 * ias * np.abs(ias)
            s.notes.append("differential pressure from airspeed.indicated_airspeed_m_s: q = rho0/2 IAS|IAS|")

        # reference attitude
        t_att = q = rates = None
        va = self._topic("vehicle_attitude")
        if va is not None:
            t_att = self._time_s(va)
            q = np.column_stack([va[f"q[{i}]"] for i in range(4)]).astype(np.float64)
            if "rollspeed" in va:
                rates = np.column_stack([va["rollspeed"], va["pitchspeed"], va["yawspeed"]]).astype(np.float64)
        return (t_imu, gyro, accel, t_mag, mag, t_baro, p_abs, temp_k, t_dp, dp, t_att, q, rates)

    def items(self) -> Iterator:
        from estimators.rotations import euler_from_quat
        (t_imu, gyro, accel, t_mag, mag, t_baro, p_abs, temp_k, t_dp, dp, t_att, q, rates) = self._streams()
        s = self.summary
        n_imu = len(t_imu)
        # magnetometer held onto the IMU samples (the last one <= t, if not older than MAG_MAX_AGE_S)
        mag_idx = np.full(n_imu, -1)
        if t_mag is not None:
            j = np.searchsorted(t_mag, t_imu, side="right") - 1
            ok = (j >= 0) & (t_imu - t_mag[np.maximum(j, 0)] <= MAG_MAX_AGE_S)
            mag_idx = np.where(ok, j, -1)
        dp_idx = None
        if t_baro is not None and t_dp is not None:
            j = np.searchsorted(t_dp, t_baro, side="right") - 1
            ok = (j >= 0) & (t_baro - t_dp[np.maximum(j, 0)] <= PRESS_DIFF_MAX_AGE_S)
            dp_idx = np.where(ok, j, -1)
        # one merged, stable time order of all events
        parts_t = [t_imu]
        parts_k = [np.full(n_imu, _IMU, np.int8)]
        parts_i = [np.arange(n_imu)]
        for t, kind in ((t_baro, _PRESS), (t_att, _ATT)):
            if t is not None:
                parts_t.append(t)
                parts_k.append(np.full(len(t), kind, np.int8))
                parts_i.append(np.arange(len(t)))
        all_t = np.concatenate(parts_t)
        all_k = np.concatenate(parts_k)
        all_i = np.concatenate(parts_i)
        order = np.lexsort((all_k, all_t))
        self._total = len(order)
        # python floats/arrays once, not per sample
        t_imu_l = t_imu.tolist()
        last_gyro = None
        bad = 0
        counts = {"imu": 0, "imu_with_mag": 0, "pressure": 0, "pressure_with_diff": 0, "attitude": 0}
        for n, e in enumerate(order.tolist()):
            self._done = n
            kind, i = all_k[e], int(all_i[e])
            if kind == _IMU:
                g = gyro[i]
                if not (np.all(np.isfinite(g)) and np.all(np.isfinite(accel[i]))):
                    bad += 1
                    continue
                m = mag_idx[i]
                mg = mag[m] if m >= 0 else None
                counts["imu"] += 1
                counts["imu_with_mag"] += mg is not None
                last_gyro = g
                yield ImuSample(t_imu_l[i], t_imu_l[i], g, accel[i], mg, "sensor_combined", 0)
            elif kind == _PRESS:
                t = float(t_baro[i])
                diff = None
                if dp_idx is not None and dp_idx[i] >= 0:
                    diff = float(dp[dp_idx[i]])
                counts["pressure"] += 1
                counts["pressure_with_diff"] += diff is not None
                tk = float(temp_k[i])
                yield PressureSample(t, t, float(p_abs[i]), diff, tk if math.isfinite(tk) else None,
                                     "vehicle_air_data")
            else:
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
        self._done = self._total
        s.counts = counts
        if bad:
            s.notes.append(f"{bad} IMU samples with non-finite values skipped")
