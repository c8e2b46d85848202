"""Polar-capable attitude filter: roll and pitch from the IMU alone (METHODS.md C, first filter).

Seed: CN108627154B (Honeywell, "polar region operating attitude and heading reference system").
The attitude filter has NO latitude input and NO heading input; its output (roll, pitch and their
covariance) is therefore the same anywhere on Earth, including at the pole.

Frames
------
B  body (FRD; the caller rotates sensor data into B with the configured mounting).
P  the "floating platform" frame: locally level at start (its azimuth is the body's azimuth at
   start, i.e. arbitrary), then carried by the mechanisation below; it is never corrected for
   position, so nothing in the filter divides by cos(latitude).

Nominal mechanisation (per sample, a sample being the mean rate and specific force over its
interval: increment (w - b_g) dt with the two-interval coning term, exact quaternion update,
so no Euler angle and no small-angle step anywhere: any attitude, rates up to the gyro range):

    C_PB' = C_PB [w_hat x] - [W_hat x] C_PB,   w_hat = w_meas - b_g_hat,
    W_hat = w_ie_P_hat + w_eP_P_hat            (Earth rate + transport rate, both in P)

Error states (25: METHODS.md C's 19 and, beyond the seed, the gyro scale factors and the gyro
bias's rate of change), true = estimate + error, except the attitude error eps (body frame):
C_PB_true = C_PB_hat (I + [eps x]).

    x = [eps(3), db_g(3), da_v(3), dw_ie_P(3), dw_eP_P(3), db_a(3), dg(1), ds_g(3), dr_g(3)]

    eps'     = -[w_hat x] eps - db_g - diag(w_hat) ds_g - C_BP_hat (dw_ie_P + dw_eP_P) - n_g
    db_g'    = -db_g / tau_bg + dr_g + w   (first-order Gauss-Markov, GM, plus the bias rate)
    dr_g'    = -dr_g / tau_br + w          (bias rate of change, GM: see below)
    da_v'    = -da_v / tau_av + w          (vehicle acceleration, body frame, GM)
    dw_ie_P' = -dw_ie_P / tau_ie + w       (Earth rate in P, GM: P drifts w.r.t. N)
    dw_eP_P' = -dw_eP_P / tau_eP + w       (transport rate in P, GM)
    db_a'    = -db_a / tau_ba + w          (accelerometer bias, body, GM)
    dg'      = -dg / tau_g + w             (equator-to-pole gravity variation, GM)
    ds_g'    = -ds_g / tau_s + w           (gyro scale-factor errors, per axis, GM)

Gyro bias rate (beyond the seed): a MEMS gyro's bias follows its temperature, and after the rest
(where the zero-rate updates pin it, estimators/zero_rate) the motors and the airflow move the
temperature for minutes: a first-order thermal settling b(t) = b_inf - (b_inf - b_0) exp(-t/tau_th)
is exactly b' = r, r' = -r / tau_th, i.e. a ramp whose rate decays; ArduPlane SITL's gyro ramps
0.05 deg/s per minute for 5 minutes (SIM_DRIFT_SPEED, SIM_DRIFT_TIME). A random-walk bias can
follow a ramp only by a wide walk (0.2 deg/s over 600 s: 4070a47), which also chases every gust
and costs roll/pitch where the bias is steady; the rate state follows a steady ramp with no lag
while the bias walk stays narrow. Nominal: b <- b + r tau_br (1 - phi), r <- r phi per sample,
phi = exp(-dt / tau_br) (``_ramp_bias``); error propagation over an update interval T: the bias
row takes tau_br (1 - phi_T) dr, the attitude -int_0^T R(T, s) s ds dr ~ -T^2/2 dr (trapezoid,
as the bias's own -0.5 T (I + R^T)).

Gyro scale factors (beyond the seed): the gyro reads w_meas = (I + diag(s_g)) w + b_g, so the rate
is w_hat = (w_meas - b_g) / (1 + s_g) ~ (w_meas - b_g)(1 - s_g) per axis, and a scale error ds_g
turns the attitude by diag(w) ds_g dt: over one 360 deg loop a consumer gyro's 0.3 % is 1.1 deg
of tilt the bias states cannot hold (they learn a rate, not a fraction of the rotation). Without
these states that tilt went into the accelerometer bias, with a tilt sigma 4x below the error,
once the zero-rate updates (estimators/zero_rate) pinned the gyro bias.

Derivation of eps': with C = C_hat (I + E), E = [eps x], C' = C[w x] - [W x]C and the nominal
C_hat' = C_hat[w_hat x] - [W_hat x]C_hat, keeping first-order terms,
E' = [dw x] + E[w_hat x] - [w_hat x]E - [(C_hat^T dW) x] and E[w x] - [w x]E = [(eps x w) x],
so eps' = eps x w_hat + dw - C_BP dW with dw = w - w_hat = -(db_g + n_g).
(tests/test_polar_filters.py checks the attitude block against an exact rotation.)

Measurement (METHODS.md C): the specific force residual, averaged over ``update_period_s``:

    f_meas = b_a + a_v - C_BP g_P + n_a,      g_P = [0, 0, g0 + dg]
    C_BP = (I - [eps x]) C_BP_hat  =>  C_BP g_P = g_B_hat + [g_B_hat x] eps + C_BP_hat[:, 2] dg
    z = f_meas - f_hat = db_a + da_v - [g_B_hat x] eps - C_BP_hat[:, 2] dg + n_a

Gated-out runs (beyond the seed): a sustained vehicle acceleration the a_v prior does not
allow (the seconds after a rail launch: ~2 m/s^2 lateral) is rejected by the gate update after
update, and a rejected update changes nothing. When the acceleration falls, the first residual
under the gate used to be fused with a_v still at its prior, i.e. attributed to the attitude
(up to sqrt(gate_chi2) = 5 attitude sigmas in one update), and which residual that was
depended on the sample pattern (a link dropping 10 % of the IMU samples moved roll by 0.7 to
2.3 deg). Now (1) after a gated-out run an update is fused only when its residual has settled:
it differs from the previous update's by no more than two consecutive residuals of a steady
state do, d = z_k - z_(k-1) ~ N(0, (2 r + q_av) I) (the measurement noise of both and one
interval of a_v process noise; the attitude and bias terms change far less in 50 ms), tested
at chi-square 3 dof ``reentry_settle_chi2`` (a residual that straddles the transient, being
a mix of two regimes, fails it); (2) that re-entry update first raises the a_v variance along
its residual to the residual's size (``_match_gated_accel``), which bounds the attitude change
of the update by one attitude sigma. After ``reentry_max_wait_updates`` unsettled residuals
under the gate the next one is fused anyway (with (2)), so a vehicle whose residual never
settles is not left on the gyros.

Holes (beyond the seed): samples the link lost inside an interval (longer than 1.5 x the previous
one, up to ``max_dt_s``) are bridged on the rate taken linear between the samples around the hole,
with the variance of what that line may miss added to the attitude (``_bridge_variance_rad2``);
a longer gap is not integrated and widens the attitude covariance (``polar_attitude_unseen``).
A sample's rate is taken as the mean over at most ``sample_span_max_s`` of its interval: a slow
stream (RAW_IMU at 2.7 Hz over a telemetry radio, one instant of the FC's gyro every 0.37 s) is a
stream of holes, bridged the same way, so its sigma says what the samples cannot see.

Re-levelling at rest (beyond the seed): a tilt error beyond the gate (after a tumble) would be
rejected for ever; after ``relevel_rest_s`` of gated-out updates at rest roll/pitch are reset
from the accelerometer with a derived sigma, P's azimuth kept (``_relevel``; diag.relevelled).

The vehicle-acceleration GM state is what keeps manoeuvre accelerations out of the attitude
(they are absorbed as a_v for ~tau_av); beyond the seed its variance is raised while the gyros
show a turn (centripetal w x [V, 0, 0], see ``manoeuvre_speed_m_s``), so a sustained banked turn
is carried by the gyros rather than levelled by the accelerometer. The accelerometer bias and
the gravity variation are slow; the Earth and transport rates in P make the horizontal drift of
P observable through the tilt it causes, at any latitude. The unobservable azimuth of P is kept
bounded (``max_platform_yaw_sigma_rad``). A horizontal accelerometer bias is indistinguishable
from a tilt except through attitude changes: it is the accuracy floor (0.1 m/s^2 ~ 0.6 deg).

Output: roll and pitch of B relative to the local level (= P's level) and their 2x2
covariance, from the attitude-error covariance through d(roll, pitch)/d(eps).

Pure: ``polar_attitude_step(state, time_s, gyro_body_rad_s, accel_body_m_s2, params)
-> (state, diag)``; the covariance and measurement update run every ``update_period_s``,
the nominal attitude at every sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.rotations import (dcm_from_quat, euler_from_dcm, quat_from_euler,
                                  quat_from_rotvec, quat_mul, rotvec_from_quat, skew)

EARTH_RATE_RAD_S = 7.292115e-5
STANDARD_GRAVITY_M_S2 = 9.80665
N_STATES = 25
# slices of the error-state vector
N_NOMINAL = N_STATES - 3
"""Length of x_hat (every state but the attitude error)."""
I_ATT, I_BG, I_AV, I_WIE, I_WEP, I_BA, I_DG, I_SG, I_BR = (slice(0, 3), slice(3, 6), slice(6, 9),
                                                           slice(9, 12), slice(12, 15), slice(15, 18),
                                                           slice(18, 19), slice(19, 22), slice(22, 25))


@dataclass(frozen=True)
class PolarAttitudeParams:
    """Tuning of the attitude filter. Units in the names; defaults suit a consumer MEMS IMU."""

    update_period_s: float = 0.05
    """Interval of the covariance propagation and specific-force update (s)."""
    init_period_s: float = 0.5
    """Specific force averaged at start to level the filter (s); the vehicle should be still."""
    gyro_noise_rad_s_rt_hz: float = math.radians(0.01)
    """Gyro angle random walk (rad/s/sqrt(Hz))."""
    gyro_bias_init_sigma_rad_s: float = math.radians(0.5)
    """Prior sigma of the gyro bias at start (turn-on bias, rad/s) unless given at init."""
    gyro_bias_sigma_rad_s: float = math.radians(0.05)
    """Steady-state sigma of the gyro bias GM process (rad/s): how far the bias wanders in flight from
    what was measured at rest (the zero-rate updates pin it to ~0.005 deg/s before the launch), apart
    from the ramp the bias-rate state carries. 2 sigma^2 / tau = 2.8e-6 (deg/s)^2/s; the simulator's
    consumer gyro walks 1.3e-6 (2e-5 rad/s/sqrt(s)). 4070a47 widened it to 0.2 deg/s over 600 s
    (1.3e-4) to follow ArduPlane SITL's ramp, which also let the bias chase every gust: roll/pitch
    worse wherever the bias is steady; the ramp is now the rate state's (below)."""
    gyro_bias_tau_s: float = 1800.0
    gyro_bias_rate_sigma_rad_s2: float = math.radians(0.05) / 60.0
    """Steady-state sigma of the gyro bias's rate of change (rad/s^2; a GM state per axis): 0.05 deg/s
    per minute, ArduPlane SITL's SIM_DRIFT_SPEED default and the order of a consumer MEMS gyro's
    warm-up drift (a bias that follows the temperature at ~0.01 deg/s per K while the board warms
    by a few K per minute after the motors start). With it the filter follows SITL's ramp (roll
    after the GNSS cut: docs/SIGMAS.md) while the bias walk above stays narrow. The rest pins the
    rate too; the take-off reopens it to this (``_open_bias_rate``)."""
    gyro_bias_rate_tau_s: float = 300.0
    """Correlation time of the bias rate (s): a thermal settling of a few minutes (and SITL's ramp
    reverses every 5 minutes, SIM_DRIFT_TIME)."""
    takeoff_bias_step_sigma_rad_s: float = math.radians(0.05)
    """Sigma of the bias's change from the rest to the flight (rad/s), added to the bias variance at
    the take-off (``_open_bias_rate``): what the zero-rate updates measured at rest is the bias of a
    still, cooler sensor; the take-off's accelerations and vibration (a consumer MEMS gyro's linear
    acceleration sensitivity is ~0.1 deg/s/g, MPU-6000) and the motors' heat move it at once.
    ArduPlane SITL's bias is 0.05 deg/s 20 s after the launch (measured offline against its own
    simulated state in level legs, docs/SIGMAS.md).
    0 leaves the bias's variance as the rest left it."""
    accel_noise_m_s2: float = 0.05
    """Per-sample white noise of the specific force (m/s^2); divided by the samples averaged."""
    accel_meas_floor_m_s2: float = 0.02
    """Floor on the sigma of the averaged specific-force residual (model error, vibration)."""
    vehicle_accel_sigma_m_s2: float = 0.2
    """Steady-state sigma of the vehicle-acceleration GM process in straight flight (m/s^2)."""
    vehicle_accel_tau_s: float = 0.5
    manoeuvre_speed_m_s: float = 25.0
    """Speed V used to bound the centripetal acceleration [0, r V, -q V] of a vehicle turning at
    body rates (q, r): the vehicle-acceleration variance of body y/z is raised to at least
    sigma_av^2 + (r V)^2 / (q V)^2 (manoeuvre-adaptive; set V to the vehicle's cruise speed)."""
    earth_rate_sigma_rad_s: float = EARTH_RATE_RAD_S
    """Prior sigma per axis of the Earth rate in P (rad/s): no latitude is given."""
    earth_rate_tau_s: float = 3600.0
    transport_rate_sigma_rad_s: float = 1.5e-5
    """Sigma per axis of the transport rate in P (rad/s), ~ ground speed / Earth radius."""
    transport_rate_tau_s: float = 600.0
    accel_bias_sigma_m_s2: float = 0.05
    accel_bias_tau_s: float = 3600.0
    gyro_scale_sigma: float = 0.0033
    """Sigma of each gyro axis's scale-factor error (dimensionless): ICM-20602's initial sensitivity
    tolerance +-1 % (its datasheet; ICM-42688-P +-0.5 %) taken as 3 sigma; no FC calibrates it."""
    gyro_scale_tau_s: float = 3600.0
    gravity_variation_sigma_m_s2: float = 0.03
    """Sigma of g - g0 (equator to pole: 9.780 -> 9.832 m/s^2)."""
    gravity_variation_tau_s: float = 3600.0
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2
    """g0: the gravity the estimated variation is relative to."""
    init_tilt_sigma_rad: float = math.radians(1.0)
    init_yaw_sigma_rad: float = math.radians(0.1)
    """Yaw of B in P at start (P takes the start azimuth, so only round-off)."""
    max_platform_yaw_sigma_rad: float = math.radians(5.0)
    """Cap on the sigma of the attitude error about P's vertical. That component is the azimuth
    of P, which is arbitrary and unobservable; letting it grow without bound would break the
    small-angle error model, so beyond the cap it is absorbed into the definition of P (the row
    and column of the covariance along P's vertical are scaled down: a congruence, P stays
    positive semi-definite). Roll and pitch do not depend on it."""
    gate_chi2: float = 25.0
    """Innovation gate on the 3-dof specific-force residual (NIS); larger is rejected."""
    reentry_settle_chi2: float = 16.27
    """Re-entry test after a gated-out run (chi-square, 3 dof; 16.27 = 99.9 %): an update that
    passes the gate is fused only if its residual differs from the previous update's residual by
    no more than the model allows between two consecutive updates, d^T D^-1 d <= this, with
    d = z_k - z_(k-1) and D = (2 r + q_av) I (see ``_reentry``)."""
    reentry_max_wait_updates: int = 5
    """After this many consecutive updates that pass the gate but not the re-entry test, the next
    one that passes the gate is fused anyway (a vehicle whose residual never settles, e.g. strong
    vibration, is not left on the gyros alone). 0 switches the re-entry test off (with
    ``reentry_match_gain`` 0 too, the filter before 2026-11-22: the first update that passed the
    gate after a gated-out run was fused)."""
    reentry_match_gain: float = 1.0
    """Covariance matching of the vehicle acceleration at the re-entry update (dimensionless,
    >= 0): before the first update fused after a gated-out run, the variance of a_v along its
    residual z is raised by this gain times ``|z|^2 - u^T S u`` (u = z/|z|), so that residual goes
    to a_v rather than to the attitude (``_match_gated_accel``). 0 switches it off."""
    max_dt_s: float = 0.5
    """Largest sample interval that is integrated (bridged when it holds lost samples, see
    ``gap_rate_walk_rad_s2_rt_hz``); a longer gap is an interval not seen (``polar_attitude_unseen``).
    The daemon sets it to [mavlink] imu_gap_s (default 0.5 s, as the strapdown's), beyond which the
    link reports a time_gap."""
    unseen_rate_sigma_rad_s: float = math.radians(10.0)
    """Over an interval the filter did not see (a gap longer than ``max_dt_s``, or an interval
    the caller reports with ``polar_attitude_unseen``) the vehicle kept manoeuvring: the attitude
    error variance grows by (this rate x the interval)^2 per axis (rad/s) ..."""
    relevel_rest_s: float = 1.0
    """Re-levelling at rest (see ``_relevel``): the specific-force update must have been gated
    out at rest for this long (s) before roll/pitch are re-initialised from the accelerometer."""
    relevel_max_rate_rad_s: float = math.radians(5.0)
    """Rest test: the bias-corrected mean body rate of an update interval is below this (rad/s)."""
    relevel_allowed: bool = True
    """The caller's word that the vehicle may be at rest. The rest test (|f| ~ g, low rate, steady
    residual) is met as well by steady flight with a lateral or along-track acceleration that
    |f| hides: in flight the daemon sets this False (service/pipeline.py; measured: a rail flight
    with 10 % packet loss re-levelled 2 s after the boost and put a 12.7 deg roll error in)."""
    relevel_norm_tol_m_s2: float = 0.1
    """Rest test: | |f - b_a| - g | of an update interval is below this (m/s^2). It also bounds
    the horizontal acceleration such a rest can hide, a_max = sqrt(2 g tol), and so the
    re-levelled tilt sigma (``_relevel``)."""
    sample_span_max_s: float = 0.05
    """Longest part of its interval one sample's rate is taken to be the mean over (s); the rest of a
    longer interval is a hole, bridged (``gap_rate_walk_rad_s2_rt_hz``). A streamed IMU sample is the
    FC's low-passed gyro at one instant (ArduPilot INS_GYRO_FILTER 20 Hz, PX4 IMU_GYRO_CUTOFF 40 Hz
    by default: a memory of ~10 ms), the daemon's filter-rate samples are means over their own
    1/filter_rate_hz (20 ms; the Pipeline raises this to its filter period if longer). At 2.7 Hz
    (0.37 s intervals) a sample taken as the mean of its whole interval integrated the rate of one
    instant over 0.37 s with no variance for the rest: the tilt sigma stayed ~1 deg while the error
    grew, the specific force was gated out and roll drifted to 57 deg RMS on a real telemetry log."""
    gap_rate_walk_rad_s2_rt_hz: float = math.radians(10.0)
    """A hole in the samples (an interval longer than 1.5 x the previous one, up to ``max_dt_s``: IMU
    samples the link lost) is bridged with the rate taken linear between the samples around it;
    the rate's deviation from that line is modelled as a random walk of this intensity (rad/s^2
    per sqrt(Hz)): see ``_bridge_variance_rad2``."""
    unseen_max_sigma_rad: float = math.radians(30.0)
    """... up to this sigma (rad): a wide prior on the attitude after an unseen interval of a few
    seconds or more, so the specific force pulls roll/pitch back at the next updates and the
    published sigma says how stale the state is."""

    def __post_init__(self) -> None:
        for name in ("update_period_s", "init_period_s", "gyro_noise_rad_s_rt_hz",
                     "gyro_bias_init_sigma_rad_s", "gyro_bias_sigma_rad_s", "gyro_bias_tau_s", "gyro_bias_rate_tau_s",
                     "accel_noise_m_s2",
                     "accel_meas_floor_m_s2", "vehicle_accel_sigma_m_s2", "vehicle_accel_tau_s",
                     "earth_rate_sigma_rad_s", "earth_rate_tau_s", "transport_rate_sigma_rad_s",
                     "transport_rate_tau_s", "accel_bias_sigma_m_s2", "accel_bias_tau_s",
                     "gyro_scale_sigma", "gyro_scale_tau_s",
                     "gravity_variation_sigma_m_s2", "gravity_variation_tau_s", "gravity_m_s2",
                     "init_tilt_sigma_rad", "init_yaw_sigma_rad", "max_platform_yaw_sigma_rad",
                     "gate_chi2", "reentry_settle_chi2", "max_dt_s", "unseen_rate_sigma_rad_s", "unseen_max_sigma_rad",
                     "relevel_rest_s", "relevel_max_rate_rad_s", "relevel_norm_tol_m_s2",
                     "gap_rate_walk_rad_s2_rt_hz", "sample_span_max_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("gyro_bias_rate_sigma_rad_s2", "takeoff_bias_step_sigma_rad_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if not (math.isfinite(self.manoeuvre_speed_m_s) and self.manoeuvre_speed_m_s >= 0.0):
            raise ValueError(f"manoeuvre_speed_m_s must be finite and >= 0, got {self.manoeuvre_speed_m_s!r}")
        g = self.reentry_match_gain
        if not (isinstance(g, (int, float)) and math.isfinite(g) and g >= 0.0):
            raise ValueError(f"reentry_match_gain must be finite and >= 0, got {g!r}")
        n = self.reentry_max_wait_updates
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"reentry_max_wait_updates must be an int >= 0, got {n!r}")


@dataclass(frozen=True)
class PolarAttitudeState:
    """Filter state; serialisable with ``to_dict``/``from_dict``."""

    initialised: bool = False
    time_s: float | None = None
    q_P_from_body: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    x_hat: np.ndarray = field(default_factory=lambda: np.zeros(N_NOMINAL))
    """Nominal non-attitude states [b_g(3) rad/s, a_v(3) m/s^2, w_ie_P(3), w_eP_P(3) rad/s,
    b_a(3) m/s^2, dg(1) m/s^2, s_g(3)]."""
    P: np.ndarray = field(default_factory=lambda: np.zeros((N_STATES, N_STATES)))
    gyro_prev_rad_s: np.ndarray | None = None
    # accumulators of the current update interval
    acc_n: int = 0
    acc_dt_s: float = 0.0
    acc_f_sum_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_f_sq_sum_m2_s4: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Sum of the squared specific force per axis over the levelling window (``_init_step``)."""
    acc_down_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Sum of the predicted down direction in B, C_BP_hat[:, 2], over the interval."""
    acc_q_b0_from_b: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    acc_C_BP_start: np.ndarray = field(default_factory=lambda: np.eye(3))
    n_updates: int = 0
    n_rejected: int = 0
    bias_prior_sigma_rad_s: float | None = None
    gated_run: int = 0
    """Consecutive updates not fused since the last fused one (gated out or not yet re-entered)."""
    reentry_wait: int = 0
    """Of those, the consecutive ones that passed the gate but not the re-entry test."""
    z_prev_m_s2: np.ndarray | None = None
    """Specific-force residual of the previous update (body, m/s^2); None before the first."""
    rest_gated_run: int = 0
    """Consecutive updates gated out at rest (``_rest_test``): the re-levelling count."""
    rest_f_sum_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Sum of the bias-corrected mean specific force (body) over those updates."""
    rest_s: float = 0.0
    """Time those updates span (s)."""
    n_relevels: int = 0
    """Re-levellings done (``_rest_test``)."""
    sample_dt_s: float | None = None
    """Span of the last sample that was not a hole (s), at most ``sample_span_max_s``: the part of an
    interval a sample's rate is the mean over."""
    bias_rate_opened: bool = False
    """The bias rate's variance was reopened for flight (``_open_bias_rate``: params.relevel_allowed
    went False, the vehicle left the rest); False again once it is allowed."""

    def to_dict(self) -> dict:
        out = {}
        for k, v in self.__dict__.items():
            out[k] = v.tolist() if isinstance(v, np.ndarray) else v
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "PolarAttitudeState":
        arrays = {"q_P_from_body", "x_hat", "P", "gyro_prev_rad_s", "acc_f_sum_m_s2", "acc_f_sq_sum_m2_s4",
                  "acc_down_sum", "acc_q_b0_from_b", "acc_C_BP_start", "z_prev_m_s2",
                  "rest_f_sum_m_s2"}
        kw = {k: (np.array(v, dtype=float) if (k in arrays and v is not None) else v)
              for k, v in d.items()}
        return cls(**kw)


@dataclass(frozen=True)
class PolarAttitudeDiag:
    updated: bool = False
    """A specific-force update was attempted at this sample."""
    fused: bool = False
    innovation_m_s2: np.ndarray | None = None
    test_ratio: float = math.nan
    """NIS / gate_chi2; > 1 means rejected."""
    reason: str = ""
    settle_ratio: float = math.nan
    """Re-entry test after a gated-out run: d^T D^-1 d / reentry_settle_chi2 (> 1: not settled);
    NaN when the previous update was fused."""
    accel_var_raised_m2_s4: float = 0.0
    """Variance added to the vehicle acceleration along the rejected residual (m^2/s^4; 0 when
    fused or when nothing was added): the flag "sustained acceleration the model did not expect"."""
    relevelled: bool = False
    """Roll/pitch were re-initialised from the accelerometer at rest at this update (``_relevel``);
    ``reason`` says by how much."""
    relevel_rad: float = 0.0
    """Tilt correction of that re-levelling (rad)."""


@dataclass(frozen=True)
class AttitudeEstimate:
    roll_rad: float
    pitch_rad: float
    cov_roll_pitch_rad2: np.ndarray
    """2x2 covariance of (roll, pitch)."""
    gyro_bias_rad_s: np.ndarray
    q_P_from_body: np.ndarray


def _down_in_body(q: np.ndarray) -> np.ndarray:
    """C_BP[:, 2] = third row of C_PB for q = q_P_from_body."""
    w, x, y, z = q
    return np.array([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)])


def _initial_covariance(C_BP: np.ndarray, p: PolarAttitudeParams,
                        bias_sigma_rad_s: float | None = None) -> np.ndarray:
    P = np.zeros((N_STATES, N_STATES))
    # tilt/yaw prior given in P, mapped into the body-frame error: eps = C_BP psi_P
    Pp = np.diag([p.init_tilt_sigma_rad ** 2, p.init_tilt_sigma_rad ** 2, p.init_yaw_sigma_rad ** 2])
    P[I_ATT, I_ATT] = C_BP @ Pp @ C_BP.T
    sb = p.gyro_bias_init_sigma_rad_s if bias_sigma_rad_s is None else bias_sigma_rad_s
    P[I_BG, I_BG] = np.eye(3) * sb ** 2
    P[I_AV, I_AV] = np.eye(3) * p.vehicle_accel_sigma_m_s2 ** 2
    P[I_WIE, I_WIE] = np.eye(3) * p.earth_rate_sigma_rad_s ** 2
    P[I_WEP, I_WEP] = np.eye(3) * p.transport_rate_sigma_rad_s ** 2
    P[I_BA, I_BA] = np.eye(3) * p.accel_bias_sigma_m_s2 ** 2
    P[I_DG, I_DG] = p.gravity_variation_sigma_m_s2 ** 2
    P[I_SG, I_SG] = np.eye(3) * p.gyro_scale_sigma ** 2
    P[I_BR, I_BR] = np.eye(3) * p.gyro_bias_rate_sigma_rad_s2 ** 2
    return P


def polar_attitude_init(params: PolarAttitudeParams = PolarAttitudeParams(),
                        gyro_bias_rad_s: np.ndarray | None = None,
                        gyro_bias_sigma_rad_s: float | None = None) -> PolarAttitudeState:
    """An uninitialised filter: it levels itself over ``init_period_s`` of data.

    ``gyro_bias_rad_s``/``gyro_bias_sigma_rad_s``: optional prior of the gyro bias (body axes),
    e.g. the pre-launch mean rate at rest (estimators/levelling.py) and its uncertainty. The
    vertical-axis bias is otherwise only observed through tilt while the vehicle is banked.
    """
    x = np.zeros(N_NOMINAL)
    if gyro_bias_rad_s is not None:
        b = np.asarray(gyro_bias_rad_s, float)
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise ValueError(f"gyro_bias_rad_s must be 3 finite numbers, got {gyro_bias_rad_s!r}")
        x[0:3] = b
    if gyro_bias_sigma_rad_s is not None and not (math.isfinite(gyro_bias_sigma_rad_s)
                                                  and gyro_bias_sigma_rad_s > 0.0):
        raise ValueError(f"gyro_bias_sigma_rad_s must be finite and > 0, got {gyro_bias_sigma_rad_s!r}")
    return PolarAttitudeState(x_hat=x, bias_prior_sigma_rad_s=gyro_bias_sigma_rad_s)


def polar_attitude_init_at(time_s: float, roll_rad: float, pitch_rad: float, tilt_sigma_rad: float,
                           params: PolarAttitudeParams = PolarAttitudeParams(),
                           gyro_bias_rad_s: np.ndarray | None = None,
                           gyro_bias_sigma_rad_s: float | None = None) -> PolarAttitudeState:
    """A filter initialised at ``time_s`` with a given roll/pitch (rad) and 1-sigma tilt
    ``tilt_sigma_rad`` instead of levelling itself: for a start in flight, where the mean specific
    force is not gravity (e.g. from a trusted FC attitude, or the accelerometer with a wide sigma).
    P's azimuth is the body's azimuth at ``time_s`` (yaw 0), as after ``_init_step``. The next
    sample starts the increments."""
    for name, v in (("time_s", time_s), ("roll_rad", roll_rad), ("pitch_rad", pitch_rad)):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    if not (math.isfinite(tilt_sigma_rad) and tilt_sigma_rad > 0.0):
        raise ValueError(f"tilt_sigma_rad must be finite and > 0, got {tilt_sigma_rad!r}")
    st = polar_attitude_init(params, gyro_bias_rad_s, gyro_bias_sigma_rad_s)
    q = quat_from_euler(roll_rad, pitch_rad, 0.0)
    C_BP = dcm_from_quat(q).T
    P = _initial_covariance(C_BP, replace(params, init_tilt_sigma_rad=tilt_sigma_rad), gyro_bias_sigma_rad_s)
    return replace(st, initialised=True, time_s=time_s, q_P_from_body=q, P=P, gyro_prev_rad_s=None,
                   acc_C_BP_start=C_BP)


def polar_attitude_unseen(state: PolarAttitudeState, unseen_s: float,
                          params: PolarAttitudeParams = PolarAttitudeParams()) -> PolarAttitudeState:
    """Account for ``unseen_s`` seconds the filter did not see (no samples: a gap, a restarted
    clock). The nominal attitude is kept (nothing better is known), but the vehicle kept turning:

        P_att <- P_att + s^2 I,   s = min(unseen_rate_sigma_rad_s * unseen_s, unseen_max_sigma_rad)

    (body-frame attitude error, all three axes; the part about P's vertical is capped at the next
    update as always). The Gauss-Markov states are propagated over the interval (their means
    decay, their variances relax toward the steady state), the partial update interval is dropped
    and the increments restart at the next sample (whatever its time: a restarted clock may
    start lower). The specific-force update then pulls roll and
    pitch back within a few updates, with a sigma that is honest meanwhile."""
    if not (math.isfinite(unseen_s) and unseen_s >= 0.0):
        raise ValueError(f"unseen_s must be finite and >= 0, got {unseen_s!r}")
    if not state.initialised:
        return state
    p = params
    F, Q = _gm_diagonals(unseen_s, p)
    P = F[:, None] * state.P * F[None, :]
    P[np.diag_indices(N_STATES)] += Q
    s = min(p.unseen_rate_sigma_rad_s * unseen_s, p.unseen_max_sigma_rad)
    P[I_ATT, I_ATT] += np.eye(3) * s * s
    x = state.x_hat.copy()
    x[3:6] *= math.exp(-unseen_s / p.vehicle_accel_tau_s)
    _ramp_bias(x, unseen_s, p)
    C_BP = dcm_from_quat(state.q_P_from_body).T
    return replace(state, P=0.5 * (P + P.T), x_hat=x, time_s=None, gyro_prev_rad_s=None, sample_dt_s=None,
                   acc_n=0, acc_dt_s=0.0,
                   acc_f_sum_m_s2=np.zeros(3), acc_down_sum=np.zeros(3),
                   acc_q_b0_from_b=np.array([1.0, 0.0, 0.0, 0.0]), acc_C_BP_start=C_BP)


def _validate(time_s: float, gyro: np.ndarray, accel: np.ndarray) -> str:
    if gyro.shape != (3,) or accel.shape != (3,):
        return "gyro and accel must have shape (3,)"
    if not (math.isfinite(time_s) and np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
        return "non-finite sample"
    return ""


def polar_attitude_step(state: PolarAttitudeState, time_s: float, gyro_body_rad_s: np.ndarray,
                        accel_body_m_s2: np.ndarray,
                        params: PolarAttitudeParams = PolarAttitudeParams()
                        ) -> tuple[PolarAttitudeState, PolarAttitudeDiag]:
    """Process one IMU sample (body frame, FC time ``time_s``)."""
    w = np.asarray(gyro_body_rad_s, dtype=float)
    f = np.asarray(accel_body_m_s2, dtype=float)
    bad = _validate(time_s, w, f)
    if bad:
        return state, PolarAttitudeDiag(reason=bad)

    if not state.initialised:
        return _init_step(state, time_s, w, f, params)

    if state.time_s is None:  # restart after polar_attitude_unseen (already accounted)
        return replace(state, time_s=time_s, gyro_prev_rad_s=w), PolarAttitudeDiag(
            reason="increments restarted")
    dt = time_s - state.time_s
    if dt <= 0.0:
        return state, PolarAttitudeDiag(reason=f"time not increasing (dt={dt:.6f} s)")
    if state.gyro_prev_rad_s is None:  # restart after polar_attitude_unseen (already accounted)
        return replace(state, time_s=time_s, gyro_prev_rad_s=w), PolarAttitudeDiag(
            reason="increments restarted")
    if dt > params.max_dt_s:
        # keep the attitude, restart the increments (strapdown.py's rule), and let the covariance
        # say what the unseen interval may have done to the attitude
        st = polar_attitude_unseen(state, dt, params)
        return replace(st, time_s=time_s, gyro_prev_rad_s=w, sample_dt_s=None), PolarAttitudeDiag(
            reason=f"gap of {dt:.3f} s not integrated; attitude sigma widened")
    # the span the sample's rate is the mean over: the stream's regular interval, at most
    # sample_span_max_s (a slow stream's sample is one instant of the FC's gyro, not a mean)
    span_s = min(dt if state.sample_dt_s is None else state.sample_dt_s, params.sample_span_max_s)
    hole = dt > 1.5 * span_s

    xh = state.x_hat
    b_g = xh[0:3]
    k_g = 1.0 - xh[16:19]                       # 1 / (1 + s_g) to first order
    W_hat = xh[6:9] + xh[9:12]
    # body increment: the sample is the mean rate over its interval (the daemon's filter-rate
    # mean of the IMU samples), so the increment is (w - b_g) dt, plus the two-interval coning
    # term (1/12) a_prev x a: a rotation whose axis turns within the interval (a tumble) is not
    # the rotation about the mean rate; at 500 deg/s with a wobbling axis and 50 Hz samples the
    # trapezoid of the mean rates lagged half a sample and drifted 4 deg in 3 s
    a_prev = (state.gyro_prev_rad_s - b_g) * k_g * dt
    a_now = (w - b_g) * k_g * dt
    if hole:
        # samples lost inside the interval (or never sent: a slow stream): this sample's mean rate
        # covers only its own last span_s; over the hole before it, h = dt - span_s, the rate is taken
        # linear between the two samples' means (centred span_s / 2 before their stamps, so the mean
        # of that line over the hole is (w_prev + w) / 2: exact for a rate ramp), and the
        # covariance says what that line may miss (``_bridge_variance_rad2``)
        h_s = dt - span_s
        dtheta = (0.5 * ((state.gyro_prev_rad_s - b_g) + (w - b_g)) * k_g * h_s + (w - b_g) * k_g * span_s
                  + np.cross(a_prev, a_now) / 12.0)
    else:
        dtheta = a_now + np.cross(a_prev, a_now) / 12.0
    qb = quat_from_rotvec(dtheta)
    q = quat_mul(quat_from_rotvec(-W_hat * dt), quat_mul(state.q_P_from_body, qb))
    q = q / math.sqrt(float(q @ q))
    # vehicle-acceleration estimate is a zero-mean GM: its mean decays
    x_new = xh.copy()
    x_new[3:6] *= math.exp(-dt / params.vehicle_accel_tau_s)
    _ramp_bias(x_new, dt, params)
    q_int = quat_mul(state.acc_q_b0_from_b, qb)
    P_att = state.P
    if hole:
        P_att = state.P.copy()
        P_att[I_ATT, I_ATT] += np.eye(3) * _bridge_variance_rad2(state.gyro_prev_rad_s, w, h_s, params)
    if hole:
        # the sample's specific force, like its rate, is the mean over its last span_s only: gravity
        # is predicted over that span (at 50 deg/s the body turns 18 deg in a 0.37 s interval: the
        # mean over the whole interval put ~9 deg of it into the residual)
        dth_span = (w - b_g) * k_g * span_s
        q_s = quat_mul(quat_from_rotvec(W_hat * span_s), quat_mul(q, quat_from_rotvec(-dth_span)))
        down_mean = _down_mean_over_sample(q_s, q, W_hat, span_s, dth_span)
    else:
        down_mean = _down_mean_over_sample(state.q_P_from_body, q, W_hat, dt, dtheta)
    st = replace(state, time_s=time_s, q_P_from_body=q, x_hat=x_new, gyro_prev_rad_s=w, P=P_att,
                 sample_dt_s=span_s if hole else min(dt, params.sample_span_max_s),
                 acc_n=state.acc_n + 1, acc_dt_s=state.acc_dt_s + dt,
                 acc_f_sum_m_s2=state.acc_f_sum_m_s2 + f,
                 acc_down_sum=state.acc_down_sum + down_mean,
                 acc_q_b0_from_b=q_int)
    if st.acc_dt_s + 1e-9 < params.update_period_s:
        return st, PolarAttitudeDiag()
    return _update(st, params)


def _bridge_variance_rad2(w_prev: np.ndarray, w: np.ndarray, dt: float, p: PolarAttitudeParams) -> float:
    """Per-axis variance (rad^2) of the angle a hole of ``dt`` adds when bridged by the line.

    Two terms, both about the rate's departure from the line between the samples around the hole:
    a rate that is a random walk of intensity q = gap_rate_walk^2 pinned at both ends is a Brownian
    bridge, and the variance of its integral over [0, T] is q T^3 / 12 (the double integral of the
    bridge covariance min(s, t) - s t / T); a step of the rate from w_prev to w at a uniformly
    unknown instant inside the hole misses ((w - w_prev) T)^2 / 12 of the angle (the variance of
    (tau - T/2) for tau uniform on [0, T]), taken per axis on the largest component."""
    step = float(np.max(np.abs(w - w_prev))) * dt
    return p.gap_rate_walk_rad_s2_rt_hz ** 2 * dt ** 3 / 12.0 + step * step / 12.0


def _down_mean_over_sample(q0: np.ndarray, q1: np.ndarray, W_hat: np.ndarray, dt: float,
                           dtheta: np.ndarray) -> np.ndarray:
    """Mean over the sample's interval of the predicted down direction in B (Simpson's rule on
    start, middle and end attitude): the specific force of a sample is the mean over its interval,
    and at 500 deg/s the body turns 10 deg in a 20 ms sample, so the end attitude alone would
    predict gravity ~5 deg off its mean direction (what a spin then fused into the tilt)."""
    qm = quat_mul(quat_from_rotvec(-0.5 * W_hat * dt), quat_mul(q0, quat_from_rotvec(0.5 * dtheta)))
    return (_down_in_body(q0) + 4.0 * _down_in_body(qm) + _down_in_body(q1)) / 6.0


def _init_step(state, time_s, w, f, params):
    st = replace(state, time_s=time_s if state.time_s is None else state.time_s,
                 acc_n=state.acc_n + 1, acc_f_sum_m_s2=state.acc_f_sum_m_s2 + f,
                 acc_f_sq_sum_m2_s4=state.acc_f_sq_sum_m2_s4 + f * f)
    if time_s - st.time_s + 1e-9 < params.init_period_s:
        return st, PolarAttitudeDiag(reason="levelling")
    fm = st.acc_f_sum_m_s2 / st.acc_n
    roll = math.atan2(-fm[1], -fm[2])
    pitch = math.atan2(fm[0], math.hypot(fm[1], fm[2]))
    q = quat_from_euler(roll, pitch, 0.0)
    C_BP = dcm_from_quat(q).T
    sigma = _levelled_tilt_sigma_rad(st, fm, params)
    return PolarAttitudeState(initialised=True, time_s=time_s, q_P_from_body=q,
                              x_hat=state.x_hat.copy(),
                              P=_initial_covariance(C_BP, replace(params, init_tilt_sigma_rad=sigma)
                                                    if sigma != params.init_tilt_sigma_rad else params,
                                                    state.bias_prior_sigma_rad_s),
                              gyro_prev_rad_s=w, acc_C_BP_start=C_BP,
                              bias_prior_sigma_rad_s=state.bias_prior_sigma_rad_s), PolarAttitudeDiag(
        reason="levelled")


def _levelled_tilt_sigma_rad(st: PolarAttitudeState, fm: np.ndarray, p: PolarAttitudeParams) -> float:
    """1-sigma of the tilt levelled on the mean specific force ``fm`` of the levelling window:
    ``init_tilt_sigma_rad``, or the window's scatter when larger, sqrt(tr Cov(f)) / |fm| (at most
    ``unseen_max_sigma_rad``). The mean is gravity only if the vehicle was still; a motion in
    the window (ArduPlane SITL's first 0.1 s after boot reads -9.5 m/s^2 along x: the mean
    levels the pitch 5.6 deg off) shows as scatter, and a prior that says so lets the first
    updates move the tilt instead of splitting that error into the accelerometer bias, which a
    still vehicle cannot tell from tilt (the pitch then stayed 1.2 deg off for the flight)."""
    n = st.acc_n
    var = float(np.sum(np.maximum(st.acc_f_sq_sum_m2_s4 / n - fm * fm, 0.0)))
    g2 = float(fm @ fm)
    if var <= p.init_tilt_sigma_rad ** 2 * g2:
        return p.init_tilt_sigma_rad
    return min(math.sqrt(var / g2), p.unseen_max_sigma_rad)


def _ramp_bias(x: np.ndarray, dt: float, p: PolarAttitudeParams) -> None:
    """The nominal gyro bias and its rate over ``dt`` (in place on x_hat): b' = r, r' = -r / tau_r,
    so r(dt) = r phi and b(dt) = b + r tau_r (1 - phi), phi = exp(-dt / tau_r)."""
    phi = math.exp(-dt / p.gyro_bias_rate_tau_s)
    x[0:3] += x[19:22] * (p.gyro_bias_rate_tau_s * (1.0 - phi))
    x[19:22] *= phi


def _gm(dt: float, tau: float, sigma: float) -> tuple[float, float]:
    """Discrete GM transition and process-noise variance."""
    phi = math.exp(-dt / tau)
    return phi, sigma * sigma * (1.0 - phi * phi)


def _gm_diagonals(dt: float, p: PolarAttitudeParams) -> tuple[np.ndarray, np.ndarray]:
    """Transition and process-noise diagonals of the Gauss-Markov states over ``dt`` (the
    attitude entries 0:3 are left 1 and 0 for the caller)."""
    F = np.ones(N_STATES)
    Q = np.zeros(N_STATES)
    for sl, tau, sig in ((I_BG, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s),
                         (I_AV, p.vehicle_accel_tau_s, p.vehicle_accel_sigma_m_s2),
                         (I_WIE, p.earth_rate_tau_s, p.earth_rate_sigma_rad_s),
                         (I_WEP, p.transport_rate_tau_s, p.transport_rate_sigma_rad_s),
                         (I_BA, p.accel_bias_tau_s, p.accel_bias_sigma_m_s2),
                         (I_DG, p.gravity_variation_tau_s, p.gravity_variation_sigma_m_s2),
                         (I_SG, p.gyro_scale_tau_s, p.gyro_scale_sigma),
                         (I_BR, p.gyro_bias_rate_tau_s, p.gyro_bias_rate_sigma_rad_s2)):
        F[sl], Q[sl] = _gm(dt, tau, sig)
    return F, Q


def _open_bias_rate(st: PolarAttitudeState, p: PolarAttitudeParams) -> PolarAttitudeState:
    """The bias rate's and the bias's priors for flight, once per take-off (the caller's relevel_allowed
    going False).

    At rest the zero-rate updates measure the bias chunk after chunk, which also pins its rate (the
    bias did not move on the ground); the motors and the airflow then start another thermal regime
    whose rate the rest did not see (ArduPlane SITL: 0 at rest, 0.05 deg/s per minute in flight).
    Left pinned, the rate's variance regrows only by its process noise (2 sigma^2 / tau per s) and
    the ramp is followed late. So at the take-off the rate's variance is set to its steady state
    sigma_br^2 and its correlations with the other states are dropped (a principal block replaced by
    a positive one: P stays positive semi-definite); its estimate is kept. The bias itself may step at
    the take-off (``takeoff_bias_step_sigma_rad_s``): that variance is added to the bias's."""
    if p.relevel_allowed:
        return replace(st, bias_rate_opened=False) if st.bias_rate_opened else st
    if st.bias_rate_opened:
        return st
    P = st.P.copy()
    P[I_BR, :] = 0.0
    P[:, I_BR] = 0.0
    P[I_BR, I_BR] = np.eye(3) * p.gyro_bias_rate_sigma_rad_s2 ** 2
    P[I_BG, I_BG] += np.eye(3) * p.takeoff_bias_step_sigma_rad_s ** 2
    return replace(st, P=P, bias_rate_opened=True)


def _update(st: PolarAttitudeState, p: PolarAttitudeParams):
    st = _open_bias_rate(st, p)
    T = st.acc_dt_s
    R_b0_b = dcm_from_quat(st.acc_q_b0_from_b)      # body rotation over the interval
    C_BP_end = dcm_from_quat(st.q_P_from_body).T
    C_BP_0 = st.acc_C_BP_start

    # --- covariance propagation over T (exact attitude block, trapezoid couplings) -------------
    F = np.eye(N_STATES)
    Rt = R_b0_b.T
    F[I_ATT, I_ATT] = Rt
    F[I_ATT, I_BG] = -0.5 * T * (np.eye(3) + Rt)
    # scale factors: the increment's error is diag(theta) ds_g, theta the body rotation over T
    # (trapezoid as for the bias: -0.5 (I + Rt) diag(w_mean) T)
    F[I_ATT, I_SG] = -0.5 * (np.eye(3) + Rt) * rotvec_from_quat(st.acc_q_b0_from_b)[None, :]
    # bias rate: db_g(s) = db_g(0) + dr s over the interval, so the angle takes -int_0^T R(T, s) s ds dr,
    # trapezoid (as for the bias): -0.5 T (0 + T I); the bias takes tau_r (1 - phi_r) dr (~T)
    F[I_ATT, I_BR] = -0.5 * T * T * np.eye(3)
    F[I_BG, I_BR] = np.eye(3) * (p.gyro_bias_rate_tau_s * (1.0 - math.exp(-T / p.gyro_bias_rate_tau_s)))
    coupling = -0.5 * T * (C_BP_end + Rt @ C_BP_0)
    F[I_ATT, I_WIE] = coupling
    F[I_ATT, I_WEP] = coupling
    phi_diag, Q = _gm_diagonals(T, p)
    gm = np.arange(3, N_STATES)
    F[gm, gm] = phi_diag[3:]
    Q[0:3] = p.gyro_noise_rad_s_rt_hz ** 2 * T
    P = F @ st.P @ F.T
    P[np.diag_indices(N_STATES)] += Q
    # manoeuvre-adaptive vehicle acceleration: flying along body x at speed V while turning at
    # w, the centripetal acceleration is w x [V, 0, 0] = [0, r V, -q V] (roll rate adds none);
    # the accelerometer cannot tell it from a tilt, so its variance is raised to cover it
    w_mean = rotvec_from_quat(st.acc_q_b0_from_b) / T
    s0 = p.vehicle_accel_sigma_m_s2 ** 2
    V = p.manoeuvre_speed_m_s
    for i, var_man in ((6, s0), (7, s0 + (w_mean[2] * V) ** 2), (8, s0 + (w_mean[1] * V) ** 2)):
        if P[i, i] < var_man:
            P[i, i] = var_man

    # --- specific-force measurement -------------------------------------------------------------
    xh = st.x_hat
    g = p.gravity_m_s2 + xh[15]
    down_mean = st.acc_down_sum / st.acc_n
    f_mean = st.acc_f_sum_m_s2 / st.acc_n
    f_hat = xh[12:15] + xh[3:6] - g * down_mean
    z = f_mean - f_hat
    gB = g * C_BP_end[:, 2]
    H = np.zeros((3, N_STATES))
    H[:, I_ATT] = -skew(gB)
    H[:, I_AV] = np.eye(3)
    H[:, I_BA] = np.eye(3)
    H[:, 18] = -C_BP_end[:, 2]
    r = max(p.accel_noise_m_s2 ** 2 / st.acc_n, p.accel_meas_floor_m_s2 ** 2)
    S = H @ P @ H.T + np.eye(3) * r
    S_inv = np.linalg.inv(S)
    nis = float(z @ S_inv @ z)
    ratio = nis / p.gate_chi2
    gate_ok = ratio <= 1.0
    reentry_ok, settle_ratio = _reentry(st, z, r, s0 * (1.0 - phi_diag[6] ** 2), p)
    fused = gate_ok and reentry_ok
    q_new = st.q_P_from_body
    x_new = xh
    raised = 0.0
    if fused and st.gated_run > 0 and p.reentry_match_gain > 0.0:
        P, raised = _match_gated_accel(P, z, S, p.reentry_match_gain)
        S = H @ P @ H.T + np.eye(3) * r
        S_inv = np.linalg.inv(S)
    if fused:
        K = P @ H.T @ S_inv
        dx = K @ z
        I_KH = np.eye(N_STATES) - K @ H
        P = I_KH @ P @ I_KH.T + K @ (np.eye(3) * r) @ K.T   # Joseph form
        # inject: C_PB <- C_PB (I + [eps x])  ==  q <- q * q(eps)
        q_new = quat_mul(st.q_P_from_body, quat_from_rotvec(dx[0:3]))
        q_new = q_new / math.sqrt(float(q_new @ q_new))
        x_new = xh + dx[3:]
        # after the reset the attitude error is zero; to first order the covariance is unchanged
    C_BP_new = dcm_from_quat(q_new).T
    P = _cap_platform_yaw(P, C_BP_new[:, 2], p.max_platform_yaw_sigma_rad)
    P = 0.5 * (P + P.T)
    st2 = replace(st, q_P_from_body=q_new, x_hat=x_new, P=P, acc_n=0, acc_dt_s=0.0,
                  acc_f_sum_m_s2=np.zeros(3), acc_down_sum=np.zeros(3),
                  acc_q_b0_from_b=np.array([1.0, 0.0, 0.0, 0.0]), acc_C_BP_start=C_BP_new,
                  n_updates=st.n_updates + 1, n_rejected=st.n_rejected + (0 if fused else 1),
                  gated_run=0 if fused else st.gated_run + 1,
                  reentry_wait=st.reentry_wait + 1 if (gate_ok and not fused) else 0,
                  z_prev_m_s2=z)
    reason = ("" if fused else "specific-force residual gated out" if not gate_ok
              else "specific-force residual not settled after a gated-out run")
    f_c = f_mean - xh[12:15]
    if not gate_ok and _at_rest(st, f_c, g, w_mean, z, r, s0 * (1.0 - phi_diag[6] ** 2), p):
        st2 = replace(st2, rest_gated_run=st.rest_gated_run + 1, rest_f_sum_m_s2=st.rest_f_sum_m_s2 + f_c,
                      rest_s=st.rest_s + T)
    elif st.rest_gated_run:
        st2 = replace(st2, rest_gated_run=0, rest_f_sum_m_s2=np.zeros(3), rest_s=0.0)
    if p.relevel_allowed and st2.rest_gated_run and st2.rest_s + 1e-9 >= p.relevel_rest_s:
        st2, moved = _relevel(st2, p)
        return st2, PolarAttitudeDiag(
            updated=True, fused=False, innovation_m_s2=z, test_ratio=ratio, settle_ratio=settle_ratio,
            reason=f"re-levelled at rest: tilt corrected by {math.degrees(moved):.1f} deg from the accelerometer "
                   f"after {p.relevel_rest_s:.1f} s of gated-out updates", relevelled=True, relevel_rad=moved)
    return st2, PolarAttitudeDiag(updated=True, fused=fused, innovation_m_s2=z, test_ratio=ratio,
                                  reason=reason, settle_ratio=settle_ratio, accel_var_raised_m2_s4=raised)


def _at_rest(st: PolarAttitudeState, f_c: np.ndarray, g: float, w_mean: np.ndarray, z: np.ndarray,
             r: float, q_av: float, p: PolarAttitudeParams) -> bool:
    """Rest test of one update interval: |f - b_a| ~ g, low rate, and a steady residual (it differs
    from the previous update's by no more than two steady residuals do, as ``_reentry``)."""
    if abs(float(np.linalg.norm(f_c)) - g) > p.relevel_norm_tol_m_s2:
        return False
    if float(np.linalg.norm(w_mean)) > p.relevel_max_rate_rad_s:
        return False
    if st.z_prev_m_s2 is None:
        return True
    d = z - st.z_prev_m_s2
    return float(d @ d) / (2.0 * r + q_av) <= p.reentry_settle_chi2


def _relevel(st: PolarAttitudeState, p: PolarAttitudeParams) -> tuple[PolarAttitudeState, float]:
    """Re-initialise roll/pitch from the accelerometer after a sustained gated-out rest.

    Why: the gate rejects a residual beyond sqrt(gate_chi2) innovation sigmas, and a rejected
    update changes nothing. A tilt error larger than that (after a tumble beyond the gyro range,
    or rotations the error model linearised badly: the issue-18 replay lay flat at roll -41 deg,
    pitch +31 deg, rejecting every update) is therefore never corrected. Widening the attitude
    covariance until the gate accepts (covariance matching, as ``_match_gated_accel`` does for
    a_v) would fuse a 40-180 deg error through the small-angle model C (I + [eps x]), which is
    wrong at that size; so at this depth the nominal attitude is reset exactly instead.

    When: every update of ``relevel_rest_s`` was gated out AND at rest (``_at_rest``: |f - b_a|
    within ``relevel_norm_tol_m_s2`` of g, body rate under ``relevel_max_rate_rad_s``, a steady
    residual). A wrong tilt at rest gives exactly that (a constant residual of |z| = 2 g sin(e/2)
    with |f| = g); a real acceleration a along the level gives |f| - g = a^2 / (2 g), so the
    norm test admits at most a_max = sqrt(2 g tol) of it (1.4 m/s^2 for 0.1 m/s^2).

    How: the measured down direction d_m = -f/|f| (mean of the rest run, b_a removed) and the
    estimated one d = C_BP[:, 2]. The smallest body rotation with R d_m = d (axis d_m x d, angle
    between them) gives C_PB' = C_PB R, so C_PB' d_m = e3: roll/pitch from the accelerometer,
    while the rotation has no component about the vertical, so P's azimuth (the heading the
    heading filter carries) and the gyro bias (a rate, not an angle) are kept.

    Sigma: the residual tilt error is the hidden acceleration and the horizontal accelerometer
    bias over g; a_max is taken as 3 sigma: sigma_t = hypot(a_max / 3, sigma_ba) / g (2.7 deg with
    the defaults). The attitude block becomes sigma_t^2 (I - d_m d_m^T) + v d_m d_m^T (v: the old
    variance about the vertical, kept), its cross-covariances are zeroed (the new tilt comes
    from the accelerometer, not from the states), and a_v restarts at its prior.
    """
    f = st.rest_f_sum_m_s2 / st.rest_gated_run
    C_BP = dcm_from_quat(st.q_P_from_body).T
    d_hat = C_BP[:, 2]
    d_m = -f / float(np.linalg.norm(f))
    axis = np.cross(d_m, d_hat)
    s_ang, c_ang = float(np.linalg.norm(axis)), float(d_m @ d_hat)
    angle = math.atan2(s_ang, c_ang)
    if s_ang < 1e-9:      # parallel (no move) or opposite (upside down): any axis normal to d_m
        axis = np.cross(d_m, [1.0, 0.0, 0.0] if abs(d_m[0]) < 0.9 else [0.0, 1.0, 0.0])
        s_ang = float(np.linalg.norm(axis))
    eps = axis / s_ang * angle
    q = quat_mul(st.q_P_from_body, quat_from_rotvec(eps))
    q = q / math.sqrt(float(q @ q))
    a_max = math.sqrt(2.0 * p.gravity_m_s2 * p.relevel_norm_tol_m_s2)
    sig_t = math.hypot(a_max / 3.0, p.accel_bias_sigma_m_s2) / p.gravity_m_s2
    v_vert = float(d_hat @ st.P[I_ATT, I_ATT] @ d_hat)
    P = st.P.copy()
    P[I_ATT, :] = 0.0
    P[:, I_ATT] = 0.0
    P[I_ATT, I_ATT] = sig_t ** 2 * (np.eye(3) - np.outer(d_m, d_m)) + v_vert * np.outer(d_m, d_m)
    P[I_AV, :] = 0.0
    P[:, I_AV] = 0.0
    P[I_AV, I_AV] = np.eye(3) * p.vehicle_accel_sigma_m_s2 ** 2
    x = st.x_hat.copy()
    x[3:6] = 0.0
    return replace(st, q_P_from_body=q, x_hat=x, P=P, acc_C_BP_start=dcm_from_quat(q).T,
                   gated_run=0, reentry_wait=0, z_prev_m_s2=None, rest_gated_run=0,
                   rest_f_sum_m_s2=np.zeros(3), rest_s=0.0, n_relevels=st.n_relevels + 1), angle


def _reentry(st: PolarAttitudeState, z: np.ndarray, r: float, q_av: float,
             p: PolarAttitudeParams) -> tuple[bool, float]:
    """(fuse allowed, settle ratio): the re-entry test after a gated-out run."""
    if st.gated_run == 0 or st.z_prev_m_s2 is None or p.reentry_max_wait_updates == 0:
        return True, math.nan
    d = z - st.z_prev_m_s2
    ratio = float(d @ d) / (2.0 * r + q_av) / p.reentry_settle_chi2
    if st.reentry_wait >= p.reentry_max_wait_updates:
        return True, ratio
    return ratio <= 1.0, ratio


def _match_gated_accel(P: np.ndarray, z: np.ndarray, S: np.ndarray, gain: float
                       ) -> tuple[np.ndarray, float]:
    """Raise the vehicle-acceleration variance along the re-entry residual (covariance matching).

    Used at the first update fused after a gated-out run (see the module docstring). A run of
    rejected residuals (NIS > gate_chi2) said the specific force held something the model gave
    almost no room, E[z z^T] = S = H P H^T + R violated; a rejected update changes nothing, so the
    a_v states are still at their prior (sigma_av = 0.2 m/s^2) when the updates pass again. Of the
    terms a residual can come from (a_v, eps, b_a, dg; H_av = I), only the vehicle acceleration
    changes by m/s^2 within seconds, so the missing variance is given to a_v, along the residual
    direction u = z/|z| where the surprise is (rank-one covariance matching, Mehra's adaptive
    process noise with a one-sample estimate):

        e = |z|^2 - u^T S u,      P_av <- P_av + gain * max(e, 0) * u u^T,  then S is recomputed

    so (gain 1) the innovation variance along u is at least |z|^2.

    The bound it buys (1-D along u, h = g, attitude sigma sigma_e, P_e = sigma_e^2): a fused
    update moves the attitude by d_eps = P_e h z / S, S = h^2 P_e + P_av + r. Without it the gate
    admits |z| up to sqrt(gate_chi2 S) with S ~ h^2 P_e (P_av at its small prior), so
    d_eps reaches sqrt(gate_chi2) sigma_e = 5 sigma_e: the first update that passed after the
    post-launch transient (which one depends on how the dropped samples fall into the update
    intervals) was attributed to roll/pitch. With it S >= max(|z|^2, h^2 P_e) >= |z| h sigma_e,
    so |d_eps| <= P_e h |z| / (|z| h sigma_e) = sigma_e: one attitude sigma at most.
    It is applied only at re-entry, not at every gated-out update: fusing a sustained
    acceleration into a_v and letting its GM mean decay (tau_av) feeds the residual back update
    after update, and part of it goes to the attitude (measured: -3.3 deg of roll over 2 s of the
    inclined_rail climb-out), whereas the gate keeps it out of the state altogether.
    """
    if gain == 0.0:
        return P, 0.0
    zz = float(z @ z)
    if not (zz > 0.0):
        return P, 0.0
    u = z / math.sqrt(zz)
    e = gain * (zz - float(u @ S @ u))
    if e <= 0.0:
        return P, 0.0
    P = P.copy()
    P[I_AV, I_AV] += e * np.outer(u, u)
    return P, e


def _cap_platform_yaw(P: np.ndarray, down_B: np.ndarray, cap_rad: float) -> np.ndarray:
    """Scale the covariance along the P-vertical attitude-error direction down to ``cap_rad``."""
    var = float(down_B @ P[I_ATT, I_ATT] @ down_B)
    if var <= cap_rad * cap_rad:
        return P
    s = cap_rad / math.sqrt(var)
    D = np.eye(N_STATES)
    D[I_ATT, I_ATT] += (s - 1.0) * np.outer(down_B, down_B)
    return D @ P @ D.T


def roll_pitch_jacobian(q_P_from_body: np.ndarray) -> np.ndarray:
    """d(roll, pitch)/d(eps) (2x3) for C_PB = C_PB_hat (I + [eps x]).

    With C_PB = C_hat (I + [eps x]) the down direction in B is d = C_BP e3 = (I - [eps x]) d_hat
    = d_hat + d_hat x eps.  roll = atan2(d_y, d_z), pitch = -asin(d_x) (d = [-sin th,
    sin ph cos th, cos ph cos th]), so with the chain rule
    d roll = (d_z dd_y - d_y dd_z) / (d_y^2 + d_z^2),  d pitch = -dd_x / sqrt(1 - d_x^2).
    1 - d_x^2 is taken as d_y^2 + d_z^2 (d is a unit vector): near pitch +-90 deg 1 - d_x^2 cancels,
    and rounding d_x (1e-16) alone moved the pitch variance by 1e-9 relative at 89.95 deg (the core's
    parity test, tests/test_core_polar_attitude.py, on the any_motion handheld flight); the sum keeps
    full precision.
    """
    d = _down_in_body(np.asarray(q_P_from_body, float))
    Dd = skew(d)                        # dd/deps: d x eps = skew(d) @ eps
    den = d[1] ** 2 + d[2] ** 2
    J_roll = (d[2] * Dd[1] - d[1] * Dd[2]) / den
    J_pitch = -Dd[0] / math.sqrt(max(1e-12, den))
    return np.vstack([J_roll, J_pitch])


def polar_attitude_estimate(state: PolarAttitudeState) -> AttitudeEstimate | None:
    """Roll, pitch (rad) and their covariance; None before the filter has levelled."""
    if not state.initialised:
        return None
    roll, pitch, _ = euler_from_dcm(dcm_from_quat(state.q_P_from_body))
    J = roll_pitch_jacobian(state.q_P_from_body)
    cov = J @ state.P[I_ATT, I_ATT] @ J.T
    return AttitudeEstimate(roll_rad=roll, pitch_rad=pitch, cov_roll_pitch_rad2=cov,
                            gyro_bias_rad_s=state.x_hat[0:3].copy(),
                            q_P_from_body=state.q_P_from_body.copy())


class PolarAttitudeFilter:
    """Thin holder around the pure step (same results as calling the functions)."""

    def __init__(self, params: PolarAttitudeParams = PolarAttitudeParams(),
                 state: PolarAttitudeState | None = None) -> None:
        self.params = params
        self.state = state if state is not None else polar_attitude_init(params)

    def step(self, time_s: float, gyro_body_rad_s, accel_body_m_s2) -> PolarAttitudeDiag:
        self.state, diag = polar_attitude_step(self.state, time_s, gyro_body_rad_s,
                                               accel_body_m_s2, self.params)
        return diag

    def estimate(self) -> AttitudeEstimate | None:
        return polar_attitude_estimate(self.state)
