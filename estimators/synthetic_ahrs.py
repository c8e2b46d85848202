"""Synthetic AHRS (METHODS.md B): one pure step for whatever input arrived.

    state = synthetic_ahrs_init(params, kf1_learn=None, kf1_applied=None)
    state, out = synthetic_ahrs_step(state, event, params)

Events (FC clock ``time_s`` on every one):
- ``ImuEvent``       gyro (rad/s) and magnetometer (gauss, or None), SENSOR axes; rotated here to
                     body axes by ``params.C_body_from_sensor`` (the configured mount).
- ``AirEvent``       SCALED_PRESSURE: press_abs_pa, press_diff_pa (None: no pitot), temperature_k.
- ``FcAttitudeEvent`` the FC's ATTITUDE (roll, pitch, yaw rad), the candidate trusted reference.
- ``FcStatusEvent``  HEARTBEAT system_status and/or EKF attitude_ok / horiz_pos_ok (None: unchanged).
- ``HeadingEvent``   an external heading (rad, true) with its sigma: B1's heading source.

Variants (``params.variant``):
- "b1": heading known (HeadingEvent); roll/pitch by Euler kinematics + air-data references +
  gyro zero correction from the trusted FC (ahrs_b1).
- "b2": heading computed: KF2 (ahrs_kf2) integrates the gyros and fuses the magnetometer
  (corrected by KF1's estimate that is at least one flight old, ``kf1_applied``) and the
  air-data roll/pitch; while the FC is trusted it also fuses the FC attitude (gyro zero
  correction = KF2's bias states, plus alignment), KF1 (``kf1_learn``) learns the magnetometer
  errors and the angle-of-attack coefficient is learnt. When the FC is not trusted: KF1 and the
  alpha learning stop, and the gyro-bias and residual magnetometer-bias estimates are set back
  to their values from ``bias_revert_age_s`` before the loss was detected; after a *silent*
  divergence the attitude is taken back too (that snapshot's attitude carried forward by the
  gyro-only increments since) (a silently failing reference may have
  pulled it during the detection delay).

``params.mag_mode`` = "heading" replaces the seed's three-component magnetometer update by a
levelled heading-only one (the magnetometer then cannot pull roll/pitch; see
ahrs_kf2.kf2_update_mag_heading). On the 10-flight check it gave the same RMS with a smaller
worst case; "vector" (the seed) stays the default.

Heading sigma while the FC is (or was) the reference. KF2 fuses the FC's yaw every
``ref_update_interval_s`` as if its errors were white; they are not (an FC's heading error is
correlated over tens of seconds: a compass/declination error, its own filter's lag), so KF2's
heading variance collapses far below the FC's error that it has copied (measured: 0.17 deg sigma
for a 1.3 deg RMS error, bench/heading_consistency.py). The FC's yaw error is therefore treated as
a *consider* parameter eps (Schmidt): not estimated, but its effect on our heading is tracked as a
sensitivity a = d(heading error)/d(eps). An update with heading gain k (k = 1 - v+/v-, v = KF2's
heading variance before/after it) maps the error e -> (1 - k) e + k (z's error), so
    FC reference update: a <- (1 - k) a + k       (z carries eps)
    other heading update (magnetometer): a <- (1 - k) a
    reset to the reference: a <- 1;  start from the FC: a = 1;  start from the magnetometer: a = 0,
and the published heading variance is v + a^2 sigma_eps^2 (the filter's own part plus the FC
error it inherited; the two overlap by at most k^2 R per update, negligible once v << R), with
sigma_eps = ``fc_sigma_yaw_rad``: the same FC yaw sigma the service gives the FC's own reading, so
B aligned to the FC never claims to be better than the FC itself (1.5 deg by default: wider
than the simulator's 1 deg FC, so the NEES of the FC-aligned heading is ~0.5 there). eps is
taken as constant (no decay with its correlation time): conservative. After the FC is no longer
trusted a only shrinks as the magnetometer corrects the heading.

Heading sigma from the magnetometer's own persistent errors. KF2 fuses the magnetometer as if its
errors were white noise about the model field plus a body-fixed bias (its beta states); they are not:
the scale factors and cross-couplings that KF1's correction leaves (its covariance: the applied
estimate's, or KF1's prior when none is applied) and the model field's declination error stay for
the whole flight, and turn with the attitude. Without the FC's yaw nothing shows them, and they
were measured at 4.5-8 sigma of KF2's heading sigma (ArduPlane SITL's 'ours' flight; the simulator's
inclined rail with the FC's yaw excluded: 16 sigma, 5.1 deg RMS at a 1.1 deg median sigma). They are
consider parameters c of KF2 (ahrs_kf2 module docstring: S = de/dc follows every propagation and
update with KF2's own gain, so its estimates are unchanged), with covariance

    P_c = blockdiag(P_kf1[3:12, 3:12], sigma_D^2)     (sigma_D = ``field_model_sigma_rad``)

and the published heading variance is v + a^2 sigma_eps^2 + [T S_gamma P_c S_gamma^T T^T]_33 (the FC's
yaw error, above, and c are independent). Where the FC's yaw is fused its updates shrink S as they
shrink a magnetometer error in the heading ((I - K H) S); while the magnetometer is not fused, S's
gyro-bias rows (a bias learnt from a wrong magnetometer heading) make the heading's share grow with
the time coasted. ``consider_mag_errors`` False leaves the sigma without this share.

Reference health: reference_health (signalled status + agreement of the FC attitude with our
gyro-only attitude, which is integrated here with the current bias estimate and never reset).

The model field ``params.field_nav_gauss`` (NED, gauss, e.g. estimators.geomag at the site) is
needed by B2. Output: roll, pitch, heading (rad, heading [0, 2pi)), 1-sigma of each, the variant
and flags (``SyntheticAhrsOutput``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.records import fast_replace

from estimators.ahrs_b1 import (B1Params, B1State, b1_air_step, b1_heading_step, b1_imu_step,
                                b1_init, b1_output, b1_reference_step)
from estimators.ahrs_kf2 import (NC, Kf2Params, Kf2State, kf2_consider_euler_cov, kf2_euler_and_cov,
                                 kf2_heading_var, kf2_init, kf2_predict, kf2_propagate, kf2_unseen,
                                 kf2_update_air, kf2_update_mag, kf2_update_mag_heading, kf2_update_reference)
from estimators.air_data import AirData, AirDataParams, AirDataState, air_data_step
from estimators.euler_kinematics import euler_rates
from estimators.geomag import earth_field_ned_gauss
from estimators.mag_error_kf import Kf1Params, Kf1State, kf1_correct_mag, kf1_init, kf1_step
from estimators.reference_health import (ReferenceHealthParams, ReferenceHealthState,
                                         health_on_attitude, health_on_ekf_status,
                                         health_on_heartbeat, health_trusted)
from estimators.rotations import (dcm_from_euler, dcm_from_quat, quat_conj, quat_from_euler,
                                  quat_from_rotvec, quat_mul)

G_M_S2 = 9.80665
VARIANTS = ("b1", "b2")


# --- events ---------------------------------------------------------------------------------


_upd = fast_replace

@dataclass(frozen=True)
class ImuEvent:
    time_s: float
    gyro_sensor_rad_s: np.ndarray
    mag_sensor_gauss: np.ndarray | None = None


@dataclass(frozen=True)
class AirEvent:
    time_s: float
    press_abs_pa: float
    press_diff_pa: float | None
    temperature_k: float | None = None


@dataclass(frozen=True)
class FcAttitudeEvent:
    time_s: float
    euler_rad: np.ndarray
    """[roll, pitch, yaw] as the FC reports them (yaw in (-pi, pi] is fine)."""


@dataclass(frozen=True)
class FcStatusEvent:
    time_s: float
    system_status: int | None = None
    attitude_ok: bool | None = None
    horiz_pos_ok: bool | None = None


@dataclass(frozen=True)
class HeadingEvent:
    time_s: float
    heading_rad: float
    sigma_rad: float


# --- params / state / output ----------------------------------------------------------------

def _as_tuple33(m) -> tuple:
    a = np.asarray(m, dtype=float)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"C_body_from_sensor must be a finite 3x3 matrix, got {m!r}")
    if not np.allclose(a @ a.T, np.eye(3), atol=1e-6) or np.linalg.det(a) < 0:
        raise ValueError("C_body_from_sensor must be a rotation matrix")
    return tuple(tuple(float(v) for v in row) for row in a)


@dataclass(frozen=True)
class SyntheticAhrsParams:
    variant: str = "b2"
    """"b1" (heading from another source) or "b2" (heading computed)."""
    mag_mode: str = "vector"
    """b2 magnetometer update: "vector" (the seed's three components, eq. 21: also corrects
    roll/pitch) or "heading" (levelled heading only; roll/pitch from air data and gyros)."""
    C_body_from_sensor: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    """IMU mount (3x3, rows); applied here to gyro and magnetometer."""
    field_nav_gauss: tuple | None = None
    """Model Earth field at the site, NED, gauss (needed by b2)."""
    fc_sigma_tilt_rad: float = math.radians(0.5)
    """1-sigma of the trusted FC roll/pitch as a KF2 measurement."""
    fc_sigma_yaw_rad: float = math.radians(1.5)
    field_model_sigma_rad: float = 0.0
    """1-sigma of the model field's declination at the site (rad; e.g. the WMM's uncertainty,
    estimators.geomag ``declination_sigma_rad``): a consider parameter of the heading (module docstring)."""
    consider_mag_errors: bool = True
    """The heading sigma carries the magnetometer's unmodelled errors (module docstring)."""
    use_fc_yaw: bool = True
    """False: the FC's yaw is used nowhere (e.g. it is our own heading fed back): the reference
    update fuses the FC's roll/pitch only, KF1 (which needs the FC's full attitude) does not learn,
    the heading starts from the magnetometer levelled with the FC's roll/pitch, and B never
    inherits the FC's yaw error (its consider sensitivity stays 0)."""
    ref_update_interval_s: float = 0.1
    mag_update_interval_s: float = 0.1
    air_update_interval_s: float = 1.0
    """Air-data roll/pitch updates at most this often (s): their errors (vertical gusts, alpha
    changes) are correlated over seconds, so denser updates would over-weight them."""
    air_roll_limit_rad: float = math.radians(35.0)
    air_pitch_limit_rad: float = math.radians(20.0)
    air_rate_limit_rad_s: float = math.radians(5.0)
    """|phi_dot| and |theta_dot| above this: no air-data update (transients)."""
    air_sigma_roll_rad: float = math.radians(2.0)
    air_sigma_pitch_rad: float = math.radians(4.0)
    """Base 1-sigma of the pitch reference: a vertical gust w gives w / v of error in
    asin(h_dot / v) (0.8 m/s at 25 m/s: 1.8 deg), correlated over seconds; inflated for the
    1 s update interval."""
    air_sigma_alt_rate_m_s: float = 0.3
    """Altitude-rate noise used in the pitch-reference sigma (seed eq. 37 sensitivity)."""
    alpha_tau_s: float = 20.0
    rate_lp_tau_s: float = 0.2
    """Low-pass of the body rate used for the turn rate in phi_ref and the gates."""
    bias_revert_age_s: float = 30.0
    bias_snapshot_period_s: float = 5.0
    init_without_reference_s: float = 5.0
    """b2: with no trusted reference this long after the first IMU sample, start from the
    magnetometer (level, wide sigmas) instead of waiting."""
    init_sigma_tilt_rad: float = math.radians(10.0)
    init_sigma_heading_rad: float = math.radians(30.0)
    air: AirDataParams = AirDataParams()
    b1: B1Params = B1Params()
    kf1: Kf1Params = Kf1Params()
    kf2: Kf2Params = Kf2Params()
    health: ReferenceHealthParams = ReferenceHealthParams()

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.mag_mode not in ("vector", "heading"):
            raise ValueError(f"mag_mode must be 'vector' or 'heading', got {self.mag_mode!r}")
        object.__setattr__(self, "C_body_from_sensor", _as_tuple33(self.C_body_from_sensor))
        if self.field_nav_gauss is not None:
            f = np.asarray(self.field_nav_gauss, dtype=float)
            if f.shape != (3,) or not np.all(np.isfinite(f)) or not np.linalg.norm(f) > 0:
                raise ValueError(f"field_nav_gauss must be 3 finite values, not all 0, got {self.field_nav_gauss!r}")
            object.__setattr__(self, "field_nav_gauss", tuple(float(v) for v in f))
        elif self.variant == "b2":
            raise ValueError("variant b2 needs field_nav_gauss (the model field at the site, NED gauss)")
        for name in ("fc_sigma_tilt_rad", "fc_sigma_yaw_rad", "air_roll_limit_rad", "air_pitch_limit_rad",
                     "air_rate_limit_rad_s", "air_sigma_roll_rad", "air_sigma_pitch_rad",
                     "air_sigma_alt_rate_m_s", "alpha_tau_s", "rate_lp_tau_s", "bias_revert_age_s",
                     "bias_snapshot_period_s", "init_without_reference_s", "init_sigma_tilt_rad",
                     "init_sigma_heading_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("ref_update_interval_s", "mag_update_interval_s", "air_update_interval_s", "field_model_sigma_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")


@dataclass(frozen=True)
class SyntheticAhrsState:
    air: AirDataState = field(default_factory=AirDataState)
    air_last: AirData | None = None
    health: ReferenceHealthState = field(default_factory=ReferenceHealthState)
    q_gyro_free: np.ndarray | None = None
    """Gyro-only attitude q_free_from_body (started at identity, never reset; trapezoidal
    increments), for the reference agreement test: only its changes are used."""
    gyro_prev_rad_s: np.ndarray | None = None
    """The last bias-corrected body rate integrated into q_gyro_free."""
    gyro_free_var_rad2: float = 0.0
    """Integration error variance of q_gyro_free (per axis, rad^2) accumulated since it started."""
    b1: B1State | None = None
    kf2: Kf2State | None = None
    kf1_learn: Kf1State | None = None
    kf1_applied: Kf1State | None = None
    k_alpha_pa: float | None = None
    omega_lp_rad_s: np.ndarray | None = None
    fc_last: tuple | None = None
    """(time_s, euler) of the last FC ATTITUDE."""
    time_s: float | None = None
    last_mag_update_s: float = -math.inf
    last_air_update_s: float = -math.inf
    last_ref_update_s: float = -math.inf
    trusted: bool = False
    trust_reason: str = "no FC attitude yet"
    bias_snapshots: tuple = ()
    """((time_s, gyro_bias_rad_s, mag_bias, q_nav_from_body, q_gyro_free, P), ...) for the
    revert on a detected loss."""
    air_active: bool = False
    air_off_reason: str = "no air data yet"
    kf1_learning: bool = False
    n_kf1_rejected: int = 0
    first_imu_time_s: float | None = None
    ref_heading_sens: float = 0.0
    """b2: sensitivity a of our heading error to the FC's (correlated) yaw error (module docstring)."""
    reacquire_heading: bool = False
    """b2: a gap left the heading as good as unknown: take it from the magnetometer next."""
    imu_integrated_s: float = 0.0
    """Sum of the IMU intervals integrated (at most ``kf2.max_dt_s`` each) ..."""
    imu_not_integrated_s: float = 0.0
    """... and of those longer, held across and not integrated (a gap; inputs too slow): the
    caller's measure of whether B can follow the rotation at all (service/heading_sources)."""


@dataclass(frozen=True)
class SyntheticAhrsOutput:
    time_s: float
    variant: str
    valid: bool
    """False until the first trusted reference (or explicit start) initialised the attitude."""
    roll_rad: float
    pitch_rad: float
    heading_rad: float
    roll_sigma_rad: float
    pitch_sigma_rad: float
    heading_sigma_rad: float
    reference_trusted: bool
    reference_reason: str
    air_correction_active: bool
    air_off_reason: str
    kf1_learning: bool
    kf1_applied_flights: int | None
    """flight_count of the KF1 estimate in use (None: no calibration applied)."""
    gyro_bias_rad_s: np.ndarray
    mag_fused: int = 0
    mag_rejected: int = 0
    mag_gated: int = 0
    """Of mag_rejected: by KF2's innovation gate (B disagrees with its own magnetometer)."""
    air_fused: int = 0
    air_rejected: int = 0
    ref_fused: int = 0
    kf1_rejected: int = 0
    imu_integrated_s: float = 0.0
    """SyntheticAhrsState.imu_integrated_s / imu_not_integrated_s: the time B integrated the gyros
    and the time it held its attitude across intervals longer than it integrates (s, since start)."""
    imu_not_integrated_s: float = 0.0


def synthetic_ahrs_params_for_site(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float,
                                   variant: str = "b2", C_body_from_sensor=None,
                                   **overrides) -> SyntheticAhrsParams:
    """Params with the model field at the site (estimators.geomag, WMM), for the service."""
    field_ned = earth_field_ned_gauss(lat_deg, lon_deg, alt_m, decimal_year)
    kw = dict(overrides)
    if C_body_from_sensor is not None:
        kw["C_body_from_sensor"] = C_body_from_sensor
    return SyntheticAhrsParams(variant=variant, field_nav_gauss=tuple(float(v) for v in field_ned), **kw)


def synthetic_ahrs_init(params: SyntheticAhrsParams, kf1_learn: Kf1State | None = None,
                        kf1_applied: Kf1State | None = None) -> SyntheticAhrsState:
    """``kf1_learn``: where this flight's KF1 starts (calibration_store.learning_start);
    ``kf1_applied``: the estimate at least one flight old (calibration_store.estimate_for_flight)."""
    return SyntheticAhrsState(b1=b1_init(params.b1) if params.variant == "b1" else None,
                              kf1_learn=kf1_init(params.kf1) if kf1_learn is None else kf1_learn,
                              kf1_applied=kf1_applied)


# --- helpers --------------------------------------------------------------------------------

def _consider_cov(state: SyntheticAhrsState, params: SyntheticAhrsParams) -> np.ndarray:
    """P_c (NC x NC): the soft-iron block of the applied KF1 estimate's covariance (KF1's prior when
    none is applied), and the declination's variance (module docstring)."""
    k1 = state.kf1_applied
    P1 = k1.P if k1 is not None and k1.field_norm_gauss is not None else kf1_init(params.kf1).P
    P_c = np.zeros((NC, NC))
    P_c[0:9, 0:9] = P1[3:12, 3:12]
    P_c[9, 9] = params.field_model_sigma_rad ** 2
    return P_c


def _C_bs(params: SyntheticAhrsParams) -> np.ndarray:
    return np.array(params.C_body_from_sensor)


def _gyro_bias(state: SyntheticAhrsState) -> np.ndarray:
    if state.kf2 is not None:
        return state.kf2.gyro_bias_rad_s
    if state.b1 is not None:
        return -state.b1.zero_corr_rad_s
    return np.zeros(3)


def air_references(air: AirData, roll_rad: float, pitch_rad: float, omega_body_rad_s: np.ndarray,
                   k_alpha_pa: float | None, params: SyntheticAhrsParams):
    """(ok, reason, phi_ref, theta_ref, sigma_phi, sigma_theta, turn_gain_s), eq. 22, 24, 37."""
    if not air.usable:
        return False, air.unusable_reason, 0.0, 0.0, 0.0, 0.0, 0.0
    if abs(roll_rad) > params.air_roll_limit_rad:
        return False, "roll beyond limit", 0.0, 0.0, 0.0, 0.0, 0.0
    if abs(pitch_rad) > params.air_pitch_limit_rad:
        return False, "pitch beyond limit", 0.0, 0.0, 0.0, 0.0, 0.0
    ed = euler_rates(roll_rad, pitch_rad, omega_body_rad_s)
    if max(abs(ed[0]), abs(ed[1])) > params.air_rate_limit_rad_s:
        return False, "attitude rate beyond limit", 0.0, 0.0, 0.0, 0.0, 0.0
    v = air.tas_m_s
    x = v * ed[2] / G_M_S2
    phi_ref = math.atan(x)                                            # eq. 24
    turn_gain = (v / G_M_S2) / (1.0 + x * x)
    s = max(-0.99, min(0.99, air.alt_rate_m_s / v))
    gamma = math.asin(s)
    sig_alpha = math.radians(3.0)
    alpha = 0.0
    if k_alpha_pa is not None:
        n = 1.0 / max(0.3, math.cos(roll_rad))
        alpha = k_alpha_pa * n / (0.5 * air.density_kg_m3 * v * v)
        sig_alpha = 0.0
    theta_ref = gamma + alpha * math.cos(roll_rad)                    # eq. 22 (beta = 0)
    # eq. 37 analogue: sensitivity of asin(h_dot / v) to the altitude-rate noise
    sig_gamma = params.air_sigma_alt_rate_m_s / (v * math.sqrt(1.0 - s * s))
    sig_theta = math.sqrt(params.air_sigma_pitch_rad ** 2 + sig_gamma ** 2 + sig_alpha ** 2)
    return True, "", phi_ref, theta_ref, params.air_sigma_roll_rad, sig_theta, turn_gain


def _learn_alpha(k: float | None, euler_fc: np.ndarray, air: AirData | None, dt: float,
                 params: SyntheticAhrsParams) -> float | None:
    """alpha_meas = (theta_fc - asin(h_dot/v)) / cos(phi); k = alpha q_dyn / n, low-passed."""
    if air is None or not air.usable or dt <= 0.0:
        return k
    roll, pitch = float(euler_fc[0]), float(euler_fc[1])
    if abs(roll) > params.air_roll_limit_rad or abs(pitch) > params.air_pitch_limit_rad:
        return k
    v = air.tas_m_s
    gamma = math.asin(max(-0.99, min(0.99, air.alt_rate_m_s / v)))
    n = 1.0 / math.cos(roll)
    k_meas = (pitch - gamma) / math.cos(roll) * (0.5 * air.density_kg_m3 * v * v) / n
    if k is None:
        return k_meas
    return k + dt / (params.alpha_tau_s + dt) * (k_meas - k)


def _trust(state: SyntheticAhrsState, time_s: float, params: SyntheticAhrsParams) -> SyntheticAhrsState:
    trusted, why = health_trusted(state.health, time_s, params.health)
    if state.trusted and not trusted and state.kf2 is not None:
        # revert the gyro bias to a snapshot taken before the reference could have failed
        old = [snap for snap in state.bias_snapshots if time_s - snap[0] >= params.bias_revert_age_s]
        if old and state.health.silent_divergence and state.q_gyro_free is not None:
            # silent: also take back the attitude the failing reference pulled, re-propagating
            # the snapshot's attitude with our gyro-only increments since then
            t_s, b_g, b_m, q_s, qf_s, P_s = old[-1]
            q = quat_mul(quat_mul(q_s, quat_conj(qf_s)), state.q_gyro_free)
            # the snapshot's whole covariance goes with its attitude and biases (its attitude block
            # alone beside today's cross-covariances is no covariance: negative variances were seen,
            # runway_gnss_denied with the FC's yaw excluded), the attitude widened by the gyro-bias
            # error integrated since
            P = P_s.copy()
            P[0:3, 0:3] += np.eye(3) * (params.health.sigma_bias_rad_s * (time_s - t_s)) ** 2
            state = _upd(state, kf2=_upd(state.kf2, gyro_bias_rad_s=b_g.copy(), mag_bias=b_m.copy(),
                                         q_nav_from_body=q / math.sqrt(float(q @ q)), P=P))
        elif old:
            _, b_g, b_m = old[-1][:3]
            state = _upd(state, kf2=_upd(state.kf2, gyro_bias_rad_s=b_g.copy(), mag_bias=b_m.copy()))
    return _upd(state, trusted=trusted, trust_reason=why)


# --- the step -------------------------------------------------------------------------------

def synthetic_ahrs_step(state: SyntheticAhrsState, event, params: SyntheticAhrsParams,
                        output: bool = True) -> tuple[SyntheticAhrsState, SyntheticAhrsOutput | None]:
    """Process one event; returns the new state and the output after it (None until the first
    IMU sample, or when ``output`` is False: call ``synthetic_ahrs_output`` when needed)."""
    t = float(event.time_s)
    if not math.isfinite(t):
        raise ValueError(f"event time_s must be finite, got {event.time_s!r}")
    if isinstance(event, ImuEvent):
        state = _on_imu(state, event, params)
    elif isinstance(event, AirEvent):
        state = _on_air(state, event, params)
    elif isinstance(event, FcAttitudeEvent):
        state = _on_fc_attitude(state, event, params)
    elif isinstance(event, FcStatusEvent):
        h = state.health
        if event.system_status is not None:
            h = health_on_heartbeat(h, event.system_status)
        if event.attitude_ok is not None or event.horiz_pos_ok is not None:
            h = health_on_ekf_status(h, h.attitude_ok if event.attitude_ok is None else event.attitude_ok,
                                     h.horiz_pos_ok if event.horiz_pos_ok is None else event.horiz_pos_ok)
        state = _trust(_upd(state, health=h), t if state.time_s is None else state.time_s, params)
    elif isinstance(event, HeadingEvent):
        if state.b1 is not None:
            state = _upd(state, b1=b1_heading_step(state.b1, event.heading_rad, event.sigma_rad, t, params.b1))
    else:
        raise ValueError(f"unknown event type {type(event).__name__}")
    return state, (synthetic_ahrs_output(state, params) if output else None)


def _on_imu(state: SyntheticAhrsState, ev: ImuEvent, params: SyntheticAhrsParams) -> SyntheticAhrsState:
    C_bs = _C_bs(params)
    g_s = np.asarray(ev.gyro_sensor_rad_s, dtype=float)
    if g_s.shape != (3,) or not np.isfinite(g_s).all():
        return state                                     # a dropped/NaN sample is skipped
    gyro_b = C_bs @ g_s
    t = float(ev.time_s)
    if state.time_s is not None and t <= state.time_s:
        return state
    bias = _gyro_bias(state)
    w = gyro_b - bias
    seen_s, unseen_s = state.imu_integrated_s, state.imu_not_integrated_s
    if state.omega_lp_rad_s is None or state.time_s is None or state.q_gyro_free is None:
        wlp, qf = w, np.array([1.0, 0.0, 0.0, 0.0])
    else:
        dt = t - state.time_s
        wlp = state.omega_lp_rad_s + dt / (params.rate_lp_tau_s + dt) * (w - state.omega_lp_rad_s)
        qf = state.q_gyro_free
        if dt <= params.kf2.max_dt_s:
            seen_s += dt
            qf = quat_mul(qf, quat_from_rotvec(w * dt))   # rectangular: ample for the test
            qf = qf / math.sqrt(float(qf @ qf))
            if state.gyro_prev_rad_s is not None:
                # each step's error is (mean rate over the interval - sample) dt. Rate content at or
                # above the sample rate (vibration, noise) makes successive samples independent
                # about the mean, E|w_k - w_k-1|^2 = 2 sigma_w^2 per axis (3 axes: 6 sigma_w^2), and
                # each step adds sigma_w^2 dt^2 per axis: summed, the one-sample estimates average
                # out. Manoeuvres inflate it (conservative).
                sigma_w2 = float(np.sum((w - state.gyro_prev_rad_s) ** 2)) / 6.0
                state = _upd(state, gyro_free_var_rad2=state.gyro_free_var_rad2 + sigma_w2 * dt * dt)
        else:
            unseen_s += dt
            if state.health.anchors:
                # a gap: the gyro-only attitude did not see it, so the FC's change across it cannot be
                # compared with ours (it would read as a silent divergence): re-lay the anchors
                state = _upd(state, health=_upd(state.health, anchors=()))
    state = _upd(state, q_gyro_free=qf, omega_lp_rad_s=wlp, time_s=t, gyro_prev_rad_s=w, imu_integrated_s=seen_s,
                 imu_not_integrated_s=unseen_s)
    state = _trust(state, t, params)
    if state.b1 is not None:
        return _upd(state, b1=b1_imu_step(state.b1, gyro_b, t, params.b1))
    if state.kf2 is None:
        state = _upd(state, first_imu_time_s=t if state.first_imu_time_s is None else state.first_imu_time_s)
        return _init_without_reference(state, ev, C_bs, t, params)
    kf2, d2 = kf2_predict(state.kf2, gyro_b, t, params.kf2)
    state = _upd(state, kf2=kf2)
    if d2.reason.startswith("gap") and kf2_heading_var(kf2) > params.init_sigma_heading_rad ** 2:
        state = _upd(state, reacquire_heading=True)
    if state.trusted and (not state.bias_snapshots or t - state.bias_snapshots[-1][0] >= params.bias_snapshot_period_s):
        keep = tuple(s for s in state.bias_snapshots if t - s[0] <= 3.0 * params.bias_revert_age_s)
        snap = (t, kf2.gyro_bias_rad_s.copy(), kf2.mag_bias.copy(), kf2.q_nav_from_body.copy(),
                state.q_gyro_free.copy(), kf2.P.copy())
        state = _upd(state, bias_snapshots=keep + (snap,))
    if ev.mag_sensor_gauss is None:
        return state
    m_s = np.asarray(ev.mag_sensor_gauss, dtype=float)
    if m_s.shape != (3,) or not np.isfinite(m_s).all():
        return state
    mag_b = C_bs @ m_s
    Bn = np.array(params.field_nav_gauss)
    kf1_learning = bool(state.trusted and state.fc_last is not None and params.use_fc_yaw)
    k1t = state.kf1_learn.time_s
    if (kf1_learning
            and (k1t is None or t - k1t >= params.kf1.min_update_interval_s - 1e-6)):
        C_fc = dcm_from_euler(*state.fc_last[1])
        kf1, d1 = kf1_step(state.kf1_learn, mag_b, C_fc, Bn, wlp, t, params.kf1)
        state = _upd(state, kf1_learn=kf1,
                        n_kf1_rejected=state.n_kf1_rejected + (d1.reason in ("chi2 gate", "rate gate")))
    state = _upd(state, kf1_learning=kf1_learning)
    if t - state.last_mag_update_s >= params.mag_update_interval_s - 1e-6:
        m = mag_b
        if state.kf1_applied is not None and state.kf1_applied.field_norm_gauss is not None:
            m = kf1_correct_mag(state.kf1_applied, mag_b)
        if state.reacquire_heading:
            return _reacquire_heading(state, m, t, params)
        update = kf2_update_mag if params.mag_mode == "vector" else kf2_update_mag_heading
        kf2 = kf2_propagate(state.kf2, params.kf2)
        sens = state.ref_heading_sens
        if sens > 0.0:
            v0 = kf2_heading_var(kf2)
        kf2, d = update(kf2, m, Bn, params.kf2)
        if sens > 0.0 and d.fused and v0 > 0.0:
            sens *= min(1.0, kf2_heading_var(kf2) / v0)          # a <- (1 - k) a
        state = _upd(state, kf2=kf2, last_mag_update_s=t, ref_heading_sens=sens)
    return state


def _init_without_reference(state: SyntheticAhrsState, ev: ImuEvent, C_bs: np.ndarray, t: float,
                            params: SyntheticAhrsParams) -> SyntheticAhrsState:
    """Start KF2 with its heading from the magnetometer: at once when the FC is trusted but its yaw
    is not to be used (``use_fc_yaw`` False: roll/pitch from the FC, their sigma the FC's), else
    after ``init_without_reference_s`` with no trusted reference (e.g. a restart after the GNSS
    loss), level with wide sigmas. The field levelled with (roll, pitch), m_lev = C(roll, pitch, 0) m,
    is R3(psi)^T-rotated from the model's horizontal field, so psi = atan2(B_E, B_N) -
    atan2(m_lev_y, m_lev_x); air data, the FC's roll/pitch and the magnetometer then pull it in."""
    fc_tilt = state.trusted and not params.use_fc_yaw and state.fc_last is not None
    if (state.trusted and not fc_tilt) or ev.mag_sensor_gauss is None or (
            not fc_tilt and t - state.first_imu_time_s < params.init_without_reference_s):
        return state
    m = C_bs @ np.asarray(ev.mag_sensor_gauss, dtype=float)
    if not np.isfinite(m).all():
        return state
    if state.kf1_applied is not None and state.kf1_applied.field_norm_gauss is not None:
        m = kf1_correct_mag(state.kf1_applied, m)
    roll, pitch = (float(state.fc_last[1][0]), float(state.fc_last[1][1])) if fc_tilt else (0.0, 0.0)
    m_lev = dcm_from_euler(roll, pitch, 0.0) @ m
    if math.hypot(m_lev[0], m_lev[1]) <= 0.0:
        return state
    Bn = params.field_nav_gauss
    psi = math.atan2(Bn[1], Bn[0]) - math.atan2(m_lev[1], m_lev[0])
    kf2 = kf2_init(quat_from_euler(roll, pitch, psi), params.kf2,
                   sigma_tilt_rad=params.fc_sigma_tilt_rad if fc_tilt else params.init_sigma_tilt_rad,
                   sigma_heading_rad=params.init_sigma_heading_rad)
    return _upd(state, kf2=kf2, ref_heading_sens=0.0)


def _reacquire_heading(state: SyntheticAhrsState, mag_body_gauss: np.ndarray, t: float,
                       params: SyntheticAhrsParams) -> SyntheticAhrsState:
    """After a gap long enough that the heading is as good as unknown (its sigma above
    ``init_sigma_heading_rad``), the linearised magnetometer update cannot pull a heading that
    may be off by anything up to 180 deg. Take the heading from the magnetometer levelled with
    our roll/pitch instead (m_lev = C(roll, pitch, 0) (m - beta_hat |B|) = R3(psi) B_n, so
    psi = atan2(B_E, B_N) - atan2(m_lev_y, m_lev_x)), keep roll/pitch and their sigma, heading
    sigma ``init_sigma_heading_rad``; the magnetometer updates then refine it."""
    kf2 = state.kf2
    Bn = np.array(params.field_nav_gauss)
    e, cov = kf2_euler_and_cov(kf2)
    m = np.asarray(mag_body_gauss, dtype=float) - kf2.mag_bias * float(np.linalg.norm(Bn))
    m_lev = dcm_from_euler(float(e[0]), float(e[1]), 0.0) @ m
    if not math.hypot(m_lev[0], m_lev[1]) > 0.05 * float(np.linalg.norm(Bn)):
        return state                                     # no usable horizontal field: wait
    psi = math.atan2(Bn[1], Bn[0]) - math.atan2(m_lev[1], m_lev[0])
    q = quat_from_euler(float(e[0]), float(e[1]), psi)
    sigma_tilt = math.sqrt(max(cov[0, 0], cov[1, 1]))
    fresh = kf2_init(q, params.kf2, sigma_tilt_rad=sigma_tilt, sigma_heading_rad=params.init_sigma_heading_rad)
    P = kf2.P.copy()
    P[0:3, :] = 0.0
    P[:, 0:3] = 0.0
    P[0:3, 0:3] = fresh.P[0:3, 0:3]
    S = kf2.consider_sens
    if S is not None:
        S = S.copy()
        S[0:3, :] = 0.0                 # the attitude anew (its 30-deg heading sigma covers it)
    return _upd(state, kf2=_upd(kf2, q_nav_from_body=fresh.q_nav_from_body, P=P, n_resets=kf2.n_resets + 1,
                                consider_sens=S),
                reacquire_heading=False, ref_heading_sens=0.0, last_mag_update_s=t)


def synthetic_ahrs_forget_fc_yaw(state: SyntheticAhrsState, params: SyntheticAhrsParams,
                                 kf1_learn_start: Kf1State | None = None) -> SyntheticAhrsState:
    """The FC's yaw has just been excluded (``params.use_fc_yaw`` now False: e.g. it is our own
    heading fed back, found once the FC's parameters are read): drop what B took from it before.
    Excluding it only from now on is not enough: an FC seen before its GNSS fix may report a
    magnetic heading (ArduPlane's DCM: one declination off, 12.7 deg at CMAC) that B started from
    with the FC's 1.5 deg sigma, and at rest KF2's residual magnetometer-bias states then hold that
    offset (a heading error and a body-fixed bias look alike until the vehicle turns), so B
    published it for a minute with a ~1 deg sigma. Dropped, when B's heading carries any of the
    FC's yaw (consider sensitivity a > 0, module docstring):
    - the heading: sigma ``init_sigma_heading_rad`` at once (its cross-covariances zeroed), the
      value re-taken from the magnetometer at its next sample (``_reacquire_heading``), a = 0;
    - the residual magnetometer biases: back to 0 with their prior (they were learnt against it);
    - the bias snapshots (their attitude and magnetometer biases came with it).
    Roll/pitch and the gyro biases stay (the FC's roll/pitch stay a reference). KF1's estimate
    learnt against the FC's full attitude goes back to ``kf1_learn_start`` (where this flight's
    learning began; None: KF1's prior). Variant b1 takes no FC yaw: only KF1 is reset."""
    kf1 = kf1_init(params.kf1) if kf1_learn_start is None else kf1_learn_start
    state = _upd(state, kf1_learn=kf1, kf1_learning=False)
    kf2 = state.kf2
    if kf2 is None or not state.ref_heading_sens > 0.0:
        return state
    e, cov = kf2_euler_and_cov(kf2)
    fresh = kf2_init(kf2.q_nav_from_body, params.kf2, sigma_tilt_rad=math.sqrt(max(cov[0, 0], cov[1, 1])),
                     sigma_heading_rad=params.init_sigma_heading_rad)
    P = kf2.P.copy()
    for k in (slice(0, 3), slice(6, 9)):                  # attitude and magnetometer-bias blocks anew
        P[k, :] = 0.0
        P[:, k] = 0.0
    P[0:3, 0:3] = fresh.P[0:3, 0:3]
    P[6:9, 6:9] = fresh.P[6:9, 6:9]
    S = kf2.consider_sens
    if S is not None:
        S = S.copy()
        S[0:3, :] = 0.0
        S[6:9, :] = 0.0
    kf2 = _upd(kf2, mag_bias=np.zeros(3), P=P, n_resets=kf2.n_resets + 1, consider_sens=S)
    return _upd(state, kf2=kf2, ref_heading_sens=0.0, reacquire_heading=True, bias_snapshots=())


def synthetic_ahrs_takeoff(state: SyntheticAhrsState, params: SyntheticAhrsParams) -> SyntheticAhrsState:
    """The vehicle has just left the ground (the caller's launch detection, e.g. the Pipeline's
    phase LAUNCH): drop the residual magnetometer bias KF2 learnt at rest. At rest a body-fixed bias
    and a field that is fixed to the place (the launcher's steel, a vehicle, rebar: the simulator's
    ``site_distortion``) look alike, so KF2's bias states take the sum of both at a certainty the
    rest gave them; the place's part is gone a few metres up, and carried into the air at that
    certainty it turns the heading (measured, sim inclined_rail with the FC's yaw excluded: 20-26 deg
    off at a ~2 deg sigma after the launch). ArduPilot's EKF3 answers the same ground problem by
    re-learning yaw and field once clear of the ground. Here: the residual biases go back to 0 with
    their prior (``kf2.sigma_mag_bias_init``), their cross-covariances and consider sensitivities
    with the rest of KF2 zeroed (the attitude keeps its marginal variance, which at rest already
    spans a bias of the prior's size: the rest could not tell the two apart), and the bias snapshots
    (their magnetometer biases came from the ground) are dropped. The magnetometer then re-learns
    the biases in the air, where turns separate them from the heading. Variant b1 and a KF2 not yet
    started are left as they are."""
    kf2 = state.kf2
    if kf2 is None:
        return state
    P = kf2.P.copy()
    P[6:9, :] = 0.0
    P[:, 6:9] = 0.0
    P[6:9, 6:9] = np.eye(3) * params.kf2.sigma_mag_bias_init ** 2
    S = kf2.consider_sens
    if S is not None:
        S = S.copy()
        S[6:9, :] = 0.0
    kf2 = _upd(kf2, mag_bias=np.zeros(3), P=P, consider_sens=S)
    return _upd(state, kf2=kf2, bias_snapshots=())


def synthetic_ahrs_unseen(state: SyntheticAhrsState, unseen_s: float,
                          params: SyntheticAhrsParams) -> SyntheticAhrsState:
    """The FC clock restarted (the caller measured ``unseen_s`` seconds not seen, on its own
    clock): every time here belongs to the old clock. KF2's covariance grows as over a gap
    (``kf2_unseen``; the heading is re-taken from the magnetometer when that leaves it unknown),
    and the clocks restart at the next event: the integration, the update schedules, the FC
    attitude and its agreement anchors, the air-data filter, KF1's update schedule and the bias
    snapshots (taken on the old clock); the FC's estimator status is forgotten (a rebooted FC
    publishes its fallback attitude before its EKF runs: no reference until it says so again).
    Variant b1 is left as it is."""
    if not (math.isfinite(unseen_s) and unseen_s >= 0.0):
        raise ValueError(f"unseen_s must be finite and >= 0, got {unseen_s!r}")
    if state.kf2 is None:
        return state
    kf2 = kf2_unseen(state.kf2, unseen_s, params.kf2)
    kf2 = _upd(kf2, time_s=None, omega_prev_rad_s=None, cov_time_s=None, acc_angle_rad=None, acc_omega_sq=0.0)
    kf1 = state.kf1_learn
    if kf1 is not None:
        kf1 = _upd(kf1, time_s=None)
    return _upd(state, kf2=kf2, time_s=None, fc_last=None, air=AirDataState(), air_last=None,
                last_mag_update_s=-math.inf, last_air_update_s=-math.inf, last_ref_update_s=-math.inf,
                health=_upd(state.health, fc_time_s=None, anchors=(), check_time_s=None, good_since_s=None,
                            attitude_ok=None, horiz_pos_ok=None, first_attitude_s=None),
                bias_snapshots=(), kf1_learn=kf1,
                reacquire_heading=kf2_heading_var(kf2) > params.init_sigma_heading_rad ** 2)


def _on_air(state: SyntheticAhrsState, ev: AirEvent, params: SyntheticAhrsParams) -> SyntheticAhrsState:
    if state.air.time_s is not None and ev.time_s <= state.air.time_s:
        return state
    if not (math.isfinite(ev.press_abs_pa) and ev.press_abs_pa > 0.0):
        return _upd(state, air_active=False, air_off_reason="no valid static pressure")
    diff = ev.press_diff_pa if ev.press_diff_pa is not None and math.isfinite(ev.press_diff_pa) else None
    temp = ev.temperature_k if ev.temperature_k is not None and math.isfinite(ev.temperature_k) else None
    air_st, air = air_data_step(state.air, ev.press_abs_pa, diff, temp, ev.time_s, params.air)
    state = _upd(state, air=air_st, air_last=air)
    if state.b1 is not None:
        if state.trusted:
            return _upd(state, air_active=False, air_off_reason="reference trusted")
        b1 = b1_air_step(state.b1, air, params.b1)
        return _upd(state, b1=b1, air_active=b1.air_active, air_off_reason=b1.air_off_reason)
    if state.kf2 is None:
        return _upd(state, air_active=False, air_off_reason="not initialised")
    if state.trusted:
        return _upd(state, air_active=False, air_off_reason="reference trusted")
    if ev.time_s - state.last_air_update_s < params.air_update_interval_s - 1e-6:
        return state
    e, _ = kf2_euler_and_cov(state.kf2)
    w = state.omega_lp_rad_s if state.omega_lp_rad_s is not None else np.zeros(3)
    ok, why, phi_ref, theta_ref, s_phi, s_theta, gain = air_references(air, e[0], e[1], w, state.k_alpha_pa, params)
    if not ok:
        return _upd(state, air_active=False, air_off_reason=why)
    kf2, d = kf2_update_air(state.kf2, phi_ref, theta_ref, s_phi, s_theta, gain, params.kf2)
    return _upd(state, kf2=kf2, last_air_update_s=ev.time_s, air_active=d.fused,
                   air_off_reason="" if d.fused else "gated")


def _on_fc_attitude(state: SyntheticAhrsState, ev: FcAttitudeEvent, params: SyntheticAhrsParams) -> SyntheticAhrsState:
    e = np.asarray(ev.euler_rad, dtype=float)
    if e.shape != (3,) or not np.all(np.isfinite(e)):
        return state
    t = float(ev.time_s)
    prev = state.fc_last
    imu_behind = state.time_s is not None and t - state.time_s > params.kf2.max_dt_s
    if state.q_gyro_free is not None and imu_behind:
        # our gyro-only attitude is not current (an IMU gap not yet closed by a sample): no
        # agreement test across it, the anchors are re-laid
        state = _upd(state, health=_upd(state.health, fc_time_s=t, anchors=()))
    elif state.q_gyro_free is not None:
        C_fc = dcm_from_euler(*e)
        q_g = state.q_gyro_free
        if state.gyro_prev_rad_s is not None and state.time_s is not None and t != state.time_s:
            # our gyro-only attitude at the FC's time, not at our last sample's: carried by the last
            # rate over the difference (ArduPlane SITL: ATTITUDE up to 29.6 ms after the last RAW_IMU,
            # 2.3 deg at its 79 deg/s take-off rotation: read as "disagrees with gyros")
            q_g = quat_mul(q_g, quat_from_rotvec(state.gyro_prev_rad_s * (t - state.time_s)))
        h = health_on_attitude(state.health, C_fc, dcm_from_quat(q_g), t, params.health,
                               state.gyro_free_var_rad2)
        state = _upd(state, health=h)
    state = _upd(state, fc_last=(t, e.copy()))
    state = _trust(state, t if state.time_s is None else max(t, state.time_s), params)
    if state.b1 is not None:
        return _upd(state, b1=b1_reference_step(state.b1, e, t, state.trusted, state.air_last, params.b1))
    if not state.trusted:
        return state
    dt = 0.0 if prev is None else t - prev[0]
    state = _upd(state, k_alpha_pa=_learn_alpha(state.k_alpha_pa, e, state.air_last, dt, params))
    if state.kf2 is None:
        if state.time_s is None or not params.use_fc_yaw:   # (no FC yaw: started from the magnetometer)
            return state
        kf2 = kf2_init(quat_from_euler(*e), params.kf2, sigma_tilt_rad=params.fc_sigma_tilt_rad,
                       sigma_heading_rad=params.fc_sigma_yaw_rad)
        return _upd(state, kf2=kf2, last_ref_update_s=t, ref_heading_sens=1.0)
    if t - state.last_ref_update_s < params.ref_update_interval_s - 1e-6 or imu_behind:
        return state        # (behind an IMU gap: KF2 first accounts for the gap at the next sample)
    kf2 = kf2_propagate(state.kf2, params.kf2)
    v0 = kf2_heading_var(kf2)
    kf2, d = kf2_update_reference(kf2, e, t, params.fc_sigma_tilt_rad, params.fc_sigma_yaw_rad, params.kf2,
                                  use_yaw=params.use_fc_yaw)
    sens = state.ref_heading_sens
    if not params.use_fc_yaw:                                    # roll/pitch only: no FC yaw error inherited
        return _upd(state, kf2=kf2, last_ref_update_s=t)
    if d.fused:                                                  # the FC gave the heading back
        state = _upd(state, reacquire_heading=False)
    if d.reason == "reset to reference":
        sens = 1.0
    elif d.fused and v0 > 0.0:
        k = max(0.0, 1.0 - kf2_heading_var(kf2) / v0)
        sens = (1.0 - k) * sens + k                              # a <- (1 - k) a + k
    return _upd(state, kf2=kf2, last_ref_update_s=t, ref_heading_sens=sens)


def synthetic_ahrs_output(state: SyntheticAhrsState, params: SyntheticAhrsParams) -> SyntheticAhrsOutput | None:
    if state.time_s is None:
        return None
    common = dict(time_s=state.time_s, variant=params.variant, reference_trusted=state.trusted,
                  reference_reason=state.trust_reason, air_correction_active=state.air_active,
                  air_off_reason=state.air_off_reason, kf1_learning=state.kf1_learning,
                  kf1_applied_flights=None if state.kf1_applied is None else state.kf1_applied.flight_count,
                  gyro_bias_rad_s=_gyro_bias(state).copy(), kf1_rejected=state.n_kf1_rejected,
                  imu_integrated_s=state.imu_integrated_s, imu_not_integrated_s=state.imu_not_integrated_s)
    nan = math.nan
    if state.b1 is not None:
        o = b1_output(state.b1, params.b1)
        return SyntheticAhrsOutput(valid=state.b1.initialised, roll_rad=o.roll_rad, pitch_rad=o.pitch_rad,
                                   heading_rad=o.heading_rad, roll_sigma_rad=o.roll_sigma_rad,
                                   pitch_sigma_rad=o.pitch_sigma_rad, heading_sigma_rad=o.heading_sigma_rad,
                                   **common)
    if state.kf2 is None:
        return SyntheticAhrsOutput(valid=False, roll_rad=nan, pitch_rad=nan, heading_rad=nan,
                                   roll_sigma_rad=nan, pitch_sigma_rad=nan, heading_sigma_rad=nan, **common)
    e, cov = kf2_euler_and_cov(state.kf2)
    k = state.kf2
    # the filter's heading variance plus the FC yaw error it inherited and the magnetometer's
    # consider parameters' share (module docstring)
    var_h = cov[2, 2] + (state.ref_heading_sens * params.fc_sigma_yaw_rad) ** 2
    if params.consider_mag_errors:
        var_h += kf2_consider_euler_cov(k, _consider_cov(state, params))[2, 2]
    return SyntheticAhrsOutput(valid=True, roll_rad=float(e[0]), pitch_rad=float(e[1]), heading_rad=float(e[2]),
                               roll_sigma_rad=math.sqrt(cov[0, 0]), pitch_sigma_rad=math.sqrt(cov[1, 1]),
                               heading_sigma_rad=math.sqrt(var_h), mag_fused=k.n_mag_fused,
                               mag_rejected=k.n_mag_rejected, mag_gated=k.n_mag_gated, air_fused=k.n_air_fused,
                               air_rejected=k.n_air_rejected, ref_fused=k.n_ref_fused, **common)


class SyntheticAhrs:
    """Thin stateful wrapper around the pure step (holds the state, nothing else)."""

    def __init__(self, params: SyntheticAhrsParams, kf1_learn: Kf1State | None = None,
                 kf1_applied: Kf1State | None = None):
        self.params = params
        self.state = synthetic_ahrs_init(params, kf1_learn=kf1_learn, kf1_applied=kf1_applied)

    def step(self, event, output: bool = True) -> SyntheticAhrsOutput | None:
        self.state, out = synthetic_ahrs_step(self.state, event, self.params, output)
        return out
