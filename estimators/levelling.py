"""Levelling and gyro bias at rest (METHODS.md A step 2, "block 305").

Averages of the specific force f (m/s^2, sensor axes) and the rate (rad/s) over a still period:

    roll  phi   = atan2(-f_y, -f_z)
    pitch theta = atan2( f_x, sqrt(f_y^2 + f_z^2))

with f the specific force (at rest and level, f = [0, 0, -g] in FRD). The gyro mean is the
pre-launch gyro bias. Stillness is judged from the spread of the samples, so a vehicle that is
handled on the launcher does not level on a wrong vector.

Pure and incremental: ``levelling_step(state, gyro, accel, params) -> state`` (Welford sums), and
``levelling_result(state, params)`` that says whether there is enough still data and why not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimators.rotations import dcm_from_euler, quat_from_euler

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class LevellingParams:
    min_samples: int = 200
    """Samples needed before a result is given (1 s at 200 Hz)."""
    max_accel_std_m_s2: float = 0.3
    """Largest per-axis standard deviation of f that still counts as at rest."""
    max_gyro_std_rad_s: float = math.radians(0.5)
    """Largest per-axis standard deviation of the rate that still counts as at rest."""
    gravity_tolerance_m_s2: float = 0.8
    """| |f| - g | above this means the vehicle is not at rest (or the accel is mis-scaled)."""
    accel_bias_sigma_m_s2: float = 0.1
    """1-sigma accelerometer bias left after the FC's calibration; it tilts the levelling by
    about bias/g and no averaging removes it (0.1 m/s^2 -> 0.6 deg: consumer MEMS)."""


@dataclass(frozen=True)
class LevellingState:
    n: int = 0
    accel_mean_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_mean_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class LevellingResult:
    ok: bool
    reason: str
    roll_rad: float = math.nan
    pitch_rad: float = math.nan
    gyro_bias_rad_s: np.ndarray | None = None
    accel_mean_m_s2: np.ndarray | None = None
    roll_sigma_rad: float = math.nan
    pitch_sigma_rad: float = math.nan
    samples: int = 0


def levelling_step(state: LevellingState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> LevellingState:
    """Add one sample (Welford's running mean and sum of squared deviations).

    Per component: d = x - mean; mean' = mean + d/n; m2' = m2 + d (x - mean'). Done on Python
    floats (the same IEEE operations as the numpy form, several times cheaper on 3-vectors)."""
    g = np.asarray(gyro_rad_s, float).tolist()
    a = np.asarray(accel_m_s2, float).tolist()
    if not all(map(math.isfinite, g + a)):
        return state
    n = state.n + 1
    am, am2 = _welford(a, state.accel_mean_m_s2.tolist(), state.accel_m2.tolist(), n)
    gm, gm2 = _welford(g, state.gyro_mean_rad_s.tolist(), state.gyro_m2.tolist(), n)
    return LevellingState(n, np.array(am), np.array(am2), np.array(gm), np.array(gm2))


def _welford(x: list, mean: list, m2: list, n: int) -> tuple[list, list]:
    new_mean = []
    new_m2 = []
    for xi, mi, si in zip(x, mean, m2):
        d = xi - mi
        mn = mi + d / n
        new_mean.append(mn)
        new_m2.append(si + d * (xi - mn))
    return new_mean, new_m2


def roll_pitch_from_specific_force(f_m_s2: np.ndarray) -> tuple[float, float]:
    """Roll and pitch (rad) of the sensor frame from a specific force at rest."""
    fx, fy, fz = (float(v) for v in f_m_s2)
    return math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))


def levelling_result(state: LevellingState, params: LevellingParams = LevellingParams()) -> LevellingResult:
    if state.n < params.min_samples:
        return LevellingResult(False, f"{state.n} of {params.min_samples} still samples", samples=state.n)
    accel_std = np.sqrt(state.accel_m2 / (state.n - 1))
    gyro_std = np.sqrt(state.gyro_m2 / (state.n - 1))
    if np.max(accel_std) > params.max_accel_std_m_s2:
        return LevellingResult(False, f"accelerometer not still (std {np.max(accel_std):.3f} m/s^2)", samples=state.n)
    if np.max(gyro_std) > params.max_gyro_std_rad_s:
        return LevellingResult(False, f"gyro not still (std {math.degrees(np.max(gyro_std)):.3f} deg/s)", samples=state.n)
    f = state.accel_mean_m_s2
    norm = float(np.linalg.norm(f))
    if abs(norm - STANDARD_GRAVITY_M_S2) > params.gravity_tolerance_m_s2:
        return LevellingResult(False, f"|f| = {norm:.2f} m/s^2 is not gravity", samples=state.n)
    roll, pitch = roll_pitch_from_specific_force(f)
    # sigma of the tilt: accelerometer noise of the mean and the accelerometer bias, over |g|
    noise = float(np.linalg.norm(accel_std[:2])) / math.sqrt(state.n)
    tilt_sigma = math.hypot(noise, params.accel_bias_sigma_m_s2) / norm
    return LevellingResult(True, "", roll, pitch, state.gyro_mean_rad_s.copy(), f.copy(),
                           tilt_sigma, tilt_sigma, state.n)


def q_level_from_sensor(roll_rad: float, pitch_rad: float, yaw_rad: float = 0.0) -> np.ndarray:
    """q_nav_from_sensor for a levelled sensor with an assumed yaw (0 when heading unknown)."""
    return quat_from_euler(roll_rad, pitch_rad, yaw_rad)


def C_level_from_sensor(roll_rad: float, pitch_rad: float) -> np.ndarray:
    return dcm_from_euler(roll_rad, pitch_rad, 0.0)
