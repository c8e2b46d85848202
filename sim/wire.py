"""What the MAVLink link does to the values: units, integer quantisation, int16 saturation,
float32 rounding. Shared by the live autopilot (encode) and the offline API (encode + decode),
so offline arrays are exactly what a decoder gets from the stream.

ArduPilot RAW_IMU: xacc mG (a / 9.80665 * 1000), xgyro mrad/s, xmag mGauss, int16.
PX4 HIGHRES_IMU: float32 m/s^2, rad/s, gauss.
SCALED_PRESSURE: press_abs, press_diff hPa float32; temperature cdegC int16.
"""
from __future__ import annotations

import numpy as np

G0_M_S2 = 9.80665
INT16_MAX = 32767


def raw_imu_ints(gyro_rad_s, accel_m_s2, mag_gauss):
    """SI (n,3) -> RAW_IMU integer fields (n,3) each: (xacc mG, xgyro mrad/s, xmag mGauss).
    A NaN (dropped) magnetometer becomes 0, which is what ArduPilot sends without a compass."""
    def q(x, k):
        x = np.nan_to_num(np.asarray(x, float) * k, nan=0.0)
        return np.clip(np.rint(x), -INT16_MAX, INT16_MAX).astype(np.int64)
    return q(accel_m_s2, 1000.0 / G0_M_S2), q(gyro_rad_s, 1000.0), q(mag_gauss, 1000.0)


def raw_imu_decode(acc_mg, gyro_mrad_s, mag_mgauss):
    return (np.asarray(gyro_mrad_s, float) / 1000.0, np.asarray(acc_mg, float) * G0_M_S2 / 1000.0,
            np.asarray(mag_mgauss, float) / 1000.0)


def f32(x):
    return np.asarray(x, float).astype(np.float32).astype(float)


def imu_as_decoded(personality: str, gyro, accel, mag):
    """The IMU arrays a decoder gets back: RAW_IMU (ardupilot) or HIGHRES_IMU float32 (px4).
    A NaN row (sensor dropout) stays NaN here (offline marks missing samples as NaN)."""
    gyro, accel, mag = (np.asarray(a, float) for a in (gyro, accel, mag))
    if personality == "px4":
        return f32(gyro), f32(accel), f32(mag)
    a, g, m = raw_imu_ints(gyro, accel, mag)
    g_d, a_d, m_d = raw_imu_decode(a, g, m)
    for src, dst in ((gyro, g_d), (accel, a_d), (mag, m_d)):
        dst[np.isnan(src)] = np.nan
    return g_d, a_d, m_d


def pressure_as_decoded(press_abs_pa, press_diff_pa, temperature_k):
    """SCALED_PRESSURE round trip: hPa float32, cdegC int16."""
    pa = f32(np.asarray(press_abs_pa, float) / 100.0) * 100.0
    pd = f32(np.asarray(press_diff_pa, float) / 100.0) * 100.0
    t = np.asarray(temperature_k, float)
    cdeg = np.clip(np.rint(np.nan_to_num((t - 273.15) * 100.0)), -INT16_MAX, INT16_MAX)
    tk = cdeg / 100.0 + 273.15
    tk[np.isnan(t)] = np.nan
    return pa, pd, tk


def temperature_cdegc(temperature_k: float) -> int:
    if not np.isfinite(temperature_k):
        return 0
    return int(np.clip(round((temperature_k - 273.15) * 100.0), -INT16_MAX, INT16_MAX))
