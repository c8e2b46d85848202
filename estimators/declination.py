"""Magnetic declination from a 9-axis IMU at rest (METHODS.md E).

Seed: CN105486275. At rest, average gyro w_B (rad/s), specific force f_B (m/s^2) and
magnetometer m_B (gauss), body axes.

1. True heading H_g by analytic (TRIAD) alignment from gravity and Earth rate at latitude L:
       reference (NED): v1_N = g_N = [0, 0, g],  v2_N = w_ie_N = [W cos L, 0, -W sin L]
       body:            v1_B = -f_B,             v2_B = w_B
       triad(a, b) = [a/|a|, (a x b)/|a x b|, a x (a x b)/|..|]
       C_nav_from_body = triad_N triad_B^T,  H_g = yaw of C_nav_from_body.
   Only the component of w_B perpendicular to gravity carries azimuth, and it is W cos L:
   a gyro error delta w_h gives a heading error ~ delta w_h / (W cos L) rad.
2. Magnetic heading H_m from the accelerometer-levelled magnetometer
       (estimators/polar_heading.magnetic_heading, roll/pitch from f_B).
3. Declination D = H_g - H_m (east positive, as the WMM; the seed's dH = H_m - H_g is west
   positive).

Gyro-grade check (physics: Earth rate is 15 deg/h; only gyros whose bias and averaged noise are
well under W cos L can see it). The heading sigma predicted from the gyro is
    sigma_Hg = sqrt(sigma_bias^2 + sigma_white^2 / n) / (W cos L)
with sigma_bias the configured (turn-on, uncompensated) bias uncertainty of the gyro grade and
sigma_white the measured per-sample spread. Earth rate is declared RESOLVED only if
sigma_Hg <= max_heading_sigma_rad AND the measured |w_B| is consistent with W (|w_B| - W within
k sigma). Otherwise the result says why and the declination comes from the WMM (source 'wmm').

Anomaly: |D_measured - D_wmm| > anomaly_k * sqrt(sigma_meas^2 + sigma_wmm^2) + anomaly_tol_rad.

Pure: ``rest_accumulate(state, gyro, accel, mag)`` (Welford) and
``estimate_declination(state, lat_rad, wmm_declination_rad, wmm_sigma_rad, params)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimators.polar_heading import magnetic_heading
from estimators.rotations import euler_from_dcm, wrap_pi

EARTH_RATE_RAD_S = 7.292115e-5
STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class DeclinationParams:
    gyro_bias_sigma_rad_s: float = math.radians(0.5)
    """Uncompensated gyro bias uncertainty of the fitted gyro grade (rad/s): it cannot be
    separated from Earth rate at rest. Consumer MEMS ~0.1-1 deg/s, tactical ~1-10 deg/h,
    navigation/FOG ~0.01 deg/h."""
    max_heading_sigma_rad: float = math.radians(1.0)
    """Largest predicted true-heading sigma for which Earth rate counts as resolved."""
    rate_consistency_k: float = 4.0
    """| |w_B| - W | must be below k * sigma_rate (+ 0.1 W) (else: motion or bias)."""
    min_samples: int = 1000
    mag_noise_floor_gauss: float = 0.0005
    """Floor on the averaged magnetometer sigma per axis (gauss)."""
    anomaly_k: float = 3.0
    anomaly_tol_rad: float = math.radians(0.5)
    max_accel_std_m_s2: float = 0.2
    """Per-axis std of f above this: not at rest."""

    def __post_init__(self) -> None:
        for name in ("gyro_bias_sigma_rad_s", "max_heading_sigma_rad", "rate_consistency_k",
                     "mag_noise_floor_gauss", "anomaly_k", "anomaly_tol_rad", "max_accel_std_m_s2"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if not (isinstance(self.min_samples, int) and self.min_samples >= 2):
            raise ValueError(f"min_samples must be an integer >= 2, got {self.min_samples!r}")


@dataclass(frozen=True)
class RestState:
    """Welford means and sums of squared deviations of gyro, accel and mag at rest."""
    n: int = 0
    gyro_mean_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_mean_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mag_mean_gauss: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mag_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "RestState":
        return cls(**{k: (int(v) if k == "n" else np.array(v, float)) for k, v in d.items()})


@dataclass(frozen=True)
class DeclinationResult:
    source: str
    """'measured' (Earth rate resolved) or 'wmm' (fallback)."""
    declination_rad: float
    """The declination to use (east positive)."""
    sigma_rad: float
    earth_rate_resolved: bool
    message: str
    """Why Earth rate was (not) resolved, for the operator."""
    measured_declination_rad: float = math.nan
    measured_sigma_rad: float = math.nan
    true_heading_rad: float = math.nan
    true_heading_sigma_rad: float = math.nan
    magnetic_heading_rad: float = math.nan
    wmm_declination_rad: float = math.nan
    anomaly: bool = False
    anomaly_test_ratio: float = math.nan
    """|D_meas - D_wmm| / (k sigma + tol); > 1 flags a local anomaly."""


def rest_accumulate(state: RestState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                    mag_gauss: np.ndarray) -> RestState:
    g = np.asarray(gyro_rad_s, float)
    a = np.asarray(accel_m_s2, float)
    m = np.asarray(mag_gauss, float)
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a)) and np.all(np.isfinite(m))):
        return state
    n = state.n + 1
    out = {}
    for key, x, mean, m2 in (("gyro", g, state.gyro_mean_rad_s, state.gyro_m2),
                             ("accel", a, state.accel_mean_m_s2, state.accel_m2),
                             ("mag", m, state.mag_mean_gauss, state.mag_m2)):
        d = x - mean
        mean_new = mean + d / n
        out[key] = (mean_new, m2 + d * (x - mean_new))
    return RestState(n, out["gyro"][0], out["gyro"][1], out["accel"][0], out["accel"][1],
                     out["mag"][0], out["mag"][1])


def rest_from_arrays(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, mag_gauss: np.ndarray) -> RestState:
    """Batch equivalent of repeated ``rest_accumulate`` (N x 3 arrays)."""
    g, a, m = (np.asarray(x, float) for x in (gyro_rad_s, accel_m_s2, mag_gauss))
    n = len(g)
    return RestState(n, g.mean(0), ((g - g.mean(0)) ** 2).sum(0), a.mean(0), ((a - a.mean(0)) ** 2).sum(0),
                     m.mean(0), ((m - m.mean(0)) ** 2).sum(0))


def _triad(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    t1 = v1 / np.linalg.norm(v1)
    c = np.cross(v1, v2)
    t2 = c / np.linalg.norm(c)
    t3 = np.cross(t1, t2)
    return np.column_stack([t1, t2, t3])


def triad_alignment(accel_body_m_s2: np.ndarray, gyro_body_rad_s: np.ndarray, lat_rad: float,
                    earth_rate_rad_s: float = EARTH_RATE_RAD_S) -> np.ndarray:
    """C_nav_from_body from the specific force and Earth rate at rest (TRIAD, gravity first)."""
    f = np.asarray(accel_body_m_s2, float)
    w = np.asarray(gyro_body_rad_s, float)
    g_N = np.array([0.0, 0.0, 1.0])
    w_N = earth_rate_rad_s * np.array([math.cos(lat_rad), 0.0, -math.sin(lat_rad)])
    return _triad(g_N, w_N) @ _triad(-f, w).T


def estimate_declination(state: RestState, lat_rad: float, wmm_declination_rad: float,
                         wmm_sigma_rad: float, params: DeclinationParams = DeclinationParams()
                         ) -> DeclinationResult:
    """Measured declination if the gyros resolve Earth rate, else the WMM value, with the reason."""
    if not (math.isfinite(lat_rad) and abs(lat_rad) <= math.pi / 2):
        raise ValueError(f"lat_rad must be in [-pi/2, pi/2], got {lat_rad}")
    if not (math.isfinite(wmm_declination_rad) and math.isfinite(wmm_sigma_rad) and wmm_sigma_rad >= 0):
        raise ValueError("wmm_declination_rad and wmm_sigma_rad >= 0 must be finite")
    fallback = dict(source="wmm", declination_rad=wmm_declination_rad, sigma_rad=wmm_sigma_rad,
                    earth_rate_resolved=False, wmm_declination_rad=wmm_declination_rad)
    n = state.n
    if n < params.min_samples:
        return DeclinationResult(**fallback, message=f"only {n} samples at rest (need {params.min_samples}); using WMM")
    acc_std = np.sqrt(state.accel_m2 / (n - 1))
    if np.any(acc_std > params.max_accel_std_m_s2):
        return DeclinationResult(**fallback, message=f"not at rest (accel std {acc_std.max():.3f} m/s^2); using WMM")
    W_h = EARTH_RATE_RAD_S * math.cos(lat_rad)
    gyro_white = np.sqrt(state.gyro_m2 / (n - 1))
    sigma_rate = math.sqrt(params.gyro_bias_sigma_rad_s ** 2 + float(np.mean(gyro_white ** 2)) / n)
    sigma_Hg = sigma_rate / W_h if W_h > 0.0 else math.inf
    w_norm = float(np.linalg.norm(state.gyro_mean_rad_s))
    rate_dev = abs(w_norm - EARTH_RATE_RAD_S)
    f = state.accel_mean_m_s2
    roll = math.atan2(-f[1], -f[2])
    pitch = math.atan2(f[0], math.hypot(f[1], f[2]))
    psi_m, H = magnetic_heading(state.mag_mean_gauss, roll, pitch)
    if sigma_Hg > params.max_heading_sigma_rad:
        return DeclinationResult(
            **fallback, magnetic_heading_rad=psi_m,
            message=(f"gyros cannot resolve Earth rate: horizontal Earth rate W cos L = "
                     f"{math.degrees(W_h) * 3600:.2f} deg/h, gyro uncertainty "
                     f"{math.degrees(sigma_rate) * 3600:.2f} deg/h -> true-heading sigma "
                     f"{math.degrees(sigma_Hg):.1f} deg > {math.degrees(params.max_heading_sigma_rad):.1f} deg; using WMM"))
    if rate_dev > params.rate_consistency_k * sigma_rate + 0.1 * EARTH_RATE_RAD_S:
        why = "motion or uncompensated bias"
        if np.any(state.gyro_m2 == 0.0):
            why = "the gyro samples do not vary: quantised coarser than Earth rate (e.g. RAW_IMU mrad/s)"
        return DeclinationResult(
            **fallback, magnetic_heading_rad=psi_m,
            message=(f"measured rate {math.degrees(w_norm) * 3600:.2f} deg/h is inconsistent with Earth "
                     f"rate 15.04 deg/h ({why}); using WMM"))
    if np.linalg.norm(np.cross(f, state.gyro_mean_rad_s)) <= 1e-12 * np.linalg.norm(f) * EARTH_RATE_RAD_S:
        return DeclinationResult(**fallback, magnetic_heading_rad=psi_m,
                                 message="measured rate is zero or parallel to gravity: no azimuth; using WMM")
    C = triad_alignment(f, state.gyro_mean_rad_s, lat_rad)
    _, _, H_g = euler_from_dcm(C)
    # magnetometer contribution: averaged noise across the horizontal field
    mag_sigma = max(params.mag_noise_floor_gauss, float(np.sqrt(np.mean(state.mag_m2 / (n - 1)) / n)))
    sigma_Hm = mag_sigma / H
    D = wrap_pi(H_g - psi_m)
    sigma_D = math.hypot(sigma_Hg, sigma_Hm)
    bound = params.anomaly_k * math.hypot(sigma_D, wmm_sigma_rad) + params.anomaly_tol_rad
    diff = abs(wrap_pi(D - wmm_declination_rad))
    ratio = diff / bound
    msg = (f"Earth rate resolved (true-heading sigma {math.degrees(sigma_Hg):.2f} deg); measured "
           f"declination {math.degrees(D):.2f} deg vs WMM {math.degrees(wmm_declination_rad):.2f} deg")
    if ratio > 1.0:
        msg += f": LOCAL MAGNETIC ANOMALY (difference {math.degrees(diff):.2f} deg > {math.degrees(bound):.2f} deg)"
    return DeclinationResult(
        source="measured", declination_rad=D, sigma_rad=sigma_D, earth_rate_resolved=True, message=msg,
        measured_declination_rad=D, measured_sigma_rad=sigma_D, true_heading_rad=H_g,
        true_heading_sigma_rad=sigma_Hg, magnetic_heading_rad=psi_m,
        wmm_declination_rad=wmm_declination_rad, anomaly=ratio > 1.0, anomaly_test_ratio=ratio)
