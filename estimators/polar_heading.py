"""Heading filter of the polar-capable cascade (METHODS.md C, second filter).

Seed: CN108627154B. Fed by the attitude filter's roll/pitch AND their covariance
(estimators/polar_attitude.py); the heading source is the tilt-compensated magnetometer.

States (4): x = [psi (true heading, rad), w_v (vertical N-frame rate, Earth + transport, rad/s,
positive down, GM), b_y, b_z (lateral and vertical gyro biases, rad/s, GM)].

Kinematics (ZYX Euler rates of B w.r.t. N, w = gyro - bias, rates in rad/s):

    psi' = (w_y sin(phi) + w_z cos(phi)) / cos(theta) - w_v

where w_v is the down component of w_in (Earth + transport rate; at rest in the northern
hemisphere w_v = -W sin(L)). The exact term also has tan(theta) * (horizontal w_in along the
nose), < 1e-4 rad/s * tan(theta); it is left to the process noise.
Error model (first order), d = true - estimate:

    d_psi' = -d_w_v - sin(phi)/cos(theta) d_b_y - cos(phi)/cos(theta) d_b_z + J [d_phi, d_theta]
    J = [ (w_y cos(phi) - w_z sin(phi)) / cos(theta),
          (w_y sin(phi) + w_z cos(phi)) sin(theta) / cos(theta)^2 ]

The roll/pitch errors of the attitude filter are correlated over time; they enter as process
noise 2 tau_c J P_rp J^T dt (a coloured error of variance J P J^T and correlation time tau_c
adds ~2 sigma^2 tau_c per second of integration).

Measurement: magnetic heading from the levelled magnetometer plus the site declination
    m_lev = R_y(theta) R_x(phi) m_B,   psi_m = atan2(-m_lev_y, m_lev_x),   psi = psi_m + D
(east-positive declination D, as the WMM). Its variance is honest about what drives it:
    R = (sigma_m / H)^2 + (sigma_D^2 + G P_rp G^T + sigma_floor^2) * tau_m / dt_m,
    G = d psi_m / d(phi, theta)
(G grows like Z/H: near the magnetic pole a tiny tilt error is a large heading error; the
bracket is correlated over tau_m, so it is counted once per correlation time, not per sample,
and optionally (``consider_floor_fraction``) the REPORTED heading variance is kept >= a
fraction of the running mean of the bracket: a consider floor for errors that never average
out; the filter's own P, which sets the gain, is never floored).
The source is declared UNAVAILABLE when the measured horizontal field H is below
``min_horizontal_field_gauss``: no update, the heading variance then grows with the process
noise while roll/pitch (the attitude filter) are unaffected. Uncalibrated magnetometer (a consider term of the PUBLISHED variance, not of the gain): the
measurement above assumes a compensated magnetometer; hard and soft iron nobody has calibrated
(method D's coefficients not applied yet) give a heading error that depends on the heading itself
(one- and two-cycle deviation) and so is neither white nor visible to the filter: it moves with
every turn, the filter follows it, and P never contains it. A body-frame field error dm turns the
magnetic heading by
    d psi_m = g^T R dm,   g = [m_lev_y, -m_lev_x, 0] / H^2,   R = R_y(theta) R_x(phi) orthonormal,
so for a hard iron b with iid per-axis sigma s_h (gauss) and a soft iron dm = S m_B with iid
element sigma s_s (dimensionless), |g^T R| = 1/H and E|S m_B|^2 per axis = s_s^2 |m|^2:
    r_uncal = (s_h^2 + s_s^2 |m|^2) / H^2                           (rad^2)
(it grows like |m|/H towards the magnetic pole, as the tilt term). When the caller says how well
the magnetometer is compensated (``HeadingInputs.mag_residual_sigma_gauss`` = s_r, e.g. method D's
per-axis residual with its coefficients applied), r_uncal = max(0, s_r^2 - mag_noise^2) / H^2 (the
white part is already in R). ``polar_heading_estimate`` publishes P_psi (or the consider floor)
+ r_uncal; the state, the gain and the gate are unchanged.
Field mismatch (what the magnetometer itself shows of its error; issue 18 item 3). The priors above
say how well an airframe is usually compensated; the measurement can say that THIS one is not: when
the caller gives the model's field at the site (``HeadingInputs.field_model_ned_gauss``, e = [e_N,
e_E, e_D]), the levelled measurement's horizontal magnitude H and down component Z are compared
with the model's H_0 = hypot(e_N, e_E), Z_0 = e_D, |B_0| = hypot(H_0, Z_0). A field error dm (level
frame) shows, to first order, along the field itself (the norm) and along the normal to it in the
magnetic meridian (the dip),
    dm . n = (H Z_0 - Z H_0) / |B_0| = |m| sin(dip_0 - dip),
and hides along the horizontal normal to the field u_p, the one that turns the heading:
d psi_m = (dm . u_p) / H. The norm is left out: a scale error (a calibration normalised to another
field strength, a gain) changes only the norm and turns no heading; ArduPilot's MAG in
arducopter-rtl-midflight.bin reads 9 % low at the right dip with a 1.5 deg heading error against
its GNSS-aided FC (counting the norm gave C a 12-15 deg sigma there). With no preferred direction
for the rest of dm (hard iron, motor currents, an anomaly: per-axis sigma s), dm . n estimates s^2
and so the variance of the hidden component. The error is correlated (it is what the heading rests
on, not noise), so s^2 is the running mean of (dm . n)^2 over the measurements that entered the
heading (initialised, fused, reset on; a reset or the first one starts it over), time constant
``mag_error_tau_s`` in the measurements' time:
    s^2 <- s^2 + ((dm . n)^2 - s^2) min(1, dt / mag_error_tau_s),  dt = min(interval, mag_update_period_s)
    r_mis = max(0, s^2 - mag_noise^2) / H^2                                     (rad^2)
and the consider term is max(r_uncal, r_mis): the measured mismatch can only widen what the prior
says (one component is a small sample: for an isotropic dm of one draw the hidden component is
within 2 s of this estimate only 70 % of the time, 80 % within 3 s: their ratio is Cauchy; the
bench has them as 70 % and 89 % with the prior, tests/test_polar_heading_field_mismatch.py).
Example: PX4's vehicle_magnetometer in the px4-quad-no-gnss log (bench/real_logs.py) reads a dip of
75 deg at the first sample C takes (the model's 63.5 deg at the assumed site): dm . n = 0.08 G, a
published sigma of 27 deg where the calibrated prior (0.016 G hard iron, 1 deg soft iron) said 8 deg;
in flight 66.5 deg (0.023 G).
An innovation gate rejects
disturbed samples; after ``reset_after_s`` of continuous rejection the heading is re-initialised
from the source (reported in the diagnostics: ``reset=True`` with the jump).

Platform formulation (issue 18: heading in every attitude; used when the caller gives the attitude
filter's ``q_P_from_body``). The Euler rate above divides by cos(theta) and has no meaning at pitch
+-90 deg. Here the filter keeps its OWN body attitude C_HB in a level frame H (nothing Euler in it):
each step it is turned by the gyro increment (w - b_hat) dt, b_hat the filter's own 3-axis bias,
and then given the attitude filter's tilt by the smallest body rotation (axis g_att x g_pred, g the
down direction in body axes: normal to the vertical, so it never turns H about the vertical; the
attitude filter's corrections about its own unobservable vertical, and its vertical bias, never
reach the heading). The body's attitude in NED is then
    C_nav_from_body = R_z(psi_H) C_HB,
and the filter estimates psi_H, the azimuth of H from true north. States (5):
[psi_H, w_v, b_x, b_y, b_z]; kinematics (C_NH = C_NB C_BH, to first order in the tilt)
    psi_H' = e_z^T C_HB (b_hat - b) - w_v        (error model: F[psi, b] = -e_z^T C_HB dt),
w_v as above (GM). Measurement: the magnetometer levelled by the full rotation, m_H = C_HB m_B,
psi_m = D - atan2(m_H_y, m_H_x). A tilt error t (the horizontal components of C_HB eps, eps the
attitude filter's body-frame error, covariance C_HB P_eps C_BH) turns it by
    d psi_m = -m_z (m_x t_x + m_y t_y) / H^2      (G = -m_z/H^2 [m_x, m_y]; |G| = tan(dip)),
and the same consider/inflation rules as above apply (R, r_uncal). Heading observable in every
attitude; unobservable (no update, sigma grows) only where the levelled horizontal field is below
``min_horizontal_field_gauss``. The published attitude is composed, R_z(psi_H) C_HB
(``polar_heading_attitude``), never from Euler angles, whose roll and yaw are one degree of freedom
at pitch +-90 deg; the heading is its Euler yaw, psi_H + yaw(C_HB).

Pure: ``polar_heading_step(state, inputs, params) -> (state, diag)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.rotations import (dcm_from_euler, dcm_from_quat, euler_from_dcm, quat_from_euler, quat_from_rotvec,
                                  quat_mul, quat_normalize, wrap_2pi, wrap_pi)

EARTH_RATE_RAD_S = 7.292115e-5
WITHHELD_AFTER_S = 1.0
"""No measurement for this long (s): the magnetometer was withheld (a disturbance), not rejected."""
EARTH_RADIUS_M = 6.371e6


def vertical_rate_sigma_for_site(lat_rad: float, speed_m_s: float) -> float:
    """A sigma (rad/s) for the vertical N-frame rate near a configured site: Earth rate plus the
    vertical transport rate v_E tan(L) / R that a vehicle flying at ``speed_m_s`` east/west can
    have (this is the polar singularity of a north-referenced heading: at 89.9 deg and 22 m/s it
    is ~0.1 deg/s). |L| is capped at 89.99 deg."""
    if not (math.isfinite(lat_rad) and abs(lat_rad) <= math.pi / 2):
        raise ValueError(f"lat_rad must be in [-pi/2, pi/2], got {lat_rad}")
    if not (math.isfinite(speed_m_s) and speed_m_s >= 0.0):
        raise ValueError(f"speed_m_s must be finite and >= 0, got {speed_m_s}")
    tan_l = math.tan(min(abs(lat_rad), math.radians(89.99)))
    return math.hypot(EARTH_RATE_RAD_S, speed_m_s * tan_l / EARTH_RADIUS_M)


@dataclass(frozen=True)
class PolarHeadingParams:
    """Units in the names; defaults for a consumer MEMS IMU and magnetometer."""

    gyro_noise_rad_s_rt_hz: float = math.radians(0.01)
    """Gyro angle random walk (rad/s/sqrt(Hz))."""
    gyro_bias_sigma_rad_s: float = math.radians(0.2)
    """Sigma of the lateral/vertical gyro bias GM processes (rad/s) (after pre-launch levelling)."""
    gyro_bias_tau_s: float = 3600.0
    vertical_rate_sigma_rad_s: float = EARTH_RATE_RAD_S
    """Sigma of the vertical N-frame rate GM process (rad/s); |W sin L| <= W at rest. In flight
    near the pole the transport rate dominates: see ``vertical_rate_sigma_for_site``."""
    vertical_rate_tau_s: float = 600.0
    attitude_error_tau_s: float = 10.0
    """Correlation time tau_c of the attitude filter's roll/pitch errors (s)."""
    heading_process_floor_rad_s_rt_hz: float = math.radians(0.005)
    """Extra heading random walk for unmodelled terms (tan(theta) w_in, scale factors)."""
    mag_noise_gauss: float = 0.003
    """Per-sample magnetometer noise (gauss, per axis, after deviation compensation)."""
    mag_heading_floor_rad: float = math.radians(1.0)
    """Floor on the heading-measurement sigma (residual deviation, local anomalies)."""
    min_horizontal_field_gauss: float = 0.03
    """Below this measured horizontal field the heading source is declared unavailable.
    WMM marks H < 0.02 G as its blackout zone and H < 0.06 G as caution; between 0.03 and
    0.06 G the measurement variance above already down-weights the source."""
    mag_update_period_s: float = 0.1
    """Interval between heading measurements (s)."""
    mag_error_tau_s: float = 30.0
    """Correlation time of the non-white heading-measurement errors (tilt error, declination,
    residual deviation) (s); their variance is inflated by tau / mag_update_period_s."""
    mag_error_turn_rad: float = 1.0
    """Body rotation over which the body-fixed part of those errors decorrelates (rad; platform
    formulation). The tilt error (an accelerometer bias, fixed in the body) and the residual
    deviation reach the heading through the body's attitude: G . t with t the tilt error in the
    level frame, a one-cycle deviation b cos(psi + c). Once the body has turned by ~1 rad their
    heading error is another draw (cos(1 rad) = 0.54 correlation left; 0 after a quarter turn), so
    while the body turns at |w| they count once per min(mag_error_tau_s, this / |w|); the
    declination error, fixed in the navigation frame, stays counted once per mag_error_tau_s.
    0 = off (all once per mag_error_tau_s)."""
    consider_floor_fraction: float = 0.0
    """Fraction of the correlated measurement variance (running mean) below which the reported
    heading variance never goes (1 = the full consider bound, very conservative when the vehicle
    turns and tilt errors average out; 0 = off: only the inflated fusion above limits the
    confidence; bench/polar_accuracy.py: heading NEES ~1.3 consumer, ~0.1 tactical with 0)."""
    uncalibrated_hard_iron_gauss: float = 0.016
    """Per-axis sigma of the hard iron an uncompensated magnetometer carries (gauss, body axes),
    for the consider term r_uncal of the published heading variance (module docstring). 0.016 G:
    ArduPilot's compass calibration accepts a fit whose RMS residual is up to COMPASS_CAL_FIT =
    16 mGauss (its default; MAG_CAL_REPORT.fitness is that residual in mGauss), and RAW_IMU carries
    that residual (was 0.013, the mean hard iron of the shipped scenarios: fitted to them). The
    daemon takes it from ``[heading] uncalibrated_hard_iron_gauss``."""
    uncalibrated_soft_iron: float = 0.0175
    """Per-element sigma of the soft-iron matrix I + S of an uncompensated magnetometer
    (dimensionless), equally the per-axis sigma (rad) of a rotation of the magnetometer's axes
    against the IMU's: a rotation r gives dm = r x m, whose heading part is r . (m x u) / H with u
    the horizontal unit vector normal to the field and |m x u| = |m|, so its variance s^2 |m|^2 / H^2
    is the iid-element soft-iron term of r_uncal (module docstring). An ellipsoid compass calibration
    (ArduPilot's COMPASS_CAL, PX4's) fits offsets, scales and cross-coupling from the field's norm and
    cannot see that rotation. 0.0175 = 1 deg per axis, the low end of the 1-2 deg OpenPilot's
    calibration work measured between a magnetometer and its accelerometer (OpenPilot README of its
    calibration branch). Was 0.01, the RMS element of the inclined_rail scenario's soft iron (fitted
    to it). The daemon takes it from ``[heading] uncalibrated_soft_iron``."""
    gate_chi2: float = 11.0
    """Innovation gate (1 dof NIS, 99.9 %)."""
    reset_after_s: float = 10.0
    """Continuous rejection longer than this re-initialises the heading from the source."""
    max_abs_pitch_rad: float = math.radians(85.0)
    """Above this |pitch| the heading kinematics are singular: no propagation of psi from the
    gyros (variance still grows) and no measurement."""
    max_dt_s: float = 0.1
    unseen_rate_sigma_rad_s: float = math.radians(20.0)
    """Over an interval the filter did not see (a gap longer than ``max_dt_s``, or one reported
    with ``polar_heading_unseen``) the vehicle kept turning: the heading variance grows by
    (this rate x the interval)^2 (rad/s; a coordinated turn is 10-30 deg/s) ..."""
    unseen_max_sigma_rad: float = math.pi
    """... up to this sigma (rad): after a few unseen seconds the heading is as good as unknown
    and the next magnetometer measurement takes it back."""

    def __post_init__(self) -> None:
        for name, v in self.__dict__.items():
            if name == "consider_floor_fraction":
                if not 0.0 <= v <= 1.0:
                    raise ValueError(f"consider_floor_fraction must be in [0, 1], got {v!r}")
            elif name in ("uncalibrated_hard_iron_gauss", "uncalibrated_soft_iron", "mag_error_turn_rad"):
                if not (math.isfinite(v) and v >= 0.0):
                    raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
            elif not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if self.max_abs_pitch_rad >= math.pi / 2:
            raise ValueError(f"max_abs_pitch_rad must be < pi/2, got {self.max_abs_pitch_rad}")


@dataclass(frozen=True)
class PolarHeadingState:
    initialised: bool = False
    time_s: float | None = None
    x: np.ndarray = field(default_factory=lambda: np.zeros(4))
    """[psi rad in [0, 2pi), w_v rad/s, b_y rad/s, b_z rad/s]."""
    P: np.ndarray = field(default_factory=lambda: np.zeros((4, 4)))
    last_mag_time_s: float | None = None
    source_available: bool = False
    rejected_since_s: float | None = None
    n_fused: int = 0
    n_rejected: int = 0
    n_resets: int = 0
    r_corr_avg_rad2: float | None = None
    """Running mean (time constant mag_error_tau_s) of the correlated measurement variance:
    the consider floor of the reported heading variance."""
    r_uncal_rad2: float = 0.0
    """Consider term of the uncalibrated (or residual) magnetometer error of the last measurement
    that entered the heading (initialised, fused or reset on; not a gated-out one) (rad^2, module
    docstring), added to the published heading variance; the field mismatch's when that is larger."""
    field_mismatch_gauss2: float | None = None
    """Running mean of the per-axis field-error variance the measurements that entered the heading
    show against the model (gauss^2, module docstring: field mismatch); None: no model given."""
    field_mismatch_time_s: float | None = None
    """Time of the measurement that last updated ``field_mismatch_gauss2`` (None after an unseen
    interval: the next one starts it over)."""
    platform: bool = False
    """True: the platform formulation (x = [psi_P, w_v, d_x, d_y, d_z], module docstring)."""
    q_P_from_body: np.ndarray | None = None
    """Platform mode: the filter's own body attitude C_HB (level frame H) at the last step."""
    gyro_bias_prev_rad_s: np.ndarray | None = None
    """Unused (kept so saved states still load)."""

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "PolarHeadingState":
        kw = dict(d)
        for k in ("x", "P", "q_P_from_body", "gyro_bias_prev_rad_s"):
            if kw.get(k) is not None:
                kw[k] = np.array(kw[k], float)
        return cls(**kw)


@dataclass(frozen=True)
class HeadingInputs:
    """One IMU sample plus what the heading filter is fed with."""
    time_s: float
    gyro_body_rad_s: np.ndarray
    roll_rad: float
    pitch_rad: float
    cov_roll_pitch_rad2: np.ndarray
    """2x2 covariance of (roll, pitch) from the attitude filter."""
    mag_body_gauss: np.ndarray | None = None
    """Deviation-compensated magnetometer (body axes), None when no new sample."""
    declination_rad: float = math.nan
    """Site declination, east positive (field model at the configured site)."""
    declination_sigma_rad: float = 0.0
    mag_residual_sigma_gauss: float | None = None
    """Per-axis sigma (gauss) of the magnetometer error its compensation leaves in
    ``mag_body_gauss`` (e.g. method D's residual when its coefficients are applied; 0 = exactly
    compensated, as a clean simulation); None = not compensated: the params' uncalibrated
    hard/soft-iron model sets the consider term."""
    q_P_from_body: np.ndarray | None = None
    """The attitude filter's attitude in its platform frame P: given, the platform formulation
    (module docstring) runs and ``roll_rad``/``pitch_rad`` only level the magnetometer when
    ``level_with_roll_pitch``; None, the Euler formulation."""
    cov_att_body_rad2: np.ndarray | None = None
    """Platform mode: 3x3 covariance of the attitude filter's body-frame attitude error eps."""
    gyro_bias_rad_s: np.ndarray | None = None
    """Platform mode: the attitude filter's gyro-bias estimate (body, rad/s); informational: the
    filter integrates with its own bias (module docstring)."""
    level_with_roll_pitch: bool = False
    """Platform mode: level the magnetometer with R_z(yaw of C_PB) R_y(pitch) R_x(roll) and
    ``cov_roll_pitch_rad2`` (e.g. a trusted FC's tilt) instead of C_PB's own tilt."""
    field_model_ned_gauss: np.ndarray | None = None
    """The field model's Earth field at the site (NED, gauss): the levelled measurement's horizontal
    magnitude and down component against it set the field-mismatch consider term (module
    docstring); None: not judged (the priors alone)."""


@dataclass(frozen=True)
class HeadingDiag:
    measured: bool = False
    """A heading measurement was formed at this step."""
    fused: bool = False
    source_available: bool = False
    horizontal_field_gauss: float = math.nan
    heading_meas_rad: float = math.nan
    innovation_rad: float = math.nan
    innovation_var_rad2: float = math.nan
    test_ratio: float = math.nan
    reset: bool = False
    reset_jump_rad: float = 0.0
    reason: str = ""


@dataclass(frozen=True)
class HeadingEstimate:
    heading_rad: float
    """True heading in [0, 2pi) (nan before the first measurement or init)."""
    variance_rad2: float
    source_available: bool
    initialised: bool


def polar_heading_init(heading_rad: float | None = None, sigma_rad: float | None = None,
                       params: PolarHeadingParams = PolarHeadingParams(),
                       gyro_bias_yz_rad_s: tuple[float, float] | None = None) -> PolarHeadingState:
    """A filter waiting for its first measurement, or seeded with a known heading (e.g. the
    launcher azimuth) and its sigma. ``gyro_bias_yz_rad_s``: optional prior of the lateral and
    vertical gyro biases, e.g. the pre-launch mean rate at rest (it then also holds the Earth
    rate seen at rest, which is what w_v + b_z must cancel: only their sum is observable level)."""
    x = np.zeros(4)
    if gyro_bias_yz_rad_s is not None:
        b = np.asarray(gyro_bias_yz_rad_s, float)
        if b.shape != (2,) or not np.all(np.isfinite(b)):
            raise ValueError(f"gyro_bias_yz_rad_s must be 2 finite numbers, got {gyro_bias_yz_rad_s!r}")
        x[2:4] = b
    if heading_rad is None:
        return PolarHeadingState(x=x)
    if not (math.isfinite(heading_rad) and sigma_rad is not None and math.isfinite(sigma_rad)
            and sigma_rad > 0.0):
        raise ValueError(f"heading_rad and sigma_rad > 0 must be finite, got {heading_rad}, {sigma_rad}")
    x[0] = wrap_2pi(heading_rad)
    return PolarHeadingState(initialised=True, x=x, P=_prior_P(sigma_rad ** 2, params))


def _prior_P(var_psi: float, p: PolarHeadingParams, n: int = 4) -> np.ndarray:
    return np.diag([var_psi, p.vertical_rate_sigma_rad_s ** 2] + [p.gyro_bias_sigma_rad_s ** 2] * (n - 2))


def magnetic_heading(mag_body_gauss: np.ndarray, roll_rad: float, pitch_rad: float) -> tuple[float, float]:
    """(magnetic heading in [0, 2pi), horizontal field in gauss) of a levelled magnetometer."""
    m = mag_body_gauss
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    # m_lev = R_y(theta) R_x(phi) m
    my = cr * m[1] - sr * m[2]
    mz1 = sr * m[1] + cr * m[2]
    mx = cp * m[0] + sp * mz1
    return wrap_2pi(math.atan2(-my, mx)), math.hypot(mx, my)


def polar_heading_step(state: PolarHeadingState, u: HeadingInputs,
                       params: PolarHeadingParams = PolarHeadingParams()
                       ) -> tuple[PolarHeadingState, HeadingDiag]:
    if u.q_P_from_body is not None:
        return _platform_step(state, u, params)
    w = np.asarray(u.gyro_body_rad_s, float)
    if (w.shape != (3,) or not np.all(np.isfinite(w)) or not math.isfinite(u.time_s)
            or not math.isfinite(u.roll_rad) or not math.isfinite(u.pitch_rad)):
        return state, HeadingDiag(reason="non-finite input", source_available=state.source_available)
    Prp = np.asarray(u.cov_roll_pitch_rad2, float)
    st = state
    if st.time_s is not None:
        dt = u.time_s - st.time_s
        if dt <= 0.0:
            return st, HeadingDiag(reason=f"time not increasing (dt={dt:.6f} s)")
        if dt <= params.max_dt_s and st.initialised:
            st = _predict(st, dt, w, u.roll_rad, u.pitch_rad, Prp, params)
        elif st.initialised:  # a gap: not integrated, the heading may have turned meanwhile
            st = polar_heading_unseen(st, dt, params)
    st = replace(st, time_s=u.time_s)
    if u.mag_body_gauss is None:
        return st, HeadingDiag(source_available=st.source_available)
    if st.last_mag_time_s is not None and u.time_s - st.last_mag_time_s + 1e-9 < params.mag_update_period_s:
        return st, HeadingDiag(source_available=st.source_available)
    return _measure(st, u, Prp, params)


def polar_heading_unseen(state: PolarHeadingState, unseen_s: float,
                         params: PolarHeadingParams = PolarHeadingParams()) -> PolarHeadingState:
    """Account for ``unseen_s`` seconds without samples: the heading is kept but its variance
    grows by min(unseen_rate_sigma_rad_s * unseen_s, unseen_max_sigma_rad)^2, and the GM states
    relax over the interval, so the next magnetometer measurement pulls the heading back and the
    published variance says how stale it is meanwhile."""
    if not (math.isfinite(unseen_s) and unseen_s >= 0.0):
        raise ValueError(f"unseen_s must be finite and >= 0, got {unseen_s!r}")
    if not state.initialised:
        return state
    a_v, q_v = _gm(unseen_s, params.vertical_rate_tau_s, params.vertical_rate_sigma_rad_s)
    a_b, q_b = _gm(unseen_s, params.gyro_bias_tau_s, params.gyro_bias_sigma_rad_s)
    n = len(state.x)
    f = np.array([1.0, a_v] + [a_b] * (n - 2))
    P = f[:, None] * state.P * f[None, :] + np.diag([0.0, q_v] + [q_b] * (n - 2))
    s = min(params.unseen_rate_sigma_rad_s * unseen_s, params.unseen_max_sigma_rad)
    P[0, 0] += s * s
    x = state.x.copy()
    x[1] *= a_v
    # the next sample restarts the time (a restarted clock may start lower)
    return replace(state, x=x, P=P, time_s=None, last_mag_time_s=None, field_mismatch_time_s=None)


def _predict(st, dt, w, phi, th, Prp, p):
    x = st.x
    sphi, cphi = math.sin(phi), math.cos(phi)
    cth = math.cos(th)
    frozen = abs(th) > p.max_abs_pitch_rad
    cth_eff = max(abs(cth), math.cos(p.max_abs_pitch_rad))
    wy, wz = w[1] - x[2], w[2] - x[3]
    psi_dot = 0.0 if frozen else (wy * sphi + wz * cphi) / cth_eff - x[1]
    a_v, q_v = _gm(dt, p.vertical_rate_tau_s, p.vertical_rate_sigma_rad_s)
    a_b, q_b = _gm(dt, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s)
    F = np.eye(4)
    F[0, 1] = -dt
    F[0, 2] = -sphi / cth_eff * dt
    F[0, 3] = -cphi / cth_eff * dt
    F[1, 1] = a_v
    F[2, 2] = a_b
    F[3, 3] = a_b
    J = np.array([(wy * cphi - wz * sphi) / cth_eff,
                  (wy * sphi + wz * cphi) * math.sin(th) / (cth_eff * cth_eff)])
    q_psi = ((p.gyro_noise_rad_s_rt_hz ** 2 / (cth_eff * cth_eff)
              + p.heading_process_floor_rad_s_rt_hz ** 2) * dt
             + 2.0 * p.attitude_error_tau_s * float(J @ Prp @ J) * dt)
    P = F @ st.P @ F.T
    P[0, 0] += q_psi
    P[1, 1] += q_v
    P[2, 2] += q_b
    P[3, 3] += q_b
    xn = np.array([wrap_2pi(x[0] + psi_dot * dt), x[1] * a_v, x[2], x[3]])
    return replace(st, x=xn, P=P)


def _gm(dt, tau, sigma):
    a = math.exp(-dt / tau)
    return a, sigma * sigma * (1.0 - a * a)


def _mag_sample(st, u):
    """(m body gauss, state with the sample's time, None) or (None, st, the diag of a refused sample)."""
    m = np.asarray(u.mag_body_gauss, float)
    if m.shape != (3,) or not np.all(np.isfinite(m)):
        return None, st, HeadingDiag(reason="non-finite magnetometer", source_available=st.source_available)
    if not math.isfinite(u.declination_rad):
        raise ValueError("declination_rad must be finite when a magnetometer sample is given")
    return m, replace(st, last_mag_time_s=u.time_s), None


def _measure(st, u, Prp, p):
    m, st, bad = _mag_sample(st, u)
    if bad is not None:
        return st, bad
    if abs(u.pitch_rad) > p.max_abs_pitch_rad:
        return st, HeadingDiag(reason="pitch beyond max_abs_pitch_rad", source_available=st.source_available)
    psi_m, H = magnetic_heading(m, u.roll_rad, u.pitch_rad)
    if H < p.min_horizontal_field_gauss:
        st = replace(st, source_available=False)
        return st, HeadingDiag(measured=False, source_available=False, horizontal_field_gauss=H,
                               reason=f"horizontal field {H:.4f} G < {p.min_horizontal_field_gauss} G")
    # sensitivity of the magnetic heading to roll and pitch (central differences)
    h = 1e-5
    G = np.array([
        wrap_pi(magnetic_heading(m, u.roll_rad + h, u.pitch_rad)[0]
                - magnetic_heading(m, u.roll_rad - h, u.pitch_rad)[0]) / (2 * h),
        wrap_pi(magnetic_heading(m, u.roll_rad, u.pitch_rad + h)[0]
                - magnetic_heading(m, u.roll_rad, u.pitch_rad - h)[0]) / (2 * h)])
    # white part (magnetometer noise) + correlated part (tilt error, declination, residual
    # deviation): the latter does not average out over the 1/mag_update_period_s samples fused
    # per second, so it is inflated by tau_c / dt (one independent sample per correlation time)
    r_white = (p.mag_noise_gauss / H) ** 2
    r_corr = u.declination_sigma_rad ** 2 + float(G @ Prp @ G) + p.mag_heading_floor_rad ** 2
    R = r_white + r_corr * max(1.0, p.mag_error_tau_s / p.mag_update_period_s)
    R_single = r_white + r_corr          # the error of ONE measurement (initialisation, reset)
    z = wrap_2pi(psi_m + u.declination_rad)
    r_uncal = uncalibrated_heading_var(m, H, u.mag_residual_sigma_gauss, p)
    mis = field_mismatch_var(H, _levelled_down(m, u.roll_rad, u.pitch_rad), u.field_model_ned_gauss)
    return _fuse_heading(st, u, z, H, R, R_single, r_corr, r_uncal, p, mis)


def _levelled_down(m: np.ndarray, roll_rad: float, pitch_rad: float) -> float:
    """Down component (gauss) of R_y(theta) R_x(phi) m (``magnetic_heading``'s levelling)."""
    mz1 = math.sin(roll_rad) * m[1] + math.cos(roll_rad) * m[2]
    return -math.sin(pitch_rad) * m[0] + math.cos(pitch_rad) * mz1


def field_mismatch_var(horizontal_field_gauss: float, down_field_gauss: float,
                       field_model_ned_gauss: np.ndarray | None) -> float | None:
    """Per-axis variance (gauss^2) of the field error one levelled measurement (horizontal
    magnitude H, down component Z) shows against the model (module docstring, field mismatch): its
    component normal to the model's field in the magnetic meridian, squared,
    ((H Z_0 - Z H_0) / |B_0|)^2 (a scale error, along the field, is none); None when the model is
    not given."""
    if field_model_ned_gauss is None:
        return None
    e = np.asarray(field_model_ned_gauss, float)
    if e.shape != (3,) or not np.all(np.isfinite(e)) or not math.hypot(e[0], e[1], e[2]) > 0.0:
        raise ValueError(f"field_model_ned_gauss must be 3 finite numbers (NED, gauss), not all 0, or None, "
                         f"got {field_model_ned_gauss!r}")
    H0 = math.hypot(e[0], e[1])
    dn = (horizontal_field_gauss * e[2] - down_field_gauss * H0) / math.hypot(H0, e[2])
    return dn * dn


def _consider(st, t, H, r_uncal, mis, p, restart):
    """(field_mismatch_gauss2, field_mismatch_time_s, consider term rad^2) once a measurement with
    prior term ``r_uncal`` and mismatch ``mis`` enters the heading (module docstring)."""
    if mis is None:
        return None, None, r_uncal
    prev, t_prev = st.field_mismatch_gauss2, st.field_mismatch_time_s
    if restart or prev is None or t_prev is None:
        avg = mis
    else:
        # one measurement's weight: its interval, at most the measurement period (a gap in which
        # nothing entered is not measured time: after a 25 s magnet rejection the first sample
        # alone replaced the mean, tests/test_mag_disturbance_pipeline.py magnet attached)
        dt = min(max(0.0, t - t_prev), p.mag_update_period_s)
        avg = prev + (mis - prev) * min(1.0, dt / p.mag_error_tau_s)
    return avg, t, max(r_uncal, max(0.0, avg - p.mag_noise_gauss ** 2) / (H * H))


def _fuse_heading(st, u, z, H, R, R_single, r_corr, r_uncal, p, mis=None):
    """Initialise from, gate, fuse (or reset on) one heading measurement z (rad) of state x[0].
    ``r_uncal``: the measurement's uncalibrated-magnetometer consider term; it becomes the state's
    (the published one) only where the measurement enters the heading (initialised, fused, reset):
    a gated-out sample is not in the estimate, and its field (a magnet nearby: a larger H) says
    nothing about the error the estimate carries (it shrank C's published sigma 2.84 -> 1.88 deg
    for the 20 s the magnet stayed, bench/any_motion.py magnet_nearby seed 1). ``mis``: its field
    mismatch (``field_mismatch_var``, None: no model), averaged in by the same rule (``_consider``)."""
    n = len(st.x)
    if not st.initialised:
        x0 = st.x.copy()
        x0[0], x0[1] = z, 0.0
        fm, fm_t, r_uncal = _consider(st, u.time_s, H, r_uncal, mis, p, True)
        st = replace(st, initialised=True, x=x0, P=_prior_P(R_single, p, n), source_available=True,
                     r_uncal_rad2=r_uncal, field_mismatch_gauss2=fm, field_mismatch_time_s=fm_t)
        return st, HeadingDiag(measured=True, fused=True, source_available=True,
                               horizontal_field_gauss=H, heading_meas_rad=z, innovation_rad=0.0,
                               innovation_var_rad2=R_single, test_ratio=0.0, reason="initialised from source")
    nu = wrap_pi(z - st.x[0])
    S = st.P[0, 0] + R
    # the gate asks whether THIS measurement is plausible: its own error, not the inflated one
    ratio = nu * nu / (st.P[0, 0] + R_single) / p.gate_chi2
    diag_kw = dict(measured=True, source_available=True, horizontal_field_gauss=H,
                   heading_meas_rad=z, innovation_rad=nu, innovation_var_rad2=S, test_ratio=ratio)
    if ratio > 1.0:
        since = st.rejected_since_s if st.rejected_since_s is not None else u.time_s
        if u.time_s - since >= p.reset_after_s:
            P = st.P.copy()
            P[0, :] = 0.0
            P[:, 0] = 0.0
            P[0, 0] = R_single
            x0 = st.x.copy()
            x0[0] = z
            fm, fm_t, r_uncal = _consider(st, u.time_s, H, r_uncal, mis, p, True)
            st = replace(st, x=x0, P=P, rejected_since_s=None,
                         source_available=True, n_resets=st.n_resets + 1, r_uncal_rad2=r_uncal,
                         field_mismatch_gauss2=fm, field_mismatch_time_s=fm_t)
            return st, HeadingDiag(**diag_kw, reset=True, reset_jump_rad=nu,
                                   reason="re-initialised from the source after continuous rejection")
        st = replace(st, rejected_since_s=since, source_available=True, n_rejected=st.n_rejected + 1)
        return st, HeadingDiag(**diag_kw, reason="innovation gated out")
    K = st.P[:, 0] / S
    x = st.x + K * nu
    x[0] = wrap_2pi(x[0])
    I_KH = np.eye(n)
    I_KH[:, 0] -= K
    P = I_KH @ st.P @ I_KH.T + np.outer(K, K) * R
    # consider floor: the correlated part of the source error (tilt, declination, residual
    # deviation) does not average out however long the source is fused, so the REPORTED heading
    # variance is kept >= its running mean over mag_error_tau_s (polar_heading_estimate); the
    # filter's own P, which sets the gain, is left alone (flooring it would make the filter
    # follow the correlated errors)
    dt_m = p.mag_update_period_s
    rc = p.consider_floor_fraction * r_corr
    avg = rc if st.r_corr_avg_rad2 is None else (
        st.r_corr_avg_rad2 + (rc - st.r_corr_avg_rad2) * min(1.0, dt_m / p.mag_error_tau_s))
    P = 0.5 * (P + P.T)
    fm, fm_t, r_uncal = _consider(st, u.time_s, H, r_uncal, mis, p, False)
    st = replace(st, x=x, P=P, rejected_since_s=None, source_available=True, n_fused=st.n_fused + 1,
                 r_corr_avg_rad2=avg, r_uncal_rad2=r_uncal, field_mismatch_gauss2=fm, field_mismatch_time_s=fm_t)
    return st, HeadingDiag(**diag_kw, fused=True)


def uncalibrated_heading_var(mag_body_gauss: np.ndarray, horizontal_field_gauss: float,
                             residual_sigma_gauss: float | None,
                             params: PolarHeadingParams = PolarHeadingParams()) -> float:
    """Heading variance (rad^2) of the magnetometer error the filter cannot see (module docstring):
    (s_h^2 + s_s^2 |m|^2) / H^2 uncompensated (``residual_sigma_gauss`` None), else
    max(0, s_r^2 - mag_noise^2) / H^2."""
    H2 = horizontal_field_gauss * horizontal_field_gauss
    if residual_sigma_gauss is None:
        m2 = float(np.dot(mag_body_gauss, mag_body_gauss))
        return (params.uncalibrated_hard_iron_gauss ** 2 + params.uncalibrated_soft_iron ** 2 * m2) / H2
    if not (math.isfinite(residual_sigma_gauss) and residual_sigma_gauss >= 0.0):
        raise ValueError(f"mag_residual_sigma_gauss must be finite and >= 0 or None, got {residual_sigma_gauss!r}")
    return max(0.0, residual_sigma_gauss ** 2 - params.mag_noise_gauss ** 2) / H2


def polar_heading_estimate(state: PolarHeadingState) -> HeadingEstimate:
    """Heading and its PUBLISHED variance: the filter's P_psi (or the consider floor, whichever is
    larger) + the uncalibrated-magnetometer consider term r_uncal (module docstring)."""
    if not state.initialised:
        return HeadingEstimate(math.nan, math.inf, state.source_available, False)
    var = float(state.P[0, 0])
    heading = float(state.x[0])
    if state.platform and state.q_P_from_body is not None:   # yaw of R_z(psi_P) C_PB
        heading = wrap_2pi(heading + euler_from_dcm(dcm_from_quat(state.q_P_from_body))[2])
    if state.r_corr_avg_rad2 is not None:
        var = max(var, state.r_corr_avg_rad2)      # consider floor (see _measure)
    var += state.r_uncal_rad2
    return HeadingEstimate(heading, var, state.source_available, True)


# ---- platform formulation (module docstring) ----------------------------------------------------
def _platform_step(state: PolarHeadingState, u: HeadingInputs, p: PolarHeadingParams):
    q_P = np.asarray(u.q_P_from_body, float)
    w = np.asarray(u.gyro_body_rad_s, float)
    if (q_P.shape != (4,) or not np.all(np.isfinite(q_P)) or not math.isfinite(u.time_s) or w.shape != (3,)
            or not np.all(np.isfinite(w))):
        return state, HeadingDiag(reason="non-finite input", source_available=state.source_available)
    q_P = q_P / np.linalg.norm(q_P)
    st = state if state.platform else _to_platform(state, q_P, p)
    q = q_P          # no own attitude yet, or after a gap: take the attitude filter's
    if st.time_s is not None:
        dt = u.time_s - st.time_s
        if dt <= 0.0:
            return st, HeadingDiag(reason=f"time not increasing (dt={dt:.6f} s)")
        if dt <= p.max_dt_s and st.q_P_from_body is not None:
            q = _own_attitude(st.q_P_from_body, (w - st.x[2:5]) * dt, q_P)
            if st.initialised:
                st = _predict_platform(st, dt, p)
        elif st.initialised:
            st = polar_heading_unseen(st, dt, p)
    st = replace(st, time_s=u.time_s, q_P_from_body=q)
    if u.mag_body_gauss is None:
        return st, HeadingDiag(source_available=st.source_available)
    if st.last_mag_time_s is not None and u.time_s - st.last_mag_time_s + 1e-9 < p.mag_update_period_s:
        return st, HeadingDiag(source_available=st.source_available)
    if st.rejected_since_s is not None and st.last_mag_time_s is not None \
            and u.time_s - st.last_mag_time_s > WITHHELD_AFTER_S:
        # the magnetometer was withheld meanwhile (a disturbance): its rejections start over
        st = replace(st, rejected_since_s=None)
    return _measure_platform(st, u, q, p)


def _own_attitude(q_prev: np.ndarray, angle_body_rad: np.ndarray, q_P: np.ndarray) -> np.ndarray:
    """The heading filter's own body attitude in its level frame H: propagated by the bias-corrected
    gyro increment, then given the attitude filter's tilt by the smallest body rotation (about an
    axis normal to the vertical: no turn about the vertical, so the azimuth of H is the gyros' alone
    and the attitude filter's corrections about its own, unobservable vertical never reach the
    heading). With R_b the body rotation and g the down direction in body axes:
        C_HB_new = C_HB_pred R_b,   R_b g_att = g_pred,   axis g_att x g_pred."""
    q_pred = quat_normalize(quat_mul(q_prev, quat_from_rotvec(angle_body_rad)))
    g_pred = dcm_from_quat(q_pred)[2, :]       # e_z^T C_HB: down in body axes
    g_att = dcm_from_quat(q_P)[2, :]
    axis = np.cross(g_att, g_pred)
    s, c = float(np.linalg.norm(axis)), float(g_att @ g_pred)
    if s < 1e-12:
        return q_pred if c > 0.0 else q_P
    return quat_normalize(quat_mul(q_pred, quat_from_rotvec(axis / s * math.atan2(s, c))))


def _to_platform(st: PolarHeadingState, q: np.ndarray, p: PolarHeadingParams) -> PolarHeadingState:
    """Switch an Euler-mode state to the platform states (a heading already known becomes psi_P =
    heading - yaw(C_PB); the gyro-bias errors start from their prior)."""
    x = np.zeros(5)
    P = _prior_P(0.0, p, 5)
    if st.initialised:
        x[0] = wrap_2pi(st.x[0] - euler_from_dcm(dcm_from_quat(q))[2])
        x[1] = st.x[1]
        P[:2, :2] = st.P[:2, :2]
    return replace(st, platform=True, x=x, P=P)


def _predict_platform(st, dt, p):
    C_PB = dcm_from_quat(st.q_P_from_body)
    row = C_PB[2, :]                    # e_z^T C_PB: a body vector's component along P's vertical
    x = st.x
    a_v, q_v = _gm(dt, p.vertical_rate_tau_s, p.vertical_rate_sigma_rad_s)
    a_b, q_b = _gm(dt, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s)
    F = np.diag([1.0, a_v, a_b, a_b, a_b])
    F[0, 1] = -dt
    F[0, 2:5] = -row * dt               # H turns with the bias error: psi' = e_z^T C_HB (b_hat - b)
    P = F @ st.P @ F.T
    P[0, 0] += (p.gyro_noise_rad_s_rt_hz ** 2 + p.heading_process_floor_rad_s_rt_hz ** 2) * dt
    P[1, 1] += q_v
    P[2:5, 2:5] += np.eye(3) * q_b
    xn = x.copy()
    xn[0] = wrap_2pi(x[0] - x[1] * dt)
    xn[1] = x[1] * a_v
    xn[2:5] = x[2:5] * a_b
    return replace(st, x=xn, P=P)


def _measure_platform(st, u, q, p):
    m, st, bad = _mag_sample(st, u)
    if bad is not None:
        return st, bad
    C_PB = dcm_from_quat(q)
    if u.level_with_roll_pitch:
        if not (math.isfinite(u.roll_rad) and math.isfinite(u.pitch_rad)):
            return st, HeadingDiag(reason="non-finite input", source_available=st.source_available)
        C_lev = dcm_from_euler(u.roll_rad, u.pitch_rad, euler_from_dcm(C_PB)[2])
        P_tilt = np.asarray(u.cov_roll_pitch_rad2, float)
    else:
        C_lev = C_PB
        Pe = np.zeros((3, 3)) if u.cov_att_body_rad2 is None else np.asarray(u.cov_att_body_rad2, float)
        P_tilt = (C_PB @ Pe @ C_PB.T)[:2, :2]
    mp = C_lev @ m
    H = math.hypot(mp[0], mp[1])
    if H < p.min_horizontal_field_gauss:
        st = replace(st, source_available=False)
        return st, HeadingDiag(measured=False, source_available=False, horizontal_field_gauss=H,
                               reason=f"horizontal field {H:.4f} G < {p.min_horizontal_field_gauss} G")
    G = -mp[2] / (H * H) * mp[:2]       # d psi_m / d(tilt in P), module docstring
    r_white = (p.mag_noise_gauss / H) ** 2
    r_nav = u.declination_sigma_rad ** 2                                 # fixed in N
    r_body = float(G @ P_tilt @ G) + p.mag_heading_floor_rad ** 2       # fixed in the body
    r_corr = r_nav + r_body
    # one independent sample per correlation time: tau for r_nav, min(tau, turn / |w|) for r_body
    rate = float(np.linalg.norm(np.asarray(u.gyro_body_rad_s, float) - st.x[2:5]))
    tau_body = p.mag_error_tau_s
    if p.mag_error_turn_rad > 0.0 and rate * tau_body > p.mag_error_turn_rad:
        tau_body = p.mag_error_turn_rad / rate
    R = (r_white + r_nav * max(1.0, p.mag_error_tau_s / p.mag_update_period_s)
         + r_body * max(1.0, tau_body / p.mag_update_period_s))
    R_single = r_white + r_corr
    z = wrap_2pi(-math.atan2(mp[1], mp[0]) + u.declination_rad)    # azimuth of P's x axis
    r_uncal = uncalibrated_heading_var(m, H, u.mag_residual_sigma_gauss, p)
    mis = field_mismatch_var(H, float(mp[2]), u.field_model_ned_gauss)
    return _fuse_heading(st, u, z, H, R, R_single, r_corr, r_uncal, p, mis)


def polar_heading_attitude(state: PolarHeadingState, heading_rad: float | None = None) -> np.ndarray | None:
    """q_nav_from_body of the platform formulation, R_z(heading - yaw(C_HB)) C_HB: the filter's own
    attitude turned about the vertical to ``heading_rad`` (default: its own estimate). Composing the
    quaternion avoids the Euler angles, whose roll and yaw are one degree of freedom at pitch +-90
    deg (recombining a roll and a yaw taken from two different attitudes is then arbitrary). None
    outside the platform formulation."""
    if not (state.platform and state.initialised and state.q_P_from_body is not None):
        return None
    if heading_rad is None:
        heading_rad = polar_heading_estimate(state).heading_rad
    yaw_H = euler_from_dcm(dcm_from_quat(state.q_P_from_body))[2]
    return quat_normalize(quat_mul(quat_from_euler(0.0, 0.0, heading_rad - yaw_H), state.q_P_from_body))
