"""Magnetometer deviation compensation by heading, roll and pitch (METHODS.md D).

Seed: US 4,870,602 (claim 1, eqs. 1a-1c, 2a-2c, 3a-3c). During a calibration manoeuvre that
sweeps all headings within roll/pitch limits, with a short-term gyro heading psi, roll phi,
pitch theta (rad) and the known local field F_N (gauss, NED, from the field model), per body
axis i in (x, y, z):

    T_ref   = C_body_from_nav(phi, theta, psi) F_N
    dT_i    = T_i_measured - T_i_ref
            = A_i + B_i sin(psi) + C_i cos(psi) + D_i phi + E_i phi^2 + F_i theta + G_i theta^2
            = h(psi, phi, theta)^T c_i,   h = [1, sin psi, cos psi, phi, phi^2, theta, theta^2]

21 coefficients (7 per axis), initialised to 0 and updated after every observation triplet by
recursive least squares. The three axes share the regressor h, so one 7x7 gain matrix P serves
all three (exactly the same as three separate RLS filters with equal priors):

    k = P h / (lambda + h^T P h);   c_i += k (dT_i - h^T c_i);   P = (P - k h^T P) / lambda

Corrected field (eq. 2-3): T_c = T_measured - h^T [c_x c_y c_z]. Corrected heading: the model
depends on the heading it corrects, so it is solved by fixed-point iteration from the
uncorrected heading (converges in a few iterations: the deviation is a small fraction of H).

Beyond the seed: coefficient covariance sigma_i^2 P (sigma_i^2 from the a-priori residuals),
a manoeuvre-coverage figure (which heading, roll and pitch bins were seen), persistence through
to_dict/from_dict (the service writes the file), and ``fit_hard_soft_iron`` for comparison.

The heading psi here is the TRUE heading of the reference (gyro heading initialised from a known
direction, claim 1 (a)); the same convention must be used when correcting.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.rotations import dcm_from_euler, wrap_2pi
from estimators.polar_heading import magnetic_heading

N_PER_AXIS = 7
N_PER_AXIS_EXTENDED = 11
COEFF_NAMES = ("A", "B", "C", "D", "E", "F", "G")
COEFF_NAMES_EXTENDED = COEFF_NAMES + ("H", "I", "J", "K")
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class DeviationParams:
    forgetting_factor: float = 1.0
    """RLS forgetting factor lambda in (0.9, 1]; 1 = plain least squares."""
    init_coeff_sigma_gauss: float = 1.0
    """Prior sigma of every coefficient (gauss per unit regressor); large = uninformative."""
    mag_noise_gauss: float = 0.002
    """Nominal magnetometer noise (gauss). P is kept normalised by the noise variance (standard
    RLS), so its prior is (init_coeff_sigma / mag_noise)^2 I; the residual sigma actually used
    for the covariance is estimated from the data."""
    roll_limit_rad: float = math.radians(30.0)
    """Roll range of the manoeuvre (coverage bins span +-roll_limit_rad)."""
    pitch_limit_rad: float = math.radians(20.0)
    heading_bins: int = 12
    """Heading bins for the coverage figure (12 x 30 deg)."""
    roll_bins: int = 6
    pitch_bins: int = 4
    min_samples_per_bin: int = 5
    """A bin counts as visited after this many observations."""
    extended: bool = False
    """Beyond the seed: add the cross terms [phi sin psi, phi cos psi, theta sin psi,
    theta cos psi] (11 coefficients per axis, 33 in all). Soft iron in a banked or pitched
    attitude produces exactly such products, which the seed's additive model cannot follow."""

    def __post_init__(self) -> None:
        if not 0.9 < self.forgetting_factor <= 1.0:
            raise ValueError(f"forgetting_factor must be in (0.9, 1], got {self.forgetting_factor}")
        for name in ("init_coeff_sigma_gauss", "mag_noise_gauss", "roll_limit_rad", "pitch_limit_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if self.roll_limit_rad > math.pi / 2 or self.pitch_limit_rad >= math.pi / 2:
            raise ValueError("roll_limit_rad must be <= pi/2 and pitch_limit_rad < pi/2")
        for name in ("heading_bins", "roll_bins", "pitch_bins", "min_samples_per_bin"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")


@dataclass(frozen=True)
class DeviationState:
    coeffs: np.ndarray
    """(7, 3): column i = [A_i .. G_i] of body axis i (gauss; per rad / rad^2 for D..G)."""
    P: np.ndarray
    """(7, 7) RLS matrix = coefficient covariance / residual variance (normalised)."""
    n: int = 0
    resid_sq_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Sum of squared normalised a-priori residuals per axis (gauss^2), after the burn-in."""
    n_resid: int = 0
    """Residuals in that sum (the first 3 x coefficients-per-axis are left out: they measure
    the prior)."""
    heading_counts: np.ndarray | None = None
    roll_counts: np.ndarray | None = None
    pitch_counts: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "DeviationState":
        kw = {}
        for k, v in d.items():
            if k in ("n", "n_resid"):
                kw[k] = int(v)
            elif v is None:
                kw[k] = None
            else:
                kw[k] = np.array(v, dtype=float if k in ("coeffs", "P", "resid_sq_sum") else np.int64)
        st = cls(**kw)
        n = st.coeffs.shape[0]
        if n not in (N_PER_AXIS, N_PER_AXIS_EXTENDED) or st.coeffs.shape != (n, 3) or st.P.shape != (n, n):
            raise ValueError("persisted deviation state has wrong shapes")
        return st


@dataclass(frozen=True)
class DeviationDiag:
    updated: bool
    residual_gauss: np.ndarray | None = None
    """A-priori residual dT - h^T c (gauss, body)."""
    reason: str = ""


@dataclass(frozen=True)
class Coverage:
    heading_fraction: float
    roll_fraction: float
    pitch_fraction: float
    overall: float
    """min of the three: the manoeuvre is only as complete as its least-covered angle."""


def deviation_init(params: DeviationParams = DeviationParams()) -> DeviationState:
    n = N_PER_AXIS_EXTENDED if params.extended else N_PER_AXIS
    return DeviationState(coeffs=np.zeros((n, 3)),
                          P=np.eye(n) * (params.init_coeff_sigma_gauss / params.mag_noise_gauss) ** 2,
                          heading_counts=np.zeros(params.heading_bins, np.int64),
                          roll_counts=np.zeros(params.roll_bins, np.int64),
                          pitch_counts=np.zeros(params.pitch_bins, np.int64))


def regressor(heading_rad: float, roll_rad: float, pitch_rad: float, extended: bool = False) -> np.ndarray:
    """h = [1, sin psi, cos psi, phi, phi^2, theta, theta^2] (eq. 1), and with ``extended``
    the cross terms [phi sin psi, phi cos psi, theta sin psi, theta cos psi]."""
    s, c = math.sin(heading_rad), math.cos(heading_rad)
    h = [1.0, s, c, roll_rad, roll_rad ** 2, pitch_rad, pitch_rad ** 2]
    if extended:
        h += [roll_rad * s, roll_rad * c, pitch_rad * s, pitch_rad * c]
    return np.array(h)


def _h(state: "DeviationState", heading_rad: float, roll_rad: float, pitch_rad: float) -> np.ndarray:
    return regressor(heading_rad, roll_rad, pitch_rad, state.coeffs.shape[0] == N_PER_AXIS_EXTENDED)


def reference_field_body(field_ned_gauss: np.ndarray, heading_rad: float, roll_rad: float,
                         pitch_rad: float) -> np.ndarray:
    """T_ref = C_body_from_nav F_N (gauss)."""
    return dcm_from_euler(roll_rad, pitch_rad, heading_rad).T @ np.asarray(field_ned_gauss, float)


def _bin(v: float, lo: float, hi: float, n: int) -> int | None:
    if not lo <= v <= hi:
        return None
    return min(n - 1, int((v - lo) / (hi - lo) * n))


def deviation_step(state: DeviationState, mag_body_gauss: np.ndarray, field_ned_gauss: np.ndarray,
                   heading_rad: float, roll_rad: float, pitch_rad: float,
                   params: DeviationParams = DeviationParams()) -> tuple[DeviationState, DeviationDiag]:
    """One observation triplet: RLS update of the 21 coefficients (eq. 1a-1c)."""
    m = np.asarray(mag_body_gauss, float)
    F = np.asarray(field_ned_gauss, float)
    if m.shape != (3,) or F.shape != (3,):
        raise ValueError("mag_body_gauss and field_ned_gauss must have shape (3,)")
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(F)) and math.isfinite(heading_rad)
            and math.isfinite(roll_rad) and math.isfinite(pitch_rad)):
        return state, DeviationDiag(False, reason="non-finite input")
    if abs(roll_rad) > params.roll_limit_rad or abs(pitch_rad) > params.pitch_limit_rad:
        return state, DeviationDiag(False, reason="outside the calibration roll/pitch limits")
    h = _h(state, heading_rad, roll_rad, pitch_rad)
    dT = m - reference_field_body(F, heading_rad, roll_rad, pitch_rad)
    lam = params.forgetting_factor
    Ph = state.P @ h
    s = lam + float(h @ Ph)
    k = Ph / s
    e = dT - h @ state.coeffs                      # a-priori residual per axis
    coeffs = state.coeffs + np.outer(k, e)
    P = (state.P - np.outer(k, Ph)) / lam
    P = 0.5 * (P + P.T)
    hc = state.heading_counts.copy()
    rc = state.roll_counts.copy()
    pc = state.pitch_counts.copy()
    hc[min(params.heading_bins - 1, int(wrap_2pi(heading_rad) / (2 * math.pi) * params.heading_bins))] += 1
    b = _bin(roll_rad, -params.roll_limit_rad, params.roll_limit_rad, params.roll_bins)
    if b is not None:
        rc[b] += 1
    b = _bin(pitch_rad, -params.pitch_limit_rad, params.pitch_limit_rad, params.pitch_bins)
    if b is not None:
        pc[b] += 1
    # e^2 / s is the a-priori residual normalised by its own variance factor (1 + h^T P h)
    burn = state.n < 3 * len(h)
    st = replace(state, coeffs=coeffs, P=P, n=state.n + 1,
                 resid_sq_sum=state.resid_sq_sum + (0.0 if burn else e * e / s),
                 n_resid=state.n_resid + (0 if burn else 1),
                 heading_counts=hc, roll_counts=rc, pitch_counts=pc)
    return st, DeviationDiag(True, residual_gauss=e)


def deviation_model(state: DeviationState, heading_rad: float, roll_rad: float, pitch_rad: float) -> np.ndarray:
    """Modelled deviation dT (gauss, body axes) at an attitude."""
    return _h(state, heading_rad, roll_rad, pitch_rad) @ state.coeffs


def residual_sigma_gauss(state: DeviationState) -> np.ndarray:
    """Per-axis residual sigma (gauss) estimated from the a-priori residuals."""
    return np.sqrt(state.resid_sq_sum / max(1, state.n_resid))


def coefficient_covariance(state: DeviationState) -> np.ndarray:
    """21x21 covariance, ordering [A_x..G_x, A_y..G_y, A_z..G_z] (axes independent);
    33x33 for the extended model."""
    s2 = residual_sigma_gauss(state) ** 2
    n = state.coeffs.shape[0]
    out = np.zeros((3 * n, 3 * n))
    for i in range(3):
        out[i * n:(i + 1) * n, i * n:(i + 1) * n] = s2[i] * state.P
    return out


def coefficients_dict(state: DeviationState) -> dict:
    """{'x': {'A': .., ..., 'G': ..}, 'y': ..., 'z': ...} (gauss; D..G per rad / rad^2)."""
    names = COEFF_NAMES_EXTENDED if state.coeffs.shape[0] == N_PER_AXIS_EXTENDED else COEFF_NAMES
    return {ax: {nm: float(state.coeffs[j, i]) for j, nm in enumerate(names)}
            for i, ax in enumerate(AXES)}


def deviation_coverage(state: DeviationState, params: DeviationParams = DeviationParams()) -> Coverage:
    k = params.min_samples_per_bin
    hf = float(np.mean(state.heading_counts >= k))
    rf = float(np.mean(state.roll_counts >= k))
    pf = float(np.mean(state.pitch_counts >= k))
    return Coverage(hf, rf, pf, min(hf, rf, pf))


def corrected_mag(state: DeviationState, mag_body_gauss: np.ndarray, heading_rad: float,
                  roll_rad: float, pitch_rad: float) -> np.ndarray:
    """T_c = T_measured - dT_model (eq. 2-3)."""
    return np.asarray(mag_body_gauss, float) - deviation_model(state, heading_rad, roll_rad, pitch_rad)


def corrected_heading(state: DeviationState, mag_body_gauss: np.ndarray, roll_rad: float,
                      pitch_rad: float, declination_rad: float, iterations: int = 6
                      ) -> tuple[float, np.ndarray]:
    """(true heading in [0, 2pi), corrected field) from a measured field (step (h) of claim 1).

    Fixed point psi_{k+1} = heading(T_m - dT(psi_k)) + declination, from the uncorrected heading.
    """
    m = np.asarray(mag_body_gauss, float)
    psi = wrap_2pi(magnetic_heading(m, roll_rad, pitch_rad)[0] + declination_rad)
    mc = m
    for _ in range(iterations):
        mc = corrected_mag(state, m, psi, roll_rad, pitch_rad)
        psi = wrap_2pi(magnetic_heading(mc, roll_rad, pitch_rad)[0] + declination_rad)
    return psi, mc


def fit_hard_soft_iron(mag_body_gauss: np.ndarray, ref_body_gauss: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batch least-squares hard/soft-iron model m = S ref + b (12 parameters), for comparison.

    Returns (S (3x3), b (3,)); correct with ref_hat = S^-1 (m - b).
    """
    m = np.asarray(mag_body_gauss, float)
    r = np.asarray(ref_body_gauss, float)
    if m.ndim != 2 or m.shape[1] != 3 or m.shape != r.shape or m.shape[0] < 4:
        raise ValueError("need (N>=4, 3) arrays of equal shape")
    X = np.hstack([r, np.ones((len(r), 1))])
    sol, *_ = np.linalg.lstsq(X, m, rcond=None)
    return sol[:3].T, sol[3]
