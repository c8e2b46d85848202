"""Flight direction u_SF in the sensor frame, and launch detection (METHODS.md A step 3).

Three cases (seed eq. 2.1-2.3), the platform's nose assumed along its flight direction:
  "vertical" : u_SF = f_rest / |f_rest|  (specific force at rest points up, along the nose)
  "inclined" : u_SF = sum_k a_k / |sum_k a_k| over the thrust phase of the boost, where
               a_k = f_k - C_SF<-ISF(t_k) f_rest_ISF is the specific force with the gravity
               reaction known from levelling removed (rotated into the current sensor frame by
               the gyro-propagated attitude): on the rail and under thrust this is the
               kinematic acceleration along the nose. Summing the vectors (not unit vectors)
               weights the strong, clean thrust samples most.
  "aligned"  : u_SF = C_SF<-body [1, 0, 0] from the configured mounting rotation.
Where two are available they are cross-checked (``angle_between``), and the elevation of u
(angle above the horizontal at launch) can be compared with a configured launcher elevation.

Launch detection: the specific-force magnitude exceeds ``|f_rest| + threshold`` for
``min_duration_s``; the reported launch time is the first sample of that run (so a caller can
replay buffered samples from the true start of motion).

Pure steps: ``boost_step(state, accel, C_sf_from_isf, time_s, params) -> state``,
``launch_detect_step(state, accel, time_s, params) -> state``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

LAUNCH_CASES = ("vertical", "inclined", "aligned")


def u_vertical(f_rest_sf_m_s2: np.ndarray) -> np.ndarray:
    """Eq. 2.1: direction of the specific force at rest (up) in SF."""
    f = np.asarray(f_rest_sf_m_s2, float)
    n = float(np.linalg.norm(f))
    if not n > 0.0:
        raise ValueError("specific force at rest is zero")
    return f / n


def u_aligned(C_body_from_sensor: np.ndarray) -> np.ndarray:
    """Eq. 2.3: body x (nose) in SF, = C_SF<-body [1,0,0] = first row of C_body<-sensor."""
    return np.asarray(C_body_from_sensor, float)[0].copy()


def elevation_rad(u_sf: np.ndarray, f_rest_sf_m_s2: np.ndarray) -> float:
    """Angle of u above the horizontal at launch (the 'up' direction is f_rest)."""
    up = u_vertical(f_rest_sf_m_s2)
    return math.asin(max(-1.0, min(1.0, float(u_sf @ up) / float(np.linalg.norm(u_sf)))))


@dataclass(frozen=True)
class BoostParams:
    window_s: float = 1.0
    """Length of the boost window after launch used for u_SF (s)."""
    min_accel_m_s2: float = 5.0
    """Samples whose gravity-free acceleration is below this are not used (coast, noise)."""
    min_samples: int = 10
    """Samples needed for a direction."""
    end_fraction: float = 0.5
    """The boost is over when |a| falls below this fraction of its peak: later samples (pull-up,
    turns, drag) are not along the nose and are not used."""

    def __post_init__(self):
        if not self.window_s > 0.0:
            raise ValueError(f"window_s must be > 0, got {self.window_s}")
        if not self.min_accel_m_s2 >= 0.0:
            raise ValueError(f"min_accel_m_s2 must be >= 0, got {self.min_accel_m_s2}")


@dataclass(frozen=True)
class BoostState:
    f_rest_isf_m_s2: np.ndarray
    """Specific force at rest (levelling mean), = ISF components of the gravity reaction."""
    launch_time_s: float
    sum_accel_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n: int = 0
    done: bool = False
    peak_m_s2: float = 0.0


def boost_init(f_rest_isf_m_s2: np.ndarray, launch_time_s: float) -> BoostState:
    return BoostState(np.asarray(f_rest_isf_m_s2, float).copy(), float(launch_time_s), np.zeros(3), 0, False, 0.0)


def boost_step(state: BoostState, accel_m_s2: np.ndarray, C_sf_from_isf: np.ndarray, time_s: float,
               params: BoostParams = BoostParams()) -> BoostState:
    """Add one sample of the boost window: a = f - C_SF<-ISF f_rest_ISF (thrust phase only)."""
    if state.done:
        return state
    if time_s - state.launch_time_s > params.window_s:
        return replace(state, done=True)
    f = np.asarray(accel_m_s2, float)
    if not np.all(np.isfinite(f)):
        return state
    a = f - C_sf_from_isf @ state.f_rest_isf_m_s2
    na = float(np.linalg.norm(a))
    peak = max(state.peak_m_s2, na)
    if state.n >= params.min_samples and na < params.end_fraction * peak:
        return replace(state, done=True, peak_m_s2=peak)        # thrust over
    if na < params.min_accel_m_s2 or na < params.end_fraction * peak:
        return replace(state, peak_m_s2=peak)
    return replace(state, sum_accel_m_s2=state.sum_accel_m_s2 + a, n=state.n + 1, peak_m_s2=peak)


def boost_direction(state: BoostState, params: BoostParams = BoostParams()) -> tuple[np.ndarray | None, str]:
    """(u_SF, '') once enough boost samples, else (None, reason)."""
    if state.n < params.min_samples:
        return None, f"{state.n} of {params.min_samples} boost samples above {params.min_accel_m_s2:.1f} m/s^2"
    s = state.sum_accel_m_s2
    return s / float(np.linalg.norm(s)), ""


# --- launch detection ------------------------------------------------------------------------

@dataclass(frozen=True)
class LaunchDetectParams:
    threshold_m_s2: float = 15.0
    """|f| must exceed the at-rest |f| by this much (about 1.5 g of thrust acceleration) ..."""
    min_duration_s: float = 0.05
    """... continuously for this long."""
    quiet_m_s2: float = 1.0
    """The launch time reported is the last sample before the run with | |f| - |f_rest| | below
    this: the start of motion, not the moment the threshold was crossed."""


@dataclass(frozen=True)
class LaunchDetectState:
    f_rest_norm_m_s2: float = 9.80665
    """|f| at rest (set it from levelling; standard gravity by default)."""
    last_quiet_s: float | None = None
    first_above_s: float | None = None
    launch_time_s: float | None = None


def launch_detect_step(state: LaunchDetectState, accel_m_s2: np.ndarray, time_s: float,
                       params: LaunchDetectParams = LaunchDetectParams()) -> LaunchDetectState:
    """Detect the start of boost; once detected, ``launch_time_s`` is the start of motion."""
    if state.launch_time_s is not None:
        return state
    f = np.asarray(accel_m_s2, float)
    if not np.all(np.isfinite(f)):
        return state
    excess = float(np.linalg.norm(f)) - state.f_rest_norm_m_s2
    quiet = state.last_quiet_s
    if abs(excess) < params.quiet_m_s2:
        quiet = time_s
    if excess <= params.threshold_m_s2:
        return LaunchDetectState(state.f_rest_norm_m_s2, quiet, None, None)
    first = time_s if state.first_above_s is None else state.first_above_s
    if time_s - first >= params.min_duration_s:
        start = quiet if quiet is not None else first
        return LaunchDetectState(state.f_rest_norm_m_s2, quiet, first, start)
    return LaunchDetectState(state.f_rest_norm_m_s2, quiet, first, None)
