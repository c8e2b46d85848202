"""Rest detection and the zero-rate update of method C's gyro biases (beyond the seed; VQF's rest
bias estimation, Laidig & Seel 2023, is the anchor).

Why: at rest the gyro reads its bias plus the Earth rate, so the mean rate over a rest measures the
bias directly, far better than the filters learn it in motion (the heading filter sees a vertical
bias only through a magnetometer it counts once per 30 s: a consumer gyro's 0.16 deg/s vertical
bias drifted the any-motion hand-held heading by 3 deg before this).

Rest (per sample, the filters' mean rate and specific force of a filter step): each sample's rate
and specific force within ``gyro_deviation_rad_s`` / ``accel_deviation_m_s2`` of their first-order
low-pass (time constant ``lowpass_tau_s``), and the low-passed rate within ``max_rate_rad_s`` per
axis (a steady turn is no rest; a slower one is the consuming filter's innovation gate's job), for
at least ``min_rest_s``. Defaults are VQF's (restThGyr 2 deg/s, restThAcc 0.5 m/s^2, restFilterTau
0.5 s, restMinT 1.5 s, biasClip 2 deg/s).

Measurement: when the run reaches ``min_rest_s``, the mean rate of its samples so far, then every
``chunk_s`` the mean of the new samples: chunks are disjoint, so their errors are independent. The
variance of a chunk mean (per axis, rad^2/s^2) is s^2 / n, n the chunk's count and s^2 the scatter
of the whole rest run's samples (the same sensor noise; a 25-sample chunk's own scatter is too
uncertain: its normalised errors had 4-sigma tails), floored at ``mean_sigma_floor_rad_s``^2 (a
noise-free or quantised sensor repeats its reading).

Updates (one measurement z = the chunk's mean body rate, R = its variance, gated at ``gate_chi2``
on 3 dof, Joseph form):
- attitude filter (estimators/polar_attitude: b_g and the Earth and transport rates in P are its
  states): z = b_g + C_BP (w_ie_P + w_eP_P), so with C_BP_true = (I - [eps x]) C_BP_hat and
  v = C_BP_hat W_hat, C_BP_true W = v + [v x] eps: H = [ [v x], I, 0, C_BP, C_BP, 0, 0, 0 ] (the
  last block: the gyro scale factors, which a rest does not see);
- heading filter, platform formulation (estimators/polar_heading: x = [psi_H, w_v, b(3)], its own
  body attitude C_HB in the level frame H): z = b + C_BH e_z w_v + the horizontal Earth rate, which
  is not a state there; it lies in H's level plane, so it never reaches the heading (the heading
  sees only e_z^T C_HB b) and is counted as noise, W^2 per axis: H = [0, (C_HB)_row3^T, I],
  R = diag(var) + W^2 I. psi_H itself is not updated (its gain row zeroed): the rest measures the
  bias, which stops the heading's drift from then on; what the drift already did stays in psi_H's
  variance, so a heading coasting on the gyros (a magnet nearby) keeps a sigma that only grows.

Wired in service/pipeline.py (after each filter's step, on the filter-rate mean rate and specific
force), only while the vehicle may be at rest (before a launch, as C's re-levelling: steady flight
has a steady rate and specific force too, and a slow turn is no bias). With it a 25 s coast on the gyros (tests/test_mag_disturbance_pipeline, magnet attached)
costs 0.6 deg of heading instead of 3.3.

Pure: ``rest_step(state, time_s, gyro_body_rad_s, accel_body_m_s2, params) -> (state, RestRate | None)``;
``attitude_zero_rate_update(state, rate, params)`` and ``heading_zero_rate_update(state, rate, params)``
-> (filter state, ZeroRateDiag).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from estimators.polar_attitude import I_ATT, I_BG, I_WEP, I_WIE, N_STATES, PolarAttitudeState
from estimators.polar_heading import EARTH_RATE_RAD_S, PolarHeadingState
from estimators.rotations import dcm_from_quat, quat_from_rotvec, quat_mul, skew, wrap_2pi


@dataclass(frozen=True)
class ZeroRateParams:
    gyro_deviation_rad_s: float = math.radians(2.0)
    """Largest |rate - low-passed rate| of a sample at rest (rad/s)."""
    accel_deviation_m_s2: float = 0.5
    """Largest |specific force - low-passed specific force| of a sample at rest (m/s^2)."""
    max_rate_rad_s: float = math.radians(2.0)
    """Largest |low-passed rate| per axis at rest (rad/s): bounds the bias it may report."""
    lowpass_tau_s: float = 0.5
    min_rest_s: float = 1.5
    """A run of rest samples this long (s) before the first measurement."""
    chunk_s: float = 0.5
    """Interval of the measurements after the first (s)."""
    mean_sigma_floor_rad_s: float = math.radians(0.002)
    """Floor of the sigma of a chunk's mean rate (rad/s, per axis)."""
    gate_chi2: float = 16.27
    """Innovation gate of the updates (NIS, 3 dof, 99.9 %): a slow turn taken for a rest is
    rejected once the bias is known better than that turn's rate."""

    def __post_init__(self) -> None:
        for name, v in self.__dict__.items():
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class ZeroRateState:
    time_s: float | None = None
    gyro_lp_rad_s: np.ndarray | None = None
    accel_lp_m_s2: np.ndarray | None = None
    rest_since_s: float | None = None
    """Time of the first sample of the current rest run (None: not at rest)."""
    reported: bool = False
    """The current run has given its first measurement."""
    n: int = 0
    sum_rad_s: np.ndarray | None = None
    """Count and sum of the rates not yet reported (the current chunk)."""
    run_n: int = 0
    run_sum_rad_s: np.ndarray | None = None
    run_sum_sq_rad2_s2: np.ndarray | None = None
    """Count, sum and sum of squares of the rates of the whole rest run (its scatter)."""
    chunk_start_s: float | None = None


@dataclass(frozen=True)
class RestRate:
    """A zero-rate measurement: the mean body rate over a rest (bias + Earth rate)."""
    mean_gyro_body_rad_s: np.ndarray
    variance_rad2_s2: np.ndarray
    """Per-axis variance of that mean."""
    n_samples: int
    rest_s: float
    """Length of the rest run so far (s)."""


def rest_step(state: ZeroRateState, time_s: float, gyro_body_rad_s: np.ndarray, accel_body_m_s2: np.ndarray,
              params: ZeroRateParams = ZeroRateParams()) -> tuple[ZeroRateState, RestRate | None]:
    w = np.asarray(gyro_body_rad_s, float)
    f = np.asarray(accel_body_m_s2, float)
    if not (math.isfinite(time_s) and np.all(np.isfinite(w)) and np.all(np.isfinite(f))):
        return state, None
    if state.time_s is None or time_s <= state.time_s:
        return ZeroRateState(time_s=time_s, gyro_lp_rad_s=w.copy(), accel_lp_m_s2=f.copy()), None
    a = 1.0 - math.exp(-(time_s - state.time_s) / params.lowpass_tau_s)
    w_lp = state.gyro_lp_rad_s + a * (w - state.gyro_lp_rad_s)
    f_lp = state.accel_lp_m_s2 + a * (f - state.accel_lp_m_s2)
    dw, df = w - w_lp, f - f_lp
    still = (float(dw @ dw) <= params.gyro_deviation_rad_s ** 2 and float(df @ df) <= params.accel_deviation_m_s2 ** 2
             and float(np.max(np.abs(w_lp))) <= params.max_rate_rad_s)
    base = ZeroRateState(time_s=time_s, gyro_lp_rad_s=w_lp, accel_lp_m_s2=f_lp)
    if not still:
        return base, None
    if state.rest_since_s is None:
        return replace(base, rest_since_s=time_s, n=1, sum_rad_s=w.copy(), run_n=1, run_sum_rad_s=w.copy(),
                       run_sum_sq_rad2_s2=w * w, chunk_start_s=time_s), None
    st = replace(base, rest_since_s=state.rest_since_s, reported=state.reported, n=state.n + 1,
                 sum_rad_s=state.sum_rad_s + w, run_n=state.run_n + 1, run_sum_rad_s=state.run_sum_rad_s + w,
                 run_sum_sq_rad2_s2=state.run_sum_sq_rad2_s2 + w * w, chunk_start_s=state.chunk_start_s)
    due = (time_s - st.rest_since_s + 1e-9 >= params.min_rest_s) if not st.reported \
        else (time_s - st.chunk_start_s + 1e-9 >= params.chunk_s)
    if not due or st.n < 1 or st.run_n < 2:
        return st, None
    run_mean = st.run_sum_rad_s / st.run_n
    s2 = np.maximum((st.run_sum_sq_rad2_s2 - st.run_n * run_mean * run_mean) / (st.run_n - 1), 0.0)
    var = np.maximum(s2 / st.n, params.mean_sigma_floor_rad_s ** 2)
    out = RestRate(st.sum_rad_s / st.n, var, st.n, time_s - st.rest_since_s)
    return replace(st, reported=True, n=0, sum_rad_s=np.zeros(3), chunk_start_s=time_s), out


@dataclass(frozen=True)
class ZeroRateDiag:
    fused: bool = False
    test_ratio: float = math.nan
    """NIS / gate_chi2 (> 1: rejected)."""
    reason: str = ""


def _kalman(P: np.ndarray, H: np.ndarray, z: np.ndarray, R: np.ndarray, gate_chi2: float, keep: tuple = ()):
    """(dx, P_new, test ratio) of one gated linear update; dx None when rejected. The states in
    ``keep`` are not updated (their gain rows zeroed; the Joseph form holds for any gain)."""
    S = H @ P @ H.T + R
    S_inv = np.linalg.inv(S)
    ratio = float(z @ S_inv @ z) / gate_chi2
    if not ratio <= 1.0:
        return None, P, ratio
    K = P @ H.T @ S_inv
    K[list(keep), :] = 0.0
    I_KH = np.eye(P.shape[0]) - K @ H
    P_new = I_KH @ P @ I_KH.T + K @ R @ K.T
    return K @ z, 0.5 * (P_new + P_new.T), ratio


def attitude_zero_rate_update(state: PolarAttitudeState, rate: RestRate, params: ZeroRateParams = ZeroRateParams()
                              ) -> tuple[PolarAttitudeState, ZeroRateDiag]:
    """The attitude filter's gyro bias (and Earth/transport rates in P) from a rest's mean rate."""
    if not state.initialised:
        return state, ZeroRateDiag(reason="attitude filter not levelled")
    xh = state.x_hat
    C_BP = dcm_from_quat(state.q_P_from_body).T
    v = C_BP @ (xh[6:9] + xh[9:12])
    z = rate.mean_gyro_body_rad_s - (xh[0:3] + v)
    H = np.zeros((3, N_STATES))
    H[:, I_ATT] = skew(v)
    H[:, I_BG] = np.eye(3)
    H[:, I_WIE] = C_BP
    H[:, I_WEP] = C_BP
    dx, P, ratio = _kalman(state.P, H, z, np.diag(rate.variance_rad2_s2), params.gate_chi2)
    if dx is None:
        return state, ZeroRateDiag(test_ratio=ratio, reason="rest rate gated out")
    q = quat_mul(state.q_P_from_body, quat_from_rotvec(dx[0:3]))   # C_PB <- C_PB (I + [eps x])
    q = q / math.sqrt(float(q @ q))
    return replace(state, q_P_from_body=q, x_hat=xh + dx[3:], P=P), ZeroRateDiag(True, ratio)


def heading_zero_rate_update(state: PolarHeadingState, rate: RestRate, params: ZeroRateParams = ZeroRateParams()
                             ) -> tuple[PolarHeadingState, ZeroRateDiag]:
    """The heading filter's gyro bias (platform formulation) from a rest's mean rate."""
    if not (state.initialised and state.platform and state.q_P_from_body is not None):
        return state, ZeroRateDiag(reason="heading filter not in the platform formulation")
    x = state.x
    up_body = dcm_from_quat(state.q_P_from_body)[2, :]     # e_z^T C_HB: H's vertical in body axes
    z = rate.mean_gyro_body_rad_s - (x[2:5] + up_body * x[1])
    H = np.zeros((3, len(x)))
    H[:, 1] = up_body
    H[:, 2:5] = np.eye(3)
    R = np.diag(rate.variance_rad2_s2) + np.eye(3) * EARTH_RATE_RAD_S ** 2
    dx, P, ratio = _kalman(state.P, H, z, R, params.gate_chi2, keep=(0,))
    if dx is None:
        return state, ZeroRateDiag(test_ratio=ratio, reason="rest rate gated out")
    xn = x + dx
    xn[0] = wrap_2pi(xn[0])
    return replace(state, x=xn, P=P), ZeroRateDiag(True, ratio)
