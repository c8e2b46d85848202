"""Health of the trusted attitude reference: the flight controller's own estimate (METHODS.md B).

The synthetic AHRS learns (gyro zero correction, KF1 magnetometer errors) and aligns only while
the FC's attitude is trusted. Trusted means all of:

1. signalled health: the last HEARTBEAT system_status is STANDBY or ACTIVE (not CRITICAL /
   EMERGENCY / booting), and the last estimator status says attitude_ok and, with
   ``require_horiz_pos_ok`` (default), horiz_pos_ok: losing GNSS (the simulator's "GNSS lost /
   degraded" switch) clears horiz_pos_ok in EKF_STATUS_REPORT, and the FC's attitude then
   degrades slowly, so the loss of the position solution is the signal to stop trusting it.
   Before the FC's first estimator status its attitude is no reference: an FC publishes ATTITUDE
   from a fallback before its EKF runs (ArduPlane SITL: DCM from boot, 13 deg of magnetic yaw off
   and its pitch still settling; its first EKF_STATUS_REPORT, 1.1 s after the first ATTITUDE the
   daemon saw, said EKF_UNINITIALIZED; trusted for that 1.1 s, method B took DCM's yaw and pitch
   and learnt a -0.19 deg/s yaw gyro bias from them that made the FC's good EKF3 attitude read as
   "disagrees with gyros" 13 s after take-off). The rule for an FC that sends no estimator status
   at all (a log without one, an FC that does not stream it): after ``status_wait_s`` of FC time
   from the first ATTITUDE checked with none, its attitude is judged on 2. and 3. alone (the
   Pipeline says so in its log once);
2. freshness: an FC ATTITUDE sample no older than ``max_attitude_age_s`` (FC time), and a stream
   that comes at least that often (the mean interval, an exponential average of the FC-time steps):
   a 1 Hz ATTITUDE (ArduPilot's stock stream rate when a faster request is refused) would otherwise
   be fresh half of each second and stale the other half, and the FC's heading source would flap
   in and out of the arbitration with it;
3. agreement with our gyros (silent divergence): the FC's attitude change since an anchor is
   compared with the change of our bias-corrected, gyro-only attitude over the same interval.
   Anchors are laid every ``anchor_period_s`` and kept up to ``window_s``; for each anchor
   taken at t_a the FC attitude carried forward by our gyros, P = C_fc(t_a) C_gyro(t_a)^T
   C_gyro(t), is compared with C_fc(t): C_fc P^T = I + [d x] (d in nav axes); its tilt part
   |d_xy| and yaw part |d_z| must stay below n_sigma sqrt(2 sigma_fc^2 + (sigma_bias (t -
   t_a))^2 + V(t) - V(t_a)) + margin, with the FC's normal tilt and yaw error sigmas
   respectively, and V the integration error variance of our gyro-only attitude (per axis, rad^2,
   accumulated by its integrator: sampled rates; see ``health_on_attitude``).
   This is the rate-agreement test integrated over the window (a mean rate disagreement
   w over T shows as w T), so a slow drift that a sample-by-sample rate test misses is caught.
   Its threshold is set by the FC's normal error (sigma_fc): a silent drift is detected once it
   exceeds a few sigma_fc; a signalled loss is detected at once.

Losing trust latches: trust returns only after ``retrust_hold_s`` of continuous good signals and
agreement (the anchors are re-laid after a loss). A *silent* divergence latches harder: a
reference that drifted without saying so is not trusted again on short-term agreement (a slow
drift passes any short window); only a signalled recovery (its status going bad and then good
again) or ``health_init`` clears it.

Clocks: every event carries ``time_s`` on the estimator's (FC) clock; the service maps
HEARTBEAT/EKF receive times onto it.

Pure: ``health_on_heartbeat``, ``health_on_ekf_status``, ``health_on_attitude`` return a new
state; ``health_trusted(state, time_s, params) -> (bool, reason)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

INTERVAL_AVERAGING = 0.2
"""Weight of the newest FC-time step in the mean ATTITUDE interval."""
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
HEALTHY_SYSTEM_STATUS = (MAV_STATE_STANDBY, MAV_STATE_ACTIVE)


@dataclass(frozen=True)
class ReferenceHealthParams:
    require_horiz_pos_ok: bool = True
    """Stop trusting the FC attitude when its position solution (GNSS) is lost."""
    max_attitude_age_s: float = 0.5
    """An FC ATTITUDE older than this (s) is stale."""
    anchor_period_s: float = 5.0
    """A new agreement anchor every this many seconds (s)."""
    window_s: float = 60.0
    """Anchors are kept this long (s): the longest interval over which drift is compared."""
    sigma_fc_tilt_rad: float = math.radians(0.4)
    """1-sigma of the FC's normal roll/pitch error."""
    sigma_fc_yaw_rad: float = math.radians(1.0)
    """1-sigma of the FC's normal yaw error."""
    sigma_bias_rad_s: float = math.radians(0.01)
    """1-sigma of our residual gyro bias (rad/s) after the zero correction."""
    check_period_s: float = 0.2
    """The agreement test runs at most this often (s); the anchors' spacing is much longer."""
    n_sigma: float = 4.0
    margin_rad: float = math.radians(0.5)
    retrust_hold_s: float = 10.0
    """Continuous good time (s) needed to trust again after a loss."""
    status_wait_s: float = 5.0
    """FC time (s) from the first ATTITUDE checked that an estimator status is waited for before the
    FC is taken to send none (then trusted without one). ArduPilot streams EKF_STATUS_REPORT at the
    2 Hz the daemon asks (1 Hz stock); PX4 ESTIMATOR_STATUS likewise: 5 s is several periods."""

    def __post_init__(self):
        for name in ("max_attitude_age_s", "anchor_period_s", "window_s", "sigma_fc_tilt_rad", "sigma_fc_yaw_rad", "check_period_s",
                     "sigma_bias_rad_s", "n_sigma", "retrust_hold_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if not (math.isfinite(self.status_wait_s) and self.status_wait_s >= 0.0):   # 0: known to send none
            raise ValueError(f"status_wait_s must be finite and >= 0, got {self.status_wait_s!r}")
        if self.margin_rad < 0.0:
            raise ValueError(f"margin_rad must be >= 0, got {self.margin_rad!r}")


@dataclass(frozen=True)
class ReferenceHealthState:
    system_status: int | None = None
    attitude_ok: bool | None = None
    horiz_pos_ok: bool | None = None
    fc_time_s: float | None = None
    """FC time of the last ATTITUDE sample."""
    first_attitude_s: float | None = None
    """FC time of the first ATTITUDE checked (``health_on_attitude``): the status wait's start."""
    attitude_interval_s: float | None = None
    """Mean interval of the FC's ATTITUDE samples (FC time, exponential average)."""
    anchors: tuple = ()
    """((t_a, C_fc(t_a), C_gyro(t_a), V(t_a)), ...), oldest first (V: the integration variance)."""
    max_discrepancy_rad: float = 0.0
    """Largest anchor test ratio at the last check (delta / threshold; > 1 diverged)."""
    check_time_s: float | None = None
    diverged: bool = False
    good_since_s: float | None = None
    """Start of the current run of good signals + agreement (None while bad)."""
    ever_trusted: bool = False
    latched_out: bool = False
    """True after a loss until retrust_hold_s of good time."""
    silent_divergence: bool = False
    """A divergence seen while the status said healthy; cleared by a signalled bad -> good."""
    reason: str = "no FC attitude yet"


def health_init() -> ReferenceHealthState:
    return ReferenceHealthState()


def health_on_heartbeat(state: ReferenceHealthState, system_status: int) -> ReferenceHealthState:
    return replace(state, system_status=int(system_status))


def health_on_ekf_status(state: ReferenceHealthState, attitude_ok: bool,
                         horiz_pos_ok: bool) -> ReferenceHealthState:
    return replace(state, attitude_ok=bool(attitude_ok), horiz_pos_ok=bool(horiz_pos_ok))


NO_STATUS_YET = "no FC estimator status yet"


def health_status_missing(state: ReferenceHealthState, params: ReferenceHealthParams = ReferenceHealthParams(),
                          time_s: float | None = None) -> bool:
    """No estimator status came within ``status_wait_s`` of the first ATTITUDE checked (at FC time
    ``time_s``, default the last ATTITUDE's): the FC is taken to send none."""
    t = state.fc_time_s if time_s is None else time_s
    return (state.attitude_ok is None and state.first_attitude_s is not None and t is not None
            and t - state.first_attitude_s >= params.status_wait_s)


def _signals_bad(state: ReferenceHealthState, params: ReferenceHealthParams, time_s: float) -> str:
    if state.system_status is not None and state.system_status not in HEALTHY_SYSTEM_STATUS:
        return f"FC system_status {state.system_status}"
    if state.attitude_ok is None and not health_status_missing(state, params, time_s):
        return NO_STATUS_YET
    if state.attitude_ok is False:
        return "FC EKF attitude not ok"
    if params.require_horiz_pos_ok and state.horiz_pos_ok is False:
        return "FC EKF horizontal position lost (GNSS)"
    return ""


def health_on_attitude(state: ReferenceHealthState, C_nav_from_body_fc: np.ndarray,
                       C_nav_from_body_gyro: np.ndarray, time_s: float,
                       params: ReferenceHealthParams = ReferenceHealthParams(),
                       gyro_integration_var_rad2: float = 0.0) -> ReferenceHealthState:
    """An FC ATTITUDE sample at FC time ``time_s`` with our gyro-only attitude at that time.

    ``gyro_integration_var_rad2``: the integration error variance (per axis, rad^2) accumulated
    by our gyro-only attitude since it started (non-decreasing); the part accumulated since an
    anchor widens that anchor's threshold. A 25 Hz log of a vibrating multicopter integrates
    degrees of error in seconds that a 400 Hz stream does not: without this term the GNSS-aided
    FC attitude of arducopter-rtl-midflight.bin read as a silent divergence after 23 s."""
    C_fc = np.asarray(C_nav_from_body_fc, dtype=float)
    C_g = np.asarray(C_nav_from_body_gyro, dtype=float)
    if not (np.all(np.isfinite(C_fc)) and np.all(np.isfinite(C_g)) and math.isfinite(time_s)):
        raise ValueError("health_on_attitude: non-finite input")
    interval = state.attitude_interval_s
    if state.fc_time_s is not None and 0.0 < time_s - state.fc_time_s < params.window_s:
        step = time_s - state.fc_time_s  # the mean interval: new = old + a (step - old)
        interval = step if interval is None else interval + INTERVAL_AVERAGING * (step - interval)
    state = replace(state, attitude_interval_s=interval,
                    first_attitude_s=time_s if state.first_attitude_s is None else state.first_attitude_s)
    if (state.check_time_s is not None and 0.0 <= time_s - state.check_time_s < params.check_period_s
            and not _signals_bad(state, params, time_s)):
        return replace(state, fc_time_s=time_s)
    worst = 0.0
    for t_a, C_fc_a, C_g_a, v_a in state.anchors:
        predicted = C_fc_a @ C_g_a.T @ C_g          # FC attitude carried forward by our gyros
        # discrepancy as a small nav-frame rotation: C_fc ~ (I + [d x]) predicted
        D = C_fc @ predicted.T
        d = 0.5 * np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
        drift2 = (params.sigma_bias_rad_s * (time_s - t_a)) ** 2 + max(0.0, gyro_integration_var_rad2 - v_a)
        thr_tilt = params.n_sigma * math.sqrt(2.0 * params.sigma_fc_tilt_rad ** 2 + drift2) + params.margin_rad
        thr_yaw = params.n_sigma * math.sqrt(2.0 * params.sigma_fc_yaw_rad ** 2 + drift2) + params.margin_rad
        worst = max(worst, math.hypot(d[0], d[1]) / thr_tilt, abs(d[2]) / thr_yaw)
    diverged = worst > 1.0
    signals = _signals_bad(state, params, time_s)
    anchors = tuple(a for a in state.anchors if time_s - a[0] <= params.window_s)
    if diverged or signals or state.silent_divergence:
        anchors = ()                                 # re-lay after the reference recovers
    elif not anchors or time_s - anchors[-1][0] >= params.anchor_period_s:
        anchors = anchors + ((time_s, C_fc.copy(), C_g.copy(), float(gyro_integration_var_rad2)),)
    silent = (state.silent_divergence or (diverged and not signals)) and not signals
    good = not (diverged or signals or silent)
    good_since = (state.good_since_s if state.good_since_s is not None else time_s) if good else None
    # waiting for the first status is no loss: trusted at once when it says good (no re-trust hold)
    latched = state.latched_out or diverged or (bool(signals) and signals != NO_STATUS_YET) or silent
    if latched and good and time_s - good_since >= params.retrust_hold_s:
        latched = False
    reason = signals or ("FC attitude disagrees with gyros" if (diverged or silent) else "")
    return replace(state, fc_time_s=time_s, check_time_s=time_s, anchors=anchors, max_discrepancy_rad=worst,
                   diverged=diverged or silent, silent_divergence=silent, good_since_s=good_since, latched_out=latched,
                   ever_trusted=state.ever_trusted or (good and not latched),
                   reason=reason if reason else ("re-trust hold" if latched else ""))


def health_trusted(state: ReferenceHealthState, time_s: float,
                   params: ReferenceHealthParams = ReferenceHealthParams()) -> tuple[bool, str]:
    """Is the FC attitude trusted at FC time ``time_s``? (trusted, reason when not)."""
    if state.fc_time_s is None:
        return False, "no FC attitude yet"
    if state.attitude_interval_s is not None and state.attitude_interval_s > params.max_attitude_age_s:
        return False, (f"FC ATTITUDE every {state.attitude_interval_s:.2f} s (> {params.max_attitude_age_s:g} s): "
                       "too slow to be a reference")
    if time_s - state.fc_time_s > params.max_attitude_age_s:
        return False, f"FC attitude stale ({time_s - state.fc_time_s:.2f} s)"
    signals = _signals_bad(state, params, time_s)
    if signals:
        return False, signals
    if state.diverged:
        return False, "FC attitude disagrees with gyros"
    if state.latched_out:
        return False, "re-trust hold"
    return True, ""
