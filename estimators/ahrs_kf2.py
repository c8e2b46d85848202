"""KF2: the 9-state closed-loop error filter of the synthetic AHRS (METHODS.md B2; seed
AU756340B2 eq. 17-37). Frames: NED nav, FRD body; fields normalised by |B_model| (as KF1).

Integration (eq. 18, the nav-frame rate neglected): C_dot = C [omega x], done on the quaternion
q_nav_from_body with the bias-corrected gyro  omega_c = omega_meas - b_hat  (trapezoidal increment,
right-multiplied: q <- q * q(dtheta)).

Error states x = [gamma (3), db_g (3), dbeta (3)]:
- gamma: small rotation of the body frame, C_true = C_hat (I + [gamma x])   (seed eq. 27-28);
- db_g = b_g - b_hat: gyro-bias error (rad/s), first-order Markov, tau ~ hours (eq. 30);
- dbeta: residual magnetometer bias in body axes (normalised) after KF1 (eq. 31).

Error dynamics. With omega_c = omega + db_g and C_hat_dot = C_hat [omega_c x], differentiating
C_true = C_hat (I + Gamma) and keeping first-order terms gives Gamma_dot = Gamma W - W Gamma -
[db_g x] with W = [omega x]; since [a x][b x] - [b x][a x] = [(a x b) x]:

    gamma_dot = -[omega x] gamma - db_g          (seed eq. 29)
    db_g_dot  = -db_g / tau_g + u_g              (eq. 30), E[u u] = 2 sigma_g^2 / tau_g
    dbeta_dot = -dbeta / tau_b + u_b             (eq. 31)

Phi = I + A dt + (A dt)^2 / 2 over the covariance period (eq. 33); Q diagonal, the gamma part
including the gyro scale-factor errors (seed: ~2 %): q_gamma = n_arw^2 + (s_g |omega|)^2 t_s.

Measurements (all residuals z = measured - predicted, H x):
- magnetometer (eq. 21, here resolved in body axes, equivalent): m = C^T B_n + beta + e, so with
  b0 = C_hat^T B_n:  z = m - b0 - beta_hat = [b0 x] gamma + dbeta;  H = [[b0 x], 0, I].
  (C^T = (I - Gamma) C_hat^T, and -gamma x b0 = b0 x gamma.)
- air-data roll/pitch (eq. 22, 24, 25): z = [phi_ref - phi_hat, theta_ref - theta_hat].
  A body rotation gamma changes the Euler angles by T(phi, theta) gamma (euler_kinematics), so
  H_gamma = rows 1-2 of T. phi_ref = atan(v psi_dot / g) uses the gyro-derived psi_dot =
  (sin(phi) q + cos(phi) r)/cos(theta), which carries the bias error:
  d phi_ref / d db_g = k [0, sin(phi), cos(phi)] / cos(theta), k = (v/g) / (1 + (v psi_dot/g)^2)
  (the seed's h44-h46).
- reference attitude (while the FC is trusted): z = euler_fc - euler_hat (yaw wrapped) = T gamma.

Every measurement is gated per component: |y_i| <= n_gate sqrt(S_ii) (seed: 1-2 sigma; the
default here is 3 because the seed's gate rejects 5-30 % of good data). After every update the
estimated errors are fed back (closed loop, seed "wire 17/18"): q <- q * q(gamma),
b_hat <- b_hat + db_g, beta_hat <- beta_hat + dbeta, x <- 0.

Consider parameters (Schmidt; not estimated, their effect tracked). The magnetometer's errors that
KF2 does not model, c = [s (3), k (6), dD] (NC = 10): the scale factors and cross-couplings KF1's
model carries (after KF1's correction, their residual; normalised) and the declination error of the
model field (rad, the true horizontal field turned east of the model's). The measured field then is
m_n = C^T B_n / |B| + beta + D_c c + e with, at the predicted body field b0 = C_hat^T B_n / |B|,

    D_c = [ D(b0)[:, 3:12] | C_hat^T (d x B_n) / |B| ],   d = [0, 0, 1] (down): d x B_n = [-B_E, B_N, 0]

(D(B) = d(dB)/dx of KF1, mag_error_kf.error_jacobian; a declination dD turns B_n about down by dD).
KF2 takes z = H x + e, so its error e = x_true - x_hat has a part linear in c, e = e_f + S c, with
the sensitivity S = de/dc (9 x NC, ``consider_sens``; 0 at the start and wherever the attitude is
taken anew). With KF2's own gain K (unchanged: the estimates are those of the filter without it):

    propagation:          S <- Phi S
    update (z = Hx + D c): S <- (I - K H) S - K D     (D = D_c for the magnetometer, 0 otherwise)
    an unseen interval:   the Markov rows decay as their states (S_b <- a S_b)

so the error covariance is P + S P_c S^T (c independent of the noises; P_c the caller's, e.g. KF1's
covariance). A magnetometer that learnt the gyro bias with a wrong heading leaves it in S's bias
rows, and while the magnetometer is not fused (disturbed, rejected) gamma_dot = -db_g turns it into a
heading sensitivity growing with the time coasted. The magnetometer-heading update has D =
dz/dm D(b0)[:, 3:12] for the soft iron (dz/dm: its H's dbeta columns) and -1 for dD.

The Kalman mechanics are estimators/kalman.py's predict and Joseph-form update (the same
arithmetic as filterpy's KalmanFilter, without importing it), on the state's (x, P) at every call,
so the step functions are pure.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from estimators.kalman import kf_predict, kf_update
from estimators.mag_error_kf import error_jacobian
from estimators.records import fast_replace

from estimators.euler_kinematics import body_rate_matrix, euler_rate_matrix, euler_rate_matrix_reported
from estimators.rotations import (dcm_from_quat, euler_from_dcm, quat_from_euler, quat_from_rotvec,
                                  quat_mul, skew, wrap_pi)

N = 9
NC = 10
"""Consider parameters: s_x s_y s_z k_xy k_xz k_yx k_yz k_zx k_zy (mag_error_kf's order), dD."""
G_M_S2 = 9.80665



_upd = fast_replace

@dataclass(frozen=True)
class Kf2Params:
    gyro_noise_rad_s_rthz: float = math.radians(0.015)
    """Gyro angle random walk (rad/s/sqrt(Hz) = rad/sqrt(s))."""
    gyro_scale_sigma: float = 0.01
    """1-sigma gyro scale-factor error (seed: ~2 %), enters Q_gamma with |omega|."""
    gyro_scale_corr_s: float = 1.0
    """Correlation time used to turn the scale-factor error into process noise (s)."""
    gyro_bias_sigma_rad_s: float = math.radians(0.1)
    """Steady-state 1-sigma of the gyro-bias Markov process (rad/s)."""
    gyro_bias_tau_s: float = 3600.0
    mag_bias_sigma: float = 0.05
    """Steady-state 1-sigma of the residual magnetometer bias (normalised)."""
    mag_bias_tau_s: float = 3600.0
    mag_sigma: float = 0.02
    """Magnetometer measurement noise per component (normalised; the seed's 0.1 is for a
    fighter's interference level)."""
    mag_gate_sigma: float = 3.0
    mag_norm_tolerance: float = 0.15
    """| |m| / |B_model| - 1 | above this: magnetic disturbance, no magnetometer update."""
    max_mag_rate_rad_s: float = math.radians(60.0)
    """No magnetometer update above this body rate (time-alignment errors)."""
    air_gate_sigma: float = 3.0
    ref_gate_sigma: float = 5.0
    ref_reset_rad: float = math.radians(10.0)
    """A reference residual larger than this re-initialises the attitude to the reference."""
    cov_period_s: float = 0.05
    """The covariance is propagated every this many seconds (attitude at every IMU sample)."""
    max_dt_s: float = 0.1
    """Larger IMU gaps are not integrated (reported); the attitude covariance then grows as for an
    unseen interval (``kf2_unseen``)."""
    unseen_tilt_rate_sigma_rad_s: float = math.radians(10.0)
    """Over an interval not seen (a gap, a restarted clock) the vehicle kept manoeuvring: roll and
    pitch sigma grow by this rate x the interval (rad/s) ..."""
    unseen_tilt_max_sigma_rad: float = math.radians(30.0)
    """... up to this (rad); the same as method C's attitude filter (polar_attitude_unseen)."""
    unseen_heading_rate_sigma_rad_s: float = math.radians(20.0)
    """Heading sigma growth over an unseen interval (rad/s; a coordinated turn is 10-30 deg/s) ..."""
    unseen_heading_max_sigma_rad: float = math.pi
    """... up to this (rad): after a few unseen seconds the heading is as good as unknown (as method
    C's heading filter, polar_heading_unseen)."""
    sigma_att_init_rad: float = math.radians(5.0)
    sigma_heading_init_rad: float = math.radians(30.0)
    sigma_gyro_bias_init_rad_s: float = math.radians(0.3)
    sigma_mag_bias_init: float = 0.05

    def __post_init__(self):
        for name, v in self.__dict__.items():
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class Kf2State:
    q_nav_from_body: np.ndarray
    gyro_bias_rad_s: np.ndarray
    """b_hat, body axes (rad/s)."""
    mag_bias: np.ndarray
    """beta_hat, residual magnetometer bias, body axes, normalised."""
    P: np.ndarray
    """9x9 error covariance."""
    time_s: float | None = None
    """FC time of the last IMU sample."""
    omega_prev_rad_s: np.ndarray | None = None
    """Last bias-corrected body rate (trapezoidal integration)."""
    cov_time_s: float | None = None
    """FC time up to which P has been propagated."""
    acc_angle_rad: np.ndarray | None = None
    """Sum of omega dt since cov_time_s (mean rate for Phi)."""
    acc_omega_sq: float = 0.0
    """Sum of |omega|^2 dt since cov_time_s (scale-factor noise)."""
    n_mag_fused: int = 0
    n_mag_rejected: int = 0
    n_mag_gated: int = 0
    """Of n_mag_rejected: by the innovation gate (the filter disagrees with its measurement), not
    by the field-magnitude or rate gates (the sample was judged disturbed)."""
    n_air_fused: int = 0
    n_air_rejected: int = 0
    n_ref_fused: int = 0
    n_ref_rejected: int = 0
    n_resets: int = 0
    consider_sens: np.ndarray | None = None
    """S = d(error state)/d(consider parameters), 9 x NC (module docstring); None: zero."""


@dataclass(frozen=True)
class Kf2Diag:
    fused: bool
    reason: str = ""
    innovation: np.ndarray | None = None
    innovation_var: np.ndarray | None = None
    test_ratio: float = float("nan")
    """max_i |y_i| / (n_gate sqrt(S_ii)); > 1 rejected."""


def kf2_init(q_nav_from_body: np.ndarray, params: Kf2Params = Kf2Params(),
             gyro_bias_rad_s: np.ndarray | None = None, sigma_tilt_rad: float | None = None,
             sigma_heading_rad: float | None = None, mag_bias: np.ndarray | None = None) -> Kf2State:
    """Start KF2 at an attitude; sigmas default to the params' initial values."""
    st = params.sigma_att_init_rad if sigma_tilt_rad is None else sigma_tilt_rad
    sh = params.sigma_heading_init_rad if sigma_heading_rad is None else sigma_heading_rad
    q = np.asarray(q_nav_from_body, dtype=float)
    q = q / math.sqrt(float(q @ q))
    P = np.zeros((N, N))
    P[0:3, 0:3] = _gamma_cov_from_euler_sigmas(q, st, sh)
    P[3:6, 3:6] = np.eye(3) * params.sigma_gyro_bias_init_rad_s ** 2
    P[6:9, 6:9] = np.eye(3) * params.sigma_mag_bias_init ** 2
    return Kf2State(q_nav_from_body=q,
                    gyro_bias_rad_s=np.zeros(3) if gyro_bias_rad_s is None else np.asarray(gyro_bias_rad_s, float).copy(),
                    mag_bias=np.zeros(3) if mag_bias is None else np.asarray(mag_bias, float).copy(), P=P)


def _gamma_cov_from_euler_sigmas(q: np.ndarray, sigma_tilt: float, sigma_heading: float) -> np.ndarray:
    """Body-frame gamma covariance for given roll/pitch and heading sigmas: gamma = W d_euler."""
    roll, pitch, _ = euler_from_dcm(dcm_from_quat(q))
    W = body_rate_matrix(roll, pitch)
    return W @ np.diag([sigma_tilt ** 2, sigma_tilt ** 2, sigma_heading ** 2]) @ W.T


def kf2_euler_and_cov(state: Kf2State) -> tuple[np.ndarray, np.ndarray]:
    """(roll, pitch, heading) in rad (heading [0, 2pi)) and their 3x3 covariance T P_gamma T^T
    (at |pitch| = 90 deg roll and heading sigma are huge, not an error: euler_rate_matrix_reported)."""
    e = np.array(euler_from_dcm(dcm_from_quat(state.q_nav_from_body)))
    T = euler_rate_matrix_reported(e[0], e[1])
    return e, T @ state.P[0:3, 0:3] @ T.T


def _propagate_cov(state: Kf2State, params: Kf2Params) -> Kf2State:
    """Apply the accumulated interval to P: Phi = I + A dt + (A dt)^2/2, Q diagonal."""
    if state.cov_time_s is None or state.time_s is None or state.acc_angle_rad is None:
        return state
    dt = state.time_s - state.cov_time_s
    if dt <= 0.0:
        return state
    w_mean = state.acc_angle_rad / dt
    A = np.zeros((N, N))
    A[0:3, 0:3] = -skew(w_mean)
    A[0:3, 3:6] = -np.eye(3)
    A[3:6, 3:6] = -np.eye(3) / params.gyro_bias_tau_s
    A[6:9, 6:9] = -np.eye(3) / params.mag_bias_tau_s
    Ad = A * dt
    Phi = np.eye(N) + Ad + 0.5 * Ad @ Ad
    q_g = params.gyro_noise_rad_s_rthz ** 2 * dt + (params.gyro_scale_sigma ** 2 * params.gyro_scale_corr_s
                                                     * state.acc_omega_sq)
    q_b = 2.0 * params.gyro_bias_sigma_rad_s ** 2 / params.gyro_bias_tau_s * dt
    q_m = 2.0 * params.mag_bias_sigma ** 2 / params.mag_bias_tau_s * dt
    _, P = kf_predict(np.zeros(N), state.P, Phi, np.diag([q_g] * 3 + [q_b] * 3 + [q_m] * 3))
    S = state.consider_sens
    return _upd(state, P=0.5 * (P + P.T), cov_time_s=state.time_s,
                   acc_angle_rad=np.zeros(3), acc_omega_sq=0.0,
                   consider_sens=None if S is None else Phi @ S)     # S <- Phi S


def kf2_propagate(state: Kf2State, params: Kf2Params = Kf2Params()) -> Kf2State:
    """P propagated up to the last IMU sample (what every update does first)."""
    return _propagate_cov(state, params)


def kf2_heading_var(state: Kf2State) -> float:
    """Variance of the heading (rad^2): element [2, 2] of ``kf2_euler_and_cov``."""
    return float(kf2_euler_and_cov(state)[1][2, 2])


def kf2_unseen(state: Kf2State, unseen_s: float, params: Kf2Params = Kf2Params()) -> Kf2State:
    """Account for ``unseen_s`` seconds without IMU samples (a gap; a restarted clock, reported by
    the caller). The attitude is kept, its covariance grows as method C's does over an unseen
    interval (polar_attitude_unseen / polar_heading_unseen), here in Euler terms mapped to the body
    rotation gamma = W d_euler (W = body_rate_matrix, as ``kf2_init``):

        P_gamma <- P_gamma + W diag(s_t^2, s_t^2, s_h^2) W^T + (sigma_bg unseen_s)^2 I
        s_t = min(unseen_tilt_rate_sigma * unseen_s, unseen_tilt_max_sigma)
        s_h = min(unseen_heading_rate_sigma * unseen_s, unseen_heading_max_sigma)

    (the last term: the gyro-bias error over the interval, as before). The Markov states relax
    over the interval (means are zero in the closed-loop error filter, so only P changes:
    P_b <- a^2 P_b + (1 - a^2) sigma^2, a = exp(-unseen_s / tau)). The caller restarts the time."""
    if not (math.isfinite(unseen_s) and unseen_s >= 0.0):
        raise ValueError(f"unseen_s must be finite and >= 0, got {unseen_s!r}")
    s_t = min(params.unseen_tilt_rate_sigma_rad_s * unseen_s, params.unseen_tilt_max_sigma_rad)
    s_h = min(params.unseen_heading_rate_sigma_rad_s * unseen_s, params.unseen_heading_max_sigma_rad)
    a = np.ones(N)
    a[3:6] = math.exp(-unseen_s / params.gyro_bias_tau_s)
    a[6:9] = math.exp(-unseen_s / params.mag_bias_tau_s)
    P = a[:, None] * state.P * a[None, :]
    P[3:6, 3:6] += np.eye(3) * (1.0 - a[3] ** 2) * params.gyro_bias_sigma_rad_s ** 2
    P[6:9, 6:9] += np.eye(3) * (1.0 - a[6] ** 2) * params.mag_bias_sigma ** 2
    P[0:3, 0:3] += (_gamma_cov_from_euler_sigmas(state.q_nav_from_body, s_t, s_h)
                    + np.eye(3) * (params.gyro_bias_sigma_rad_s * unseen_s) ** 2)
    S = state.consider_sens
    return _upd(state, P=0.5 * (P + P.T), consider_sens=None if S is None else a[:, None] * S)


def kf2_predict(state: Kf2State, gyro_body_rad_s: np.ndarray, time_s: float,
                params: Kf2Params = Kf2Params()) -> tuple[Kf2State, Kf2Diag]:
    """One IMU sample: integrate the attitude (every sample) and P (every cov_period_s)."""
    w = np.asarray(gyro_body_rad_s, dtype=float) - state.gyro_bias_rad_s
    if w.shape != (3,) or not np.isfinite(w).all() or not math.isfinite(time_s):
        return state, Kf2Diag(False, "non-finite gyro sample")
    if state.time_s is None or state.omega_prev_rad_s is None:
        return (_upd(state, time_s=time_s, omega_prev_rad_s=w, cov_time_s=time_s,
                        acc_angle_rad=np.zeros(3), acc_omega_sq=0.0), Kf2Diag(False, "first sample"))
    dt = time_s - state.time_s
    if dt <= 0.0:
        return state, Kf2Diag(False, f"time not increasing (dt={dt:.6f} s)")
    if dt > params.max_dt_s:
        # a gap: keep the attitude (nothing better is known), but the vehicle kept turning. The
        # interval counted as unseen is the part beyond max_dt_s (what an integrated step may span),
        # so an interval just over the limit (timestamp jitter) does not widen the attitude.
        st = kf2_unseen(_propagate_cov(state, params), dt - params.max_dt_s, params)
        return (_upd(st, time_s=time_s, omega_prev_rad_s=w, cov_time_s=time_s, acc_angle_rad=np.zeros(3),
                     acc_omega_sq=0.0), Kf2Diag(False, f"gap of {dt:.3f} s not integrated"))
    dtheta = 0.5 * (state.omega_prev_rad_s + w) * dt
    q = quat_mul(state.q_nav_from_body, quat_from_rotvec(dtheta))
    q = q / math.sqrt(float(q @ q))
    st = _upd(state, q_nav_from_body=q, time_s=time_s, omega_prev_rad_s=w,
                 acc_angle_rad=state.acc_angle_rad + dtheta,
                 acc_omega_sq=state.acc_omega_sq + float(dtheta @ dtheta) / dt)
    if time_s - state.cov_time_s >= params.cov_period_s - 1e-9:
        st = _propagate_cov(st, params)
    return st, Kf2Diag(True)


def _update(state: Kf2State, z: np.ndarray, H: np.ndarray, R: np.ndarray, n_gate: float,
            params: Kf2Params, D: np.ndarray | None = None) -> tuple[Kf2State, Kf2Diag]:
    """Gated update + closed-loop feedback. Returns the state unchanged (P propagated) when gated.
    ``D``: dz/dc of the consider parameters (m x NC; None: z does not depend on them)."""
    state = _propagate_cov(state, params)
    S = H @ state.P @ H.T + R
    s_diag = np.diag(S).copy()
    ratio = float(np.max(np.abs(z) / (n_gate * np.sqrt(s_diag))))
    if ratio > 1.0:
        return state, Kf2Diag(False, "gate", z.copy(), s_diag, ratio)
    S_c = state.consider_sens
    if S_c is not None or D is not None:
        # the same gain kf_update forms (same operations): S <- (I - K H) S - K D
        PHT = state.P @ H.T
        K = PHT @ np.linalg.inv(H @ PHT + R)
        S_c = (np.eye(N) - K @ H) @ (np.zeros((N, NC)) if S_c is None else S_c)
        if D is not None:
            S_c = S_c - K @ D
    dx, P = kf_update(np.zeros(N), state.P, z, H, R)   # error state: x- = 0
    q = quat_mul(state.q_nav_from_body, quat_from_rotvec(dx[0:3]))   # C <- C (I + [gamma x])
    q = q / math.sqrt(float(q @ q))
    new = _upd(state, q_nav_from_body=q, gyro_bias_rad_s=state.gyro_bias_rad_s + dx[3:6],
                  mag_bias=state.mag_bias + dx[6:9], P=0.5 * (P + P.T), consider_sens=S_c)
    return new, Kf2Diag(True, "", z.copy(), s_diag, ratio)


def _mag_inputs(mag_body_gauss, field_nav_gauss):
    """(m, B_nav, |B_nav|) as float arrays, or (None, None, None) for a non-finite sample; a zero
    reference field is a caller's bug (ValueError)."""
    m = np.asarray(mag_body_gauss, dtype=float)
    Bn = np.asarray(field_nav_gauss, dtype=float)
    if m.shape != (3,) or not np.all(np.isfinite(m)) or not np.all(np.isfinite(Bn)):
        return None, None, None
    norm = float(np.linalg.norm(Bn))
    if not norm > 0.0:
        raise ValueError("field_nav_gauss must be non-zero")
    return m, Bn, norm


def mag_consider_jacobian(C_nav_from_body: np.ndarray, b0: np.ndarray, field_nav_unit: np.ndarray) -> np.ndarray:
    """D_c = dm_n/dc (3 x NC, module docstring): the soft iron at the predicted body field b0
    (normalised), and a declination error turning the model field about down."""
    D = np.zeros((3, NC))
    D[:, 0:9] = error_jacobian(b0)[:, 3:12]
    D[:, 9] = C_nav_from_body.T @ np.array([-field_nav_unit[1], field_nav_unit[0], 0.0])
    return D


def kf2_consider_euler_cov(state: Kf2State, P_c: np.ndarray) -> np.ndarray:
    """The consider parameters' share of the (roll, pitch, heading) covariance, T S_gamma P_c
    S_gamma^T T^T (rad^2, 3 x 3); zeros while S is."""
    if state.consider_sens is None:
        return np.zeros((3, 3))
    e = euler_from_dcm(dcm_from_quat(state.q_nav_from_body))
    A = euler_rate_matrix_reported(e[0], e[1]) @ state.consider_sens[0:3, :]
    return A @ P_c @ A.T


def _mag_gates(state: Kf2State, m_n: np.ndarray, params: Kf2Params) -> tuple[Kf2State, Kf2Diag] | None:
    """The gates both magnetometer updates share: a field magnitude off the reference's (a magnetic
    disturbance) and a turn rate too high for the sample; the rejection (counted), or None."""
    if abs(float(np.linalg.norm(m_n)) - 1.0) > params.mag_norm_tolerance:
        return (_upd(state, n_mag_rejected=state.n_mag_rejected + 1),
                Kf2Diag(False, "magnetic disturbance (field magnitude)"))
    if state.omega_prev_rad_s is not None and float(np.linalg.norm(state.omega_prev_rad_s)) > params.max_mag_rate_rad_s:
        return _upd(state, n_mag_rejected=state.n_mag_rejected + 1), Kf2Diag(False, "rate gate")
    return None


def kf2_update_mag(state: Kf2State, mag_body_gauss: np.ndarray, field_nav_gauss: np.ndarray,
                   params: Kf2Params = Kf2Params()) -> tuple[Kf2State, Kf2Diag]:
    """Magnetometer update (eq. 21, 34). ``mag_body_gauss``: KF1-corrected field, body axes."""
    m, Bn, norm = _mag_inputs(mag_body_gauss, field_nav_gauss)
    if m is None:
        return state, Kf2Diag(False, "non-finite magnetometer sample")
    m_n = m / norm
    rejected = _mag_gates(state, m_n, params)
    if rejected is not None:
        return rejected
    C = dcm_from_quat(state.q_nav_from_body)
    b0 = C.T @ (Bn / norm)
    z = m_n - b0 - state.mag_bias
    H = np.zeros((3, N))
    H[:, 0:3] = skew(b0)
    H[:, 6:9] = np.eye(3)
    new, diag = _update(state, z, H, params.mag_sigma ** 2 * np.eye(3), params.mag_gate_sigma, params,
                        mag_consider_jacobian(C, b0, Bn / norm))
    if diag.fused:
        return _upd(new, n_mag_fused=new.n_mag_fused + 1), diag
    return _upd(new, n_mag_rejected=new.n_mag_rejected + 1, n_mag_gated=new.n_mag_gated + 1), diag


def kf2_update_mag_heading(state: Kf2State, mag_body_gauss: np.ndarray, field_nav_gauss: np.ndarray,
                           params: Kf2Params = Kf2Params()) -> tuple[Kf2State, Kf2Diag]:
    """Magnetometer as a heading-only measurement (an alternative to eq. 21, as x-io Fusion does):
    the field, less beta_hat, is levelled with our roll/pitch, m_h = (C_hat m)_{N,E}, and

        z = atan2(B_E, B_N) - atan2(m_h,E, m_h,N)  (= the heading error for a correct tilt)

    H = [T row 3 (d psi / d gamma), 0, d z / d dbeta]; d z / d dbeta = -(x C_1 - y C_0) / r^2 with
    (x, y) = m_h and C_i the rows of C_hat (d atan2(y, x) = (x dy - y dx) / r^2, d m_h = C dbeta).
    The magnetometer then cannot pull roll/pitch: with a residual calibration error its tilt
    information is biased, and roll/pitch come from the air data and the gyros alone.
    R: mag_sigma / (|B_h| / |B|) (rad)."""
    m, Bn, norm = _mag_inputs(mag_body_gauss, field_nav_gauss)
    if m is None:
        return state, Kf2Diag(False, "non-finite magnetometer sample")
    bh = math.hypot(Bn[0], Bn[1]) / norm
    if not bh > 0.05:
        return state, Kf2Diag(False, "horizontal field too weak for a heading")
    m_n = m / norm
    rejected = _mag_gates(state, m_n, params)
    if rejected is not None:
        return rejected
    C = dcm_from_quat(state.q_nav_from_body)
    roll, pitch, _ = euler_from_dcm(C)
    mh = C @ (m_n - state.mag_bias)
    x, y = float(mh[0]), float(mh[1])
    r2 = x * x + y * y
    z = np.array([wrap_pi(math.atan2(Bn[1], Bn[0]) - math.atan2(y, x))])
    H = np.zeros((1, N))
    H[0, 0:3] = euler_rate_matrix(roll, pitch)[2, :]
    H[0, 6:9] = -(x * C[1, :] - y * C[0, :]) / r2
    R = np.array([[(params.mag_sigma / bh) ** 2]])
    D = np.zeros((1, NC))
    D[:, 0:9] = H[:, 6:9] @ error_jacobian(C.T @ (Bn / norm))[:, 3:12]    # dz/dm D(b0)
    D[0, 9] = -1.0
    new, diag = _update(state, z, H, R, params.mag_gate_sigma, params, D)
    if diag.fused:
        return replace(new, n_mag_fused=new.n_mag_fused + 1), diag
    return replace(new, n_mag_rejected=new.n_mag_rejected + 1, n_mag_gated=new.n_mag_gated + 1), diag


def kf2_update_air(state: Kf2State, roll_ref_rad: float, pitch_ref_rad: float,
                   sigma_roll_ref_rad: float, sigma_pitch_ref_rad: float, turn_gain_s: float,
                   params: Kf2Params = Kf2Params()) -> tuple[Kf2State, Kf2Diag]:
    """Air-data roll/pitch update (eq. 22, 24-25, 35-37).

    ``turn_gain_s`` = d phi_ref / d psi_dot = (v/g) / (1 + (v psi_dot / g)^2) (s), for the
    gyro-bias column; the caller (who formed phi_ref from the gyro) supplies it.
    """
    C = dcm_from_quat(state.q_nav_from_body)
    roll, pitch, _ = euler_from_dcm(C)
    T = euler_rate_matrix(roll, pitch)
    z = np.array([wrap_pi(roll_ref_rad - roll), pitch_ref_rad - pitch])
    H = np.zeros((2, N))
    H[:, 0:3] = T[0:2, :]
    sphi, cphi, cth = math.sin(roll), math.cos(roll), math.cos(pitch)
    H[0, 4] = turn_gain_s * sphi / cth
    H[0, 5] = turn_gain_s * cphi / cth
    R = np.diag([sigma_roll_ref_rad ** 2, sigma_pitch_ref_rad ** 2])
    new, diag = _update(state, z, H, R, params.air_gate_sigma, params)
    if diag.fused:
        return _upd(new, n_air_fused=new.n_air_fused + 1), diag
    return _upd(new, n_air_rejected=new.n_air_rejected + 1), diag


def kf2_update_reference(state: Kf2State, euler_ref_rad: np.ndarray, time_ref_s: float,
                         sigma_tilt_rad: float, sigma_yaw_rad: float,
                         params: Kf2Params = Kf2Params(), use_yaw: bool = True) -> tuple[Kf2State, Kf2Diag]:
    """Trusted reference attitude (the FC's ATTITUDE) as a measurement: z = euler_ref - euler_hat.

    Our attitude is carried back to the reference's time with the last body rate. A residual
    beyond ``ref_reset_rad`` re-initialises the attitude to the reference (e.g. at start-up).
    ``use_yaw`` False: roll and pitch only (rows 1-2 of z, H, R; a reset keeps our heading).
    """
    q = state.q_nav_from_body
    if state.time_s is not None and state.omega_prev_rad_s is not None:
        q = quat_mul(q, quat_from_rotvec(-state.omega_prev_rad_s * (state.time_s - time_ref_s)))
    roll, pitch, yaw = euler_from_dcm(dcm_from_quat(q))
    e = np.asarray(euler_ref_rad, dtype=float)
    z = np.array([wrap_pi(e[0] - roll), e[1] - pitch, wrap_pi(e[2] - yaw)])
    n = 3 if use_yaw else 2
    if not use_yaw:
        e = np.array([e[0], e[1], yaw])
    if float(np.max(np.abs(z[:n]))) > params.ref_reset_rad:
        q_ref = quat_from_euler(*e)
        if state.time_s is not None and state.omega_prev_rad_s is not None:
            q_ref = quat_mul(q_ref, quat_from_rotvec(state.omega_prev_rad_s * (state.time_s - time_ref_s)))
        P = state.P.copy()
        P[0:3, :] = 0.0
        P[:, 0:3] = 0.0
        P[0:3, 0:3] = _gamma_cov_from_euler_sigmas(
            q_ref, sigma_tilt_rad, sigma_yaw_rad if use_yaw else math.sqrt(kf2_heading_var(state)))
        S = state.consider_sens
        if S is not None and use_yaw:
            S = S.copy()
            S[0:3, :] = 0.0                                  # the attitude is the reference's now
        return (_upd(state, q_nav_from_body=q_ref / math.sqrt(float(q_ref @ q_ref)), P=P,
                        n_resets=state.n_resets + 1, consider_sens=S), Kf2Diag(True, "reset to reference", z))
    H = np.zeros((3, N))
    H[:, 0:3] = euler_rate_matrix(roll, pitch)
    R = np.diag([sigma_tilt_rad ** 2, sigma_tilt_rad ** 2, sigma_yaw_rad ** 2])
    new, diag = _update(state, z[:n], H[:n], R[:n, :n], params.ref_gate_sigma, params)
    if diag.fused:
        return _upd(new, n_ref_fused=new.n_ref_fused + 1), diag
    return _upd(new, n_ref_rejected=new.n_ref_rejected + 1), diag
