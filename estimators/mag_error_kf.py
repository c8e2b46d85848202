"""KF1: magnetometer error filter (METHODS.md B2 "KF1"; seed AU756340B2 eq. 9-16).

Runs only while a trusted attitude (the flight controller's healthy estimate) is available.
Fields are normalised by the model field magnitude |B_model| (dimensionless, as the seed).

Error model (eq. 13), body frame, B = true body field (normalised):

    B_meas = B + dB,   dB = b + diag(s) B + K B
    K = [[0, k_xy, k_xz], [k_yx, 0, k_yz], [k_zx, k_zy, 0]]      (k_ij: how B_j leaks into i)

12 random-walk states (eq. 14-15): x = [b_x b_y b_z, s_x s_y s_z, k_xy k_xz k_yx k_yz k_zx k_zy],
F = I, Q = sigma_rw^2 dt I.

Measurement (eq. 9-10, 16): with C = C_nav_from_body from the trusted reference,

    z = C B_meas - B_model_nav = C dB = C D(B) x + e,    R = sigma_meas^2 I
    D(B) = d(dB)/dx = [ I3 | diag(Bx, By, Bz) | [[By Bz 0 0 0 0], [0 0 Bx Bz 0 0], [0 0 0 0 Bx By]] ]
    H = C D(B)                                                       (eq. 16)

B in D is taken as the reference-predicted body field C^T B_model_nav (noise-free, and exact
for a correct reference, so the model is exactly linear in x).

Gates: the update is skipped when |omega| exceeds ``max_rate_rad_s`` (time-alignment errors
between the magnetometer and the reference grow with the rate) and when the innovation's
Mahalanobis distance squared y^T S^-1 y exceeds ``chi2_gate`` (3 degrees of freedom).

Using the estimate (inverse of eq. 13): B = M^-1 (B_meas - b), M = I + diag(s) + K.

The Kalman mechanics are estimators/kalman.py's predict and Joseph-form update (filterpy's
arithmetic, without importing it), on the state's (x, P), so ``kf1_step`` is a pure function of
(state, inputs) and ``to_dict``/``from_dict`` reproduce a run exactly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.kalman import kf_predict, kf_update

N_STATES = 12
STATE_NAMES = ("b_x", "b_y", "b_z", "s_x", "s_y", "s_z",
               "k_xy", "k_xz", "k_yx", "k_yz", "k_zx", "k_zy")
CHI2_3DOF_99 = 11.345
KF1_DICT_VERSION = 1


@dataclass(frozen=True)
class Kf1Params:
    sigma_rw_per_sqrt_s: float = 3e-5
    """Random-walk drift of every state (normalised / sqrt(s)); seed: 1e-5 per 0.1 s update."""
    sigma_meas: float = 0.1
    """Measurement noise per field component (normalised), seed: 0.1."""
    sigma_bias_init: float = 0.05
    """Initial 1-sigma of the biases (normalised). The FC's own compass calibration is already
    applied to RAW_IMU, so KF1 learns residuals: a tight prior keeps the weakly observable
    combinations (little attitude diversity, a reference with correlated errors) near zero."""
    sigma_scale_init: float = 0.03
    """Initial 1-sigma of the scale-factor errors."""
    sigma_cross_init: float = 0.03
    """Initial 1-sigma of the cross-couplings."""
    chi2_gate: float = CHI2_3DOF_99
    """Innovation gate on y^T S^-1 y (3 dof; 11.345 = 99 %)."""
    max_rate_rad_s: float = math.radians(20.0)
    """No update above this body rate magnitude (rad/s)."""
    min_update_interval_s: float = 1.0
    """Updates are decimated to at most one per this interval (s): the reference's errors are
    correlated over many seconds, so denser updates would only feign information."""

    def __post_init__(self):
        for name in ("sigma_rw_per_sqrt_s", "sigma_meas", "sigma_bias_init", "sigma_scale_init",
                     "sigma_cross_init", "chi2_gate", "max_rate_rad_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if not (math.isfinite(self.min_update_interval_s) and self.min_update_interval_s >= 0.0):
            raise ValueError(f"min_update_interval_s must be >= 0, got {self.min_update_interval_s!r}")


@dataclass(frozen=True)
class Kf1State:
    x: np.ndarray
    """The 12 error states (see module docstring), normalised."""
    P: np.ndarray
    """12x12 covariance."""
    field_norm_gauss: float | None = None
    """|B_model| (gauss) used to normalise; the bias in gauss is b * field_norm_gauss."""
    time_s: float | None = None
    """FC time of the last update attempt (s)."""
    n_updates: int = 0
    n_rejected_chi2: int = 0
    n_rejected_rate: int = 0
    flight_count: int = 0
    """Number of flights this estimate has learnt from (the service increments it)."""
    meta: dict = field(default_factory=dict)
    """Free metadata the service attaches (e.g. wall-clock save times); JSON-serialisable."""


@dataclass(frozen=True)
class Kf1Diag:
    fused: bool
    reason: str = ""
    innovation: np.ndarray | None = None
    innovation_var: np.ndarray | None = None
    test_ratio: float = float("nan")
    """y^T S^-1 y / chi2_gate (> 1 rejected)."""


def kf1_init(params: Kf1Params = Kf1Params()) -> Kf1State:
    sig = np.r_[np.full(3, params.sigma_bias_init), np.full(3, params.sigma_scale_init),
                np.full(6, params.sigma_cross_init)]
    return Kf1State(x=np.zeros(N_STATES), P=np.diag(sig * sig))


def error_jacobian(B_body: np.ndarray) -> np.ndarray:
    """D(B) = d(dB)/dx (3x12) at the body field B (eq. 13)."""
    bx, by, bz = B_body
    D = np.zeros((3, N_STATES))
    D[:, 0:3] = np.eye(3)
    D[0, 3], D[1, 4], D[2, 5] = bx, by, bz
    D[0, 6], D[0, 7] = by, bz
    D[1, 8], D[1, 9] = bx, bz
    D[2, 10], D[2, 11] = bx, by
    return D


def error_matrix(x: np.ndarray) -> np.ndarray:
    """M = I + diag(s) + K, so that B_meas = M B + b."""
    s, k = x[3:6], x[6:12]
    return np.array([[1.0 + s[0], k[0], k[1]],
                     [k[2], 1.0 + s[1], k[3]],
                     [k[4], k[5], 1.0 + s[2]]])


def kf1_correct_mag(state_or_x, mag_body_gauss: np.ndarray,
                    field_norm_gauss: float | None = None) -> np.ndarray:
    """Corrected body field (gauss): B = M^-1 (B_meas - b |B_model|)."""
    if isinstance(state_or_x, Kf1State):
        x = state_or_x.x
        norm = state_or_x.field_norm_gauss if field_norm_gauss is None else field_norm_gauss
    else:
        x, norm = np.asarray(state_or_x, float), field_norm_gauss
    if norm is None:
        raise ValueError("field_norm_gauss unknown: the estimate has never been updated")
    return np.linalg.solve(error_matrix(x), np.asarray(mag_body_gauss, float) - x[0:3] * norm)


def kf1_step(state: Kf1State, mag_body_gauss: np.ndarray, C_nav_from_body: np.ndarray,
             field_nav_gauss: np.ndarray, omega_body_rad_s: np.ndarray, time_s: float,
             params: Kf1Params = Kf1Params()) -> tuple[Kf1State, Kf1Diag]:
    """One magnetometer sample with a trusted attitude -> updated error estimate.

    mag_body_gauss: measured field, body axes (gauss); C_nav_from_body: the trusted reference;
    field_nav_gauss: model field NED (gauss); omega_body_rad_s: body rate for the rate gate.
    """
    m = np.asarray(mag_body_gauss, dtype=float)
    Bn = np.asarray(field_nav_gauss, dtype=float)
    w = np.asarray(omega_body_rad_s, dtype=float)
    if m.shape != (3,) or Bn.shape != (3,) or w.shape != (3,):
        raise ValueError("mag_body_gauss, field_nav_gauss and omega_body_rad_s must have shape (3,)")
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(Bn)) and np.all(np.isfinite(w))
            and math.isfinite(time_s)):
        raise ValueError("kf1_step: non-finite input")
    norm = float(np.linalg.norm(Bn))
    if not norm > 0.0:
        raise ValueError("field_nav_gauss must be non-zero")
    if state.time_s is not None:
        dt = time_s - state.time_s
        if dt < params.min_update_interval_s - 1e-6:  # 1 us slack for float sample times
            return state, Kf1Diag(False, "decimated")
    else:
        dt = 0.0
    if float(np.linalg.norm(w)) > params.max_rate_rad_s:
        return (replace(state, n_rejected_rate=state.n_rejected_rate + 1),
                Kf1Diag(False, "rate gate"))
    C = np.asarray(C_nav_from_body, dtype=float)
    Bn_n = Bn / norm
    B_body = C.T @ Bn_n                    # reference-predicted body field, normalised
    z = C @ (m / norm) - Bn_n              # eq. 9-10
    H = C @ error_jacobian(B_body)         # eq. 16
    R = params.sigma_meas ** 2 * np.eye(3)
    x, P = kf_predict(state.x, state.P, np.eye(N_STATES),
                      (params.sigma_rw_per_sqrt_s ** 2 * dt) * np.eye(N_STATES))   # random walk
    y = z - H @ x
    S = H @ P @ H.T + R
    d2 = float(y @ np.linalg.solve(S, y))
    ratio = d2 / params.chi2_gate
    base = replace(state, x=x, P=P, time_s=time_s,
                   field_norm_gauss=norm if state.field_norm_gauss is None else state.field_norm_gauss)
    if ratio > 1.0:
        return (replace(base, n_rejected_chi2=state.n_rejected_chi2 + 1),
                Kf1Diag(False, "chi2 gate", y, np.diag(S).copy(), ratio))
    x, P = kf_update(x, P, z, H, R)
    P = 0.5 * (P + P.T)
    return (replace(base, x=x, P=P, n_updates=state.n_updates + 1),
            Kf1Diag(True, "", y, np.diag(S).copy(), ratio))


def kf1_sigma(state: Kf1State) -> np.ndarray:
    """1-sigma of the 12 states."""
    return np.sqrt(np.diag(state.P))


def kf1_to_dict(state: Kf1State) -> dict:
    """JSON-ready dict; floats kept exactly (Python's repr round-trips)."""
    return {"version": KF1_DICT_VERSION, "state_names": list(STATE_NAMES),
            "x": [float(v) for v in state.x], "P": [[float(v) for v in row] for row in state.P],
            "field_norm_gauss": state.field_norm_gauss, "time_s": state.time_s,
            "n_updates": state.n_updates, "n_rejected_chi2": state.n_rejected_chi2,
            "n_rejected_rate": state.n_rejected_rate, "flight_count": state.flight_count,
            "meta": dict(state.meta)}


def kf1_from_dict(d: dict) -> Kf1State:
    """Inverse of kf1_to_dict, validating shapes and values (ValueError on anything wrong)."""
    if not isinstance(d, dict) or d.get("version") != KF1_DICT_VERSION:
        raise ValueError(f"KF1 dict: unsupported version {d.get('version') if isinstance(d, dict) else d!r}")
    try:
        x = np.array(d["x"], dtype=float)
        P = np.array(d["P"], dtype=float)
        norm = d["field_norm_gauss"]
        state = Kf1State(x=x, P=P, field_norm_gauss=None if norm is None else float(norm),
                         time_s=None if d["time_s"] is None else float(d["time_s"]),
                         n_updates=int(d["n_updates"]), n_rejected_chi2=int(d["n_rejected_chi2"]),
                         n_rejected_rate=int(d["n_rejected_rate"]),
                         flight_count=int(d["flight_count"]), meta=dict(d.get("meta", {})))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"KF1 dict: missing or malformed field: {exc}") from exc
    if x.shape != (N_STATES,) or P.shape != (N_STATES, N_STATES):
        raise ValueError(f"KF1 dict: x {x.shape} / P {P.shape}, expected (12,) / (12, 12)")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        raise ValueError("KF1 dict: non-finite x or P")
    if np.any(np.diag(P) < 0.0) or not np.allclose(P, P.T, rtol=0, atol=1e-12 * max(1.0, np.abs(P).max())):
        raise ValueError("KF1 dict: P is not a covariance (negative diagonal or asymmetric)")
    return state
