"""B1: synthetic attitude when the heading is known from another source (METHODS.md B1;
seed AU756340B2 eq. 1-4, 22, 24 and the gyro zero correction of Fig. 1).

Roll and pitch are integrated from the zero-corrected gyro rates with the Euler kinematics
(eq. 1, euler_kinematics.euler_integrate). The heading is the external one (``b1_heading_step``);
until one arrives, the gyro-integrated yaw is reported with a growing sigma.

Reference attitude from air data (eq. 22, 24; alpha = k_alpha n / q_dyn, see below):

    theta_ref = asin(h_dot / v) + alpha cos(phi)       (beta = 0: no sideslip sensor)
    phi_ref   = atan(v psi_dot / g)                    (coordinated turn)

psi_dot is the derivative of the external heading (filtered, the seed's high-passed heading),
or the gyro-derived Euler yaw rate while there is no heading input.

Correction (eq. 3-4): delta = phi_AHRS - phi_ref; the integrator is pulled toward the reference
with time constant ``tau_s`` through a limiter:

    phi <- phi - clip(delta, +-limit_rad) * dt / tau_s

switched off (flag ``air_off_reason``) outside level, slow flight: |phi| > roll_limit,
|theta| > pitch_limit, |phi_dot| or |theta_dot| > rate_limit, or air data not usable. Each axis
carries a 2x2 covariance of (angle error, rate-bias error), propagated exactly for this linear
correction law, so the reported sigma is that of the estimator actually running.

Angle of attack: UAVs have no alpha vane. While the reference is trusted we learn the trim
coefficient k_alpha from alpha_meas = (theta_fc - asin(h_dot / v)) / cos(phi) with
alpha = k_alpha n / q_dyn (n = 1/cos(phi) the turn load factor, q_dyn = rho v^2 / 2: the lift
coefficient scales with n / q_dyn), low-passed with ``alpha_tau_s``; frozen when untrusted.

Gyro zero correction (Fig. 1, filters 3 and 5): while the trusted reference works, the rates
implied by the reference are compared with the zero-corrected gyro rates, and the difference is
averaged with a long time constant (growing from ``zero_tau_min_s`` to ``zero_tau_s``,
"initialised with the shorter time constant") into the correction c, used as omega = gyro + c.
Differentiating the reference's Euler angles sample by sample (the seed's high-pass) amplifies
their noise (0.2 deg at 50 Hz -> 14 deg/s), so the comparison is made on increments over a
window of ``zero_window_s``: with C_r the reference attitude and C_g our gyro-only attitude
(integrated with gyro + c, never reset), the body-frame rate error over the window is

    delta_omega = rotvec( (C_r(a)^T C_r(b))^T (C_g(a)^T C_g(b)) ) / (t_b - t_a)

(the gyro-only relative rotation minus the reference's, i.e. the mean of (gyro + c) - omega
for slow attitude changes), and c <- c - k delta_omega with k = T / (tau + T). When the
reference fails the last correction is kept (frozen).

Frames: all rates are FRD body axes (the caller rotates sensor-frame gyros by
C_body_from_sensor). Pure: ``b1_imu_step``, ``b1_air_step``, ``b1_reference_step``,
``b1_heading_step``; ``b1_output``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from estimators.air_data import AirData
from estimators.euler_kinematics import euler_integrate, euler_rates
from estimators.rotations import (dcm_from_euler, dcm_from_quat, quat_from_dcm, quat_from_rotvec,
                                  quat_mul, rotvec_from_quat, wrap_2pi, wrap_pi)

G_M_S2 = 9.80665


@dataclass(frozen=True)
class B1Params:
    tau_s: float = 10.0
    """Air-data correction time constant (s)."""
    limit_rad: float = math.radians(5.0)
    """Limiter on the attitude difference fed back (rad)."""
    roll_limit_rad: float = math.radians(30.0)
    pitch_limit_rad: float = math.radians(20.0)
    rate_limit_rad_s: float = math.radians(5.0)
    """|phi_dot| and |theta_dot| above this switch the correction off."""
    sigma_roll_ref_rad: float = math.radians(2.0)
    sigma_pitch_ref_rad: float = math.radians(2.0)
    gyro_noise_rad_s_rthz: float = math.radians(0.015)
    sigma_bias_uncorrected_rad_s: float = math.radians(0.3)
    """Gyro-zero uncertainty without any zero correction."""
    sigma_bias_corrected_rad_s: float = math.radians(0.03)
    """Residual gyro-zero uncertainty once the zero correction has converged."""
    zero_window_s: float = 2.0
    """Window of the reference-vs-gyro increment comparison (s)."""
    zero_tau_min_s: float = 2.0
    zero_tau_s: float = 60.0
    alpha_tau_s: float = 20.0
    heading_rate_tau_s: float = 1.0
    heading_timeout_s: float = 1.0
    sigma_fc_rad: float = math.radians(0.5)
    max_dt_s: float = 0.1

    def __post_init__(self):
        for name, v in self.__dict__.items():
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class B1State:
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_gyro_rad: float = 0.0
    """Gyro-integrated yaw, used only while no heading input is fresh."""
    P_roll: np.ndarray = None  # 2x2 (angle, rate bias)
    P_pitch: np.ndarray = None
    yaw_var: float = math.radians(30.0) ** 2
    zero_corr_rad_s: np.ndarray = None
    """c: added to the gyro (rad/s, body)."""
    zero_corr_time_s: float = 0.0
    """Accumulated time of zero-correction learning (s)."""
    q_free: np.ndarray | None = None
    """Gyro-only attitude q_free_from_body, integrated with gyro + c, never reset."""
    zero_window: tuple | None = None
    """(t_a, C_ref(a), C_free(a)) at the start of the current zero-correction window."""
    k_alpha_pa: float | None = None
    """Learnt angle-of-attack coefficient alpha = k n / q_dyn (rad Pa)."""
    heading_rad: float | None = None
    heading_time_s: float | None = None
    heading_rate_rad_s: float = 0.0
    heading_sigma_rad: float = 0.0
    omega_prev_rad_s: np.ndarray | None = None
    time_s: float | None = None
    air_time_s: float | None = None
    air_active: bool = False
    air_off_reason: str = "no air data yet"
    initialised: bool = False


def b1_init(params: B1Params = B1Params()) -> B1State:
    P = np.diag([math.radians(10.0) ** 2, params.sigma_bias_uncorrected_rad_s ** 2])
    return B1State(P_roll=P.copy(), P_pitch=P.copy(), zero_corr_rad_s=np.zeros(3))


def _prop_axis(P: np.ndarray, dt: float, q_angle: float) -> np.ndarray:
    """e' = e - b dt (+ noise), b' = b."""
    F = np.array([[1.0, -dt], [0.0, 1.0]])
    return F @ P @ F.T + np.diag([q_angle, 0.0])


def b1_imu_step(state: B1State, gyro_body_rad_s: np.ndarray, time_s: float,
                params: B1Params = B1Params()) -> B1State:
    """Integrate eq. 1 with the zero-corrected rate omega = gyro + c."""
    g = np.asarray(gyro_body_rad_s, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or not math.isfinite(time_s):
        raise ValueError("b1_imu_step: gyro must be 3 finite values and time finite")
    w = g + state.zero_corr_rad_s
    if state.time_s is None or state.omega_prev_rad_s is None:
        return replace(state, time_s=time_s, omega_prev_rad_s=w, q_free=np.array([1.0, 0.0, 0.0, 0.0]))
    dt = time_s - state.time_s
    if dt <= 0.0:
        raise ValueError(f"b1_imu_step: time must increase ({time_s!r} after {state.time_s!r})")
    if dt > params.max_dt_s:
        return replace(state, time_s=time_s, omega_prev_rad_s=w)
    qf = quat_mul(state.q_free, quat_from_rotvec(0.5 * (state.omega_prev_rad_s + w) * dt))
    qf = qf / math.sqrt(float(qf @ qf))
    e = euler_integrate([state.roll_rad, state.pitch_rad, state.yaw_gyro_rad], state.omega_prev_rad_s, w, dt)
    q_angle = params.gyro_noise_rad_s_rthz ** 2 * dt
    Pr, Pp = _prop_axis(state.P_roll, dt, q_angle), _prop_axis(state.P_pitch, dt, q_angle)
    yaw_var = state.yaw_var + params.gyro_noise_rad_s_rthz ** 2 * dt + (state.P_roll[1, 1] * dt * dt)
    return replace(state, roll_rad=wrap_pi(e[0]), pitch_rad=float(e[1]), yaw_gyro_rad=wrap_2pi(e[2]),
                   P_roll=Pr, P_pitch=Pp, yaw_var=yaw_var, omega_prev_rad_s=w, time_s=time_s, q_free=qf)


def b1_heading_step(state: B1State, heading_rad: float, sigma_rad: float, time_s: float,
                    params: B1Params = B1Params()) -> B1State:
    """An external heading sample (rad, true); its filtered derivative feeds phi_ref."""
    if not (math.isfinite(heading_rad) and math.isfinite(sigma_rad) and math.isfinite(time_s)):
        raise ValueError("b1_heading_step: non-finite input")
    rate = state.heading_rate_rad_s
    if state.heading_time_s is not None and 0.0 < time_s - state.heading_time_s <= params.heading_timeout_s:
        dt = time_s - state.heading_time_s
        T = params.heading_rate_tau_s
        rate = (T * rate + wrap_pi(heading_rad - state.heading_rad)) / (T + dt)
    else:
        rate = 0.0
    return replace(state, heading_rad=wrap_2pi(heading_rad), heading_time_s=time_s,
                   heading_rate_rad_s=rate, heading_sigma_rad=sigma_rad)


def _heading_fresh(state: B1State, params: B1Params) -> bool:
    return (state.heading_time_s is not None and state.time_s is not None
            and state.time_s - state.heading_time_s <= params.heading_timeout_s)


def b1_air_step(state: B1State, air: AirData, params: B1Params = B1Params()) -> B1State:
    """Pull roll/pitch toward the air-data references (eq. 3-4, 22, 24) when allowed."""
    dt = 0.0 if state.air_time_s is None else min(air.time_s - state.air_time_s, params.max_dt_s)
    st = replace(state, air_time_s=air.time_s)
    if not state.initialised or state.omega_prev_rad_s is None:
        return replace(st, air_active=False, air_off_reason="not initialised")
    if not air.usable:
        return replace(st, air_active=False, air_off_reason=air.unusable_reason)
    roll, pitch = state.roll_rad, state.pitch_rad
    ed = euler_rates(roll, pitch, state.omega_prev_rad_s)
    why = ""
    if abs(roll) > params.roll_limit_rad:
        why = "roll beyond limit"
    elif abs(pitch) > params.pitch_limit_rad:
        why = "pitch beyond limit"
    elif max(abs(ed[0]), abs(ed[1])) > params.rate_limit_rad_s:
        why = "attitude rate beyond limit"
    if why or dt <= 0.0:
        return replace(st, air_active=False, air_off_reason=why or "first air sample")
    v = air.tas_m_s
    psi_dot = state.heading_rate_rad_s if _heading_fresh(state, params) else ed[2]
    phi_ref = math.atan(v * psi_dot / G_M_S2)                                   # eq. 24
    gamma = math.asin(max(-1.0, min(1.0, air.alt_rate_m_s / v)))
    alpha = 0.0
    if state.k_alpha_pa is not None:
        n = 1.0 / max(0.3, math.cos(roll))
        alpha = state.k_alpha_pa * n / (0.5 * air.density_kg_m3 * v * v)
    theta_ref = gamma + alpha * math.cos(roll)                                  # eq. 22
    k = dt / params.tau_s
    new = {}
    for name, ang, ref, P, sig in (("roll", roll, phi_ref, state.P_roll, params.sigma_roll_ref_rad),
                                   ("pitch", pitch, theta_ref, state.P_pitch, params.sigma_pitch_ref_rad)):
        delta = wrap_pi(ang - ref)                                              # eq. 3
        corr = max(-params.limit_rad, min(params.limit_rad, delta))
        F = np.array([[1.0 - k, 0.0], [0.0, 1.0]])
        new[name] = (ang - corr * k, F @ P @ F.T + np.diag([k * k * sig * sig, 0.0]))  # eq. 4
    return replace(st, roll_rad=wrap_pi(new["roll"][0]), pitch_rad=new["pitch"][0],
                   P_roll=new["roll"][1], P_pitch=new["pitch"][1], air_active=True, air_off_reason="")


def b1_reference_step(state: B1State, euler_ref_rad: np.ndarray, time_s: float, trusted: bool,
                      air: AirData | None = None, params: B1Params = B1Params()) -> B1State:
    """A reference (FC ATTITUDE) sample. While trusted: align roll/pitch, learn the zero
    correction and alpha; untrusted: everything frozen (the comparison window restarts)."""
    e = np.asarray(euler_ref_rad, dtype=float)
    if e.shape != (3,) or not np.all(np.isfinite(e)) or not math.isfinite(time_s):
        raise ValueError("b1_reference_step: euler must be 3 finite values, time finite")
    if not trusted:
        return replace(state, zero_window=None)
    st = replace(state, roll_rad=float(e[0]), pitch_rad=float(e[1]), initialised=True,
                 P_roll=np.array([[params.sigma_fc_rad ** 2, 0.0], [0.0, state.P_roll[1, 1]]]),
                 P_pitch=np.array([[params.sigma_fc_rad ** 2, 0.0], [0.0, state.P_pitch[1, 1]]]))
    if not _heading_fresh(st, params):
        st = replace(st, yaw_gyro_rad=wrap_2pi(float(e[2])), yaw_var=params.sigma_fc_rad ** 2)
    prev_t = st.zero_window[0] if st.zero_window is not None else None
    if st.q_free is None:
        return st
    C_r, C_g = dcm_from_euler(*e), dcm_from_quat(st.q_free)
    if st.zero_window is None:
        return replace(st, zero_window=(time_s, C_r, C_g))
    T = time_s - prev_t
    if T < params.zero_window_s:
        return st
    _, C_ra, C_ga = st.zero_window
    R_ref, R_gyro = C_ra.T @ C_r, C_ga.T @ C_g
    d_omega = rotvec_from_quat(quat_from_dcm(R_ref.T @ R_gyro)) / T
    t_zc = st.zero_corr_time_s + T
    tau = min(params.zero_tau_s, max(params.zero_tau_min_s, t_zc))
    c = st.zero_corr_rad_s - T / (tau + T) * d_omega
    sb = max(params.sigma_bias_corrected_rad_s,
             params.sigma_bias_uncorrected_rad_s * math.sqrt(params.zero_tau_min_s / t_zc))
    st = replace(st, zero_corr_rad_s=c, zero_corr_time_s=t_zc, zero_window=(time_s, C_r, C_g),
                 P_roll=np.diag([st.P_roll[0, 0], sb * sb]), P_pitch=np.diag([st.P_pitch[0, 0], sb * sb]))
    dt = T
    if air is not None and air.usable and abs(e[0]) < params.roll_limit_rad and abs(e[1]) < params.pitch_limit_rad:
        v = air.tas_m_s
        gamma = math.asin(max(-1.0, min(1.0, air.alt_rate_m_s / v)))
        n = 1.0 / math.cos(e[0])
        k_meas = (e[1] - gamma) / math.cos(e[0]) * (0.5 * air.density_kg_m3 * v * v) / n
        ka = k_meas if st.k_alpha_pa is None else st.k_alpha_pa + dt / (params.alpha_tau_s + dt) * (k_meas - st.k_alpha_pa)
        st = replace(st, k_alpha_pa=ka)
    return st


@dataclass(frozen=True)
class B1Output:
    roll_rad: float
    pitch_rad: float
    heading_rad: float
    roll_sigma_rad: float
    pitch_sigma_rad: float
    heading_sigma_rad: float
    heading_source: str
    """"external" or "gyro" (integrated, drifting)."""
    air_active: bool
    air_off_reason: str
    zero_corr_rad_s: np.ndarray


def b1_output(state: B1State, params: B1Params = B1Params()) -> B1Output:
    fresh = _heading_fresh(state, params)
    return B1Output(roll_rad=state.roll_rad, pitch_rad=state.pitch_rad,
                    heading_rad=state.heading_rad if fresh else state.yaw_gyro_rad,
                    roll_sigma_rad=math.sqrt(state.P_roll[0, 0]), pitch_sigma_rad=math.sqrt(state.P_pitch[0, 0]),
                    heading_sigma_rad=state.heading_sigma_rad if fresh else math.sqrt(state.yaw_var),
                    heading_source="external" if fresh else "gyro", air_active=state.air_active,
                    air_off_reason=state.air_off_reason, zero_corr_rad_s=state.zero_corr_rad_s.copy())
