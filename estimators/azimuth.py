"""In-flight azimuth without GNSS (METHODS.md A; seed AU2018311656B2): the incremental estimator.

Phases and API (pure functions; the parameters live in the state, set once by ``azimuth_init``):

    state = azimuth_init(params)                                  # AzimuthParams, frozen
    state = azimuth_prelaunch_step(state, gyro_rad_s, accel_m_s2, time_s)   # at rest
    state, reason = azimuth_launch(state, launch_time_s)          # freeze ISF, start propagation
    state, out = azimuth_step(state, gyro_rad_s, accel_m_s2, mag_gauss_or_None, time_s)
    # out: AzimuthOutput at the IMU rate (valid once the gate has passed)

Pre-launch: samples go through a short delay line (``prelaunch_buffer_s``) into the levelling
(roll, pitch of ISF, gyro bias, METHODS.md A step 2). ``azimuth_launch(t_L)`` levels on the
samples older than t_L and replays the buffered samples from t_L on through the flight step, so
a launch detected a few tens of ms late still starts the gyro propagation at the true start of
motion (``launch_direction.launch_detect_step`` returns that start time).

In flight, per IMU sample:
 1. C_ISF<-SF(t) by the coning-correct strapdown of bias-corrected rates (step 4), and the
    attitude-error sensitivity G(t) (3 x 12) to the gyro errors c_g = [bias change (3), scale and
    misalignment matrix T (9)]: bias columns -int C_ISF<-SF dt, T columns int C[:, i] w_j dt.
 2. flight direction u_SF (step 3): vertical from gravity, inclined from the thrust phase of the
    boost, aligned from ``C_body_from_sensor``; cross-checked against the mount-aligned direction
    (angle in the output) and against the configured launcher elevation.
 3. magnetometer samples, decimated to ``mag_decimation_s`` and skipped for
    ``mag_skip_after_launch_s`` (the launcher's own field, the site distortion), are kept with
    their attitude, G and the weight
       w_i = 1 / (sigma_h^2 + 2/3 |e|^2 (ARW^2 tau_i + sigma_bias^2 tau_i^2))   tau_i = t_i - t_L
    i.e. samples whose attitude carries more gyro drift count less (beyond the seed).
 4. every ``resolve_period_s`` (``resolve_period_unsolved_s`` before the first solution)
    ``azimuth_fit.fit_psi`` re-solves psi_s with all samples ("none" / "seed7" / "full12"
    distortion model). With ``estimate_errors`` the gyro errors c_g and the levelling tilt beta
    (2) are estimated jointly with their priors (MAP; else they are consider parameters that only
    widen the sigma). The gate decides; an accepted solution is kept until a newer one passes the
    gate (a later failed re-solve is reported as "holding" with the reason).
 5. output at every sample (eq. 6-8), the propagated attitude corrected by the estimated errors
    (C = (I - [G c_g]x) C_ISF<-SF, (I - [beta]x) C_AF<-ISF):
       C_NF<-SF = R3(psi)^T C_AF<-ISF C_ISF<-SF(t),  azimuth = az(C_NF<-SF u_SF)
       heading  = yaw of C_NF<-body = C_NF<-SF C_SF<-body (the body x axis, may differ from u)
    with sigmas from the joint covariance of [psi, c] and the instantaneous sensitivities
    (``azimuth_fit.direction_azimuth_and_sigma``) + ARW + the configured field-model sigma.
    roll/pitch (and q_nav_from_body with yaw from psi = 0) are output from launch on.

What limits it (bench/azimuth_accuracy.py): the levelling tilt from the accelerometer bias
(~bias/g) turns into a heading error of about tilt * tan(inclination) that no magnetometer data
can remove (a rotation about the field vector is unobservable); the sigma carries it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators import azimuth_fit as af
from estimators.launch_direction import (LAUNCH_CASES, BoostParams, BoostState, boost_direction, boost_init, boost_step, elevation_rad,
                                         u_aligned, u_vertical)
from estimators.azimuth_fit import angle_between
from estimators.records import fast_replace
from estimators.levelling import (LevellingParams, LevellingResult,
                                  LevellingState, levelling_result, levelling_step)
from estimators.rotations import dcm_from_quat, euler_from_dcm, quat_from_dcm, skew
from estimators.strapdown import StrapdownParams, StrapdownState, strapdown_init, strapdown_step

STATUS = ("prelaunch", "failed", "collecting", "withheld", "solved", "holding")
N_GYRO_CONSIDER = 12
"""Gyro consider parameters: bias error (3) and the scale/misalignment matrix T (9)."""


@dataclass(frozen=True)
class AzimuthParams:
    e_ned_gauss: np.ndarray
    """Earth field at the flight area, NED, gauss (estimators.geomag.earth_field or configured)."""
    launch_case: str = "inclined"
    """'vertical' | 'inclined' | 'aligned' (how u_SF is found, METHODS.md A step 3)."""
    distortion_model: str = "seed7"
    """'none' (psi only) | 'seed7' (3 scales, 3 biases, psi) | 'full12' (soft + hard iron, psi)."""
    C_body_from_sensor: np.ndarray = field(default_factory=lambda: np.eye(3))
    """Configured IMU mounting rotation (3x3). Used for 'aligned', the heading and cross-checks."""
    mount_configured: bool = True
    """False when C_body_from_sensor is only a placeholder: then no mount cross-check."""
    launcher_elevation_rad: float | None = None
    """Configured launcher elevation, for the cross-check of u_SF (None: not configured)."""
    gate: af.GateParams = af.GateParams()
    levelling: LevellingParams = LevellingParams()
    strapdown: StrapdownParams = StrapdownParams()
    boost: BoostParams = BoostParams()
    prelaunch_buffer_s: float = 0.5
    """Delay line before the levelling; must exceed the launch detector's latency."""
    mag_decimation_s: float = 0.1
    """Smallest interval between magnetometer samples entering the fit (10 Hz)."""
    mag_skip_after_launch_s: float = 2.0
    """Magnetometer samples this close to launch are not used: the launcher's own field and the
    site distortion fade within 10-20 m, ~40 m is flown in 2 s."""
    max_fit_samples: int = 1500
    """Samples kept for the fit; later ones are not added (they carry the most drift)."""
    resolve_period_s: float = 1.0
    """Re-solve interval once solved."""
    resolve_period_unsolved_s: float = 0.5
    """Re-solve interval before the first accepted solution."""
    mag_noise_sigma_gauss: float = 0.003
    """Per-axis white noise of the magnetometer, incl. quantisation (G)."""
    gyro_arw_rad_sqrt_s: float = math.radians(0.01)
    """Gyro angle random walk, rad/sqrt(s) (= rad/s/sqrt(Hz))."""
    gyro_bias_sigma_rad_s: float = math.radians(0.01)
    """1-sigma of the gyro bias change between the rest calibration and flight (rad/s)."""
    gyro_scale_sigma: float = 3e-3
    """1-sigma gyro scale-factor error (consider parameter, per axis)."""
    gyro_misalign_sigma_rad: float = 3e-3
    """1-sigma gyro axis misalignment / cross-coupling (consider parameter, 6 elements)."""
    estimate_errors: bool = True
    """Estimate the gyro bias change, gyro scale/misalignment and levelling tilt jointly with psi_s
    (MAP with their priors); False: only consider them (their effect widens the sigma)."""
    drift_weighting: bool = True
    """Weight samples by the gyro drift their attitude carries (False: white noise only)."""
    field_model_sigma_rad: float = 0.0
    """Declination uncertainty of the field model added to the azimuth/heading variance (rad).
    0 reports the error relative to the model; the WMM's own figure is in EarthField."""
    cross_check_max_rad: float = math.radians(5.0)
    """Flight-direction cross-checks above this are flagged."""
    consistency_chi2: float = 6.63
    """A's consistency check (``_wander_var``) widens the sigma only when a re-solve's heading moved
    from the first solution's by d with d^2 > this x its model variance (chi-square, 1 dof: 6.63 =
    a 1 % false alarm per check, |d| > 2.58 sigma_d). Under a consistent model d^2 / var(d) is
    chi-square distributed and exceeds 1 on 32 % of the checks: every excess counted (0, session 6's
    check) widened consistent solutions (azimuth_accuracy's aligned NEES 0.86 -> 0.47)."""

    def __post_init__(self):
        e = np.asarray(self.e_ned_gauss, float)
        if e.shape != (3,) or not np.all(np.isfinite(e)) or math.hypot(e[0], e[1]) < 1e-3:
            raise ValueError(f"e_ned_gauss must be a finite NED field with a horizontal part, got {self.e_ned_gauss!r}")
        object.__setattr__(self, "e_ned_gauss", e)
        if self.launch_case not in LAUNCH_CASES:
            raise ValueError(f"launch_case must be one of {LAUNCH_CASES}, got {self.launch_case!r}")
        if self.distortion_model not in af.MODELS:
            raise ValueError(f"distortion_model must be one of {af.MODELS}, got {self.distortion_model!r}")
        C = np.asarray(self.C_body_from_sensor, float)
        if C.shape != (3, 3) or not np.all(np.isfinite(C)) or not np.allclose(C @ C.T, np.eye(3), atol=1e-6) \
                or np.linalg.det(C) < 0:
            raise ValueError("C_body_from_sensor must be a 3x3 rotation matrix")
        object.__setattr__(self, "C_body_from_sensor", C)
        for name in ("prelaunch_buffer_s", "mag_decimation_s", "resolve_period_s", "resolve_period_unsolved_s",
                     "mag_noise_sigma_gauss"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("mag_skip_after_launch_s", "gyro_arw_rad_sqrt_s", "gyro_bias_sigma_rad_s",
                     "gyro_scale_sigma", "gyro_misalign_sigma_rad",
                     "field_model_sigma_rad", "consistency_chi2"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {getattr(self, name)}")
        if self.max_fit_samples < self.gate.min_samples:
            raise ValueError(f"max_fit_samples {self.max_fit_samples} < gate.min_samples {self.gate.min_samples}")


@dataclass(frozen=True)
class MagRecord:
    time_s: float
    h_sf_gauss: np.ndarray
    C_sf_from_isf: np.ndarray
    G_gyro: np.ndarray


@dataclass(frozen=True)
class Solution:
    """An accepted (gated) fit."""
    time_s: float
    fit: af.FitResult
    psi_sigma_rad: float
    diversity_rad: float
    C_nf_af: np.ndarray
    """R3(psi)^T."""
    C_af_isf: np.ndarray
    """C_AF<-ISF corrected by the estimated tilt: (I - [beta]x) C_AF<-ISF."""
    c_gyro: np.ndarray
    """Estimated gyro errors (K); the attitude is corrected by alpha = G(t) c_gyro."""
    wander_var_rad2: float = 0.0
    """Heading variance the fit's own re-solves showed beyond its model (``_wander_var``),
    added to the output sigma."""
    last_sample_s: float = math.nan
    """Time of the last magnetometer sample the fit used: after it A's attitude is the gyros' alone
    (``_output``: the in-run bias consider term)."""


@dataclass(frozen=True)
class AzimuthState:
    params: AzimuthParams
    phase: str = "prelaunch"
    reason: str = "levelling"
    levelling: LevellingState = LevellingState()
    pending: tuple = ()
    """Delay line of (time_s, gyro, accel) before they enter the levelling."""
    # frozen at launch
    launch_time_s: float | None = None
    levelled: LevellingResult | None = None
    C_isf_af: np.ndarray | None = None
    gyro_bias_rad_s: np.ndarray | None = None
    P_consider: np.ndarray | None = None
    # in flight
    strapdown: StrapdownState | None = None
    C_isf_sf: np.ndarray = field(default_factory=lambda: np.eye(3))
    """C_ISF<-SF of the strapdown quaternion (cached)."""
    G_gyro: np.ndarray = field(default_factory=lambda: np.zeros((3, N_GYRO_CONSIDER)))
    """Attitude-error sensitivity alpha_ISF = G c_g to the gyro errors c_g = [bias error (3),
    T row-major (9): scale on the diagonal, misalignment off it] (see azimuth_fit)."""
    boost: BoostState | None = None
    u_sf: np.ndarray | None = None
    u_reason: str = ""
    cross_check_rad: float = math.nan
    """Angle between the configured-case u_SF and the other available one (nan: none)."""
    elevation_check_rad: float = math.nan
    """Elevation of u_SF minus the configured launcher elevation (nan: not configured)."""
    du_dbeta_sf: np.ndarray | None = None
    """(3, 2) error of u_SF per levelling tilt error (vertical case: u is the measured up);
    derivation: up_meas = C_ISF<-AF (I - [beta]x) z_up, so d up = C_ISF<-AF [z_up]x beta."""
    samples: tuple = ()
    last_mag_s: float = -math.inf
    last_solve_s: float = -math.inf
    solution: Solution | None = None
    first_solution: Solution | None = None
    """The first accepted solution: the reference of the re-solves' consistency check."""
    last_fit: af.FitResult | None = None
    last_diversity_rad: float = math.nan
    last_gate_reason: str = ""


@dataclass(frozen=True)
class AzimuthOutput:
    time_s: float
    status: str
    """prelaunch | failed | collecting | withheld | solved | holding (see STATUS)."""
    reason: str
    """Why not (yet) valid, or what is flagged; '' when all is well."""
    valid: bool
    """azimuth/heading may be used (a gated solution and a flight direction exist)."""
    azimuth_rad: float = math.nan
    """Azimuth of the flight direction u (true, [0, 2pi))."""
    azimuth_sigma_rad: float = math.nan
    launch_azimuth_rad: float = math.nan
    """Azimuth of u at the launch instant (the launcher azimuth for a rail)."""
    heading_rad: float = math.nan
    """Heading (true) of the body x axis."""
    heading_sigma_rad: float = math.nan
    roll_rad: float = math.nan
    pitch_rad: float = math.nan
    q_nav_from_body: np.ndarray | None = None
    """Full attitude (valid yaw only when ``valid``); roll/pitch are available from launch on."""
    psi_s_rad: float = math.nan
    psi_s_sigma_rad: float = math.nan
    n_samples: int = 0
    diversity_rad: float = math.nan
    condition_number: float = math.nan
    normalised_residual: float = math.nan
    distortion_A: np.ndarray | None = None
    distortion_b_gauss: np.ndarray | None = None
    u_sf: np.ndarray | None = None
    cross_check_rad: float = math.nan
    elevation_check_rad: float = math.nan


def azimuth_init(params: AzimuthParams) -> AzimuthState:
    return AzimuthState(params=params)


def azimuth_prelaunch_step(state: AzimuthState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                           time_s: float) -> AzimuthState:
    """At rest on the launcher: feed the levelling through the delay line."""
    if state.phase != "prelaunch":
        raise ValueError(f"azimuth_prelaunch_step in phase {state.phase!r}")
    g = np.asarray(gyro_rad_s, float)
    a = np.asarray(accel_m_s2, float)
    if g.shape != (3,) or a.shape != (3,) or not math.isfinite(time_s):
        raise ValueError("gyro_rad_s and accel_m_s2 must have shape (3,), time_s finite")
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
        return state  # a bad sample is dropped, not levelled
    pending = state.pending + ((float(time_s), g, a),)
    lev = state.levelling
    cut = time_s - state.params.prelaunch_buffer_s
    k = 0
    while k < len(pending) and pending[k][0] < cut:
        lev = levelling_step(lev, pending[k][1], pending[k][2])
        k += 1
    return fast_replace(state, levelling=lev, pending=pending[k:])  # per sample: no __post_init__ to re-run


def azimuth_levelling(state: AzimuthState) -> LevellingResult:
    """The levelling result so far (what the daemon shows before launch)."""
    return levelling_result(state.levelling, state.params.levelling)


def azimuth_launch(state: AzimuthState, launch_time_s: float) -> tuple[AzimuthState, str]:
    """Freeze ISF at the start of motion ``launch_time_s``; returns (state, '' or why it failed)."""
    if state.phase != "prelaunch":
        raise ValueError(f"azimuth_launch in phase {state.phase!r}")
    p = state.params
    lev = state.levelling
    replay = []
    for t, g, a in state.pending:
        if t < launch_time_s:
            lev = levelling_step(lev, g, a)
        else:
            replay.append((t, g, a))
    res = levelling_result(lev, p.levelling)
    if not res.ok:
        reason = f"levelling failed: {res.reason}"
        return replace(state, phase="failed", reason=reason, levelling=lev, pending=(),
                       launch_time_s=float(launch_time_s)), reason
    f_rest = res.accel_mean_m_s2
    C_isf_af = af.C_isf_from_af(res.roll_rad, res.pitch_rad)
    # the levelling's tilt sigma includes its accelerometer-bias allowance (LevellingParams)
    tilt_var = 0.5 * (res.roll_sigma_rad ** 2 + res.pitch_sigma_rad ** 2)
    T_var = [p.gyro_scale_sigma ** 2 if i == j else p.gyro_misalign_sigma_rad ** 2 for i in range(3) for j in range(3)]
    P_c = np.diag([p.gyro_bias_sigma_rad_s ** 2] * 3 + T_var + [tilt_var] * 2)
    u_sf, u_reason, cross, elev = None, "", math.nan, math.nan
    du_dbeta = None
    if p.launch_case == "vertical":
        u_sf = u_vertical(f_rest)
        du_dbeta = (C_isf_af @ skew(np.array([0.0, 0.0, -1.0])))[:, :2]
    elif p.launch_case == "aligned":
        u_sf = u_aligned(p.C_body_from_sensor)
    else:
        u_reason = "flight direction: waiting for boost"
    new = replace(state, phase="flight", reason="collecting", levelling=lev, pending=(),
                  launch_time_s=float(launch_time_s), levelled=res, C_isf_af=C_isf_af,
                  gyro_bias_rad_s=res.gyro_bias_rad_s, P_consider=P_c,
                  strapdown=strapdown_init(np.array([1.0, 0.0, 0.0, 0.0]), None),
                  boost=boost_init(f_rest, launch_time_s) if p.launch_case == "inclined" else None,
                  u_sf=u_sf, u_reason=u_reason, cross_check_rad=cross, elevation_check_rad=elev,
                  du_dbeta_sf=du_dbeta)
    if u_sf is not None:
        new = _with_checks(new, u_sf)
    # the first integration interval starts at the launch instant, at rest (corrected rate 0)
    new = replace(new, strapdown=StrapdownState(q_ref_from_sensor=new.strapdown.q_ref_from_sensor,
                                                time_s=float(launch_time_s), gyro_prev_rad_s=np.zeros(3)))
    for t, g, a in replay:
        if t > launch_time_s:
            new, _ = azimuth_step(new, g, a, None, t)
    return new, ""


def _with_checks(state: AzimuthState, u_sf: np.ndarray) -> AzimuthState:
    """Cross-check u_SF with the mount-aligned direction and the launcher elevation."""
    p = state.params
    cross = math.nan
    if p.mount_configured and p.launch_case != "aligned":
        cross = angle_between(u_sf, u_aligned(p.C_body_from_sensor))
    elev = math.nan
    if p.launcher_elevation_rad is not None:
        elev = elevation_rad(u_sf, state.levelled.accel_mean_m_s2) - p.launcher_elevation_rad
    return replace(state, u_sf=u_sf, cross_check_rad=cross, elevation_check_rad=elev)


REC_COLUMNS = 1 + 3 + 9 + 36
"""A stored sample packed as one row: time_s, h_sf_gauss (3), C_sf_from_isf (9, row-major), G_gyro (36)
(core/hot_path.hpp AzimuthRun.rec's layout)."""


def pack_samples(records) -> np.ndarray:
    """MagRecords as (N, REC_COLUMNS) rows."""
    out = np.empty((len(records), REC_COLUMNS))
    for i, r in enumerate(records):
        out[i, 0] = r.time_s
        out[i, 1:4] = r.h_sf_gauss
        out[i, 4:13] = r.C_sf_from_isf.reshape(9)
        out[i, 13:] = r.G_gyro.reshape(36)
    return out


def record_of(row: np.ndarray) -> MagRecord:
    """One packed row as its MagRecord (copies)."""
    return MagRecord(float(row[0]), row[1:4].copy(), row[4:13].reshape(3, 3).copy(), row[13:49].reshape(3, 12).copy())


class PackedSamples:
    """AzimuthState.samples as one (N, REC_COLUMNS) array (a sequence of MagRecord built on access): what
    the Pipeline hands its solver, so a worker process gets one ndarray instead of N pickled records
    (``_solve`` reads the rows straight). The same samples, the same solve."""
    __slots__ = ("rows",)

    def __init__(self, rows: np.ndarray):
        self.rows = rows

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return tuple(record_of(r) for r in self.rows[i])
        return record_of(self.rows[i])

    def __iter__(self):
        return (record_of(r) for r in self.rows)


def _solve(state: AzimuthState, time_s: float, fit_psi=af.fit_psi,
           orientation_diversity=af.orientation_diversity_rad) -> AzimuthState:
    """Re-solve with all kept samples and gate the result. ``fit_psi``, ``orientation_diversity``: the
    solve's implementations (``azimuth_fit``'s or the core's twins in estimators.core: the same results).
    The samples: a tuple of MagRecord, or PackedSamples (the same arrays, read from its rows)."""
    p = state.params
    recs = state.samples
    n = len(recs)
    e = p.e_ned_gauss
    if n < p.gate.min_samples:
        reason = af.gate_reason(None, n, 0.0, math.inf, p.gate)
        return replace(state, last_solve_s=time_s, last_gate_reason=reason)
    rows = recs.rows if isinstance(recs, PackedSamples) else pack_samples(recs)
    C = np.ascontiguousarray(rows[:, 4:13]).reshape(n, 3, 3)
    G = np.ascontiguousarray(rows[:, 13:]).reshape(n, 3, N_GYRO_CONSIDER)
    h = np.ascontiguousarray(rows[:, 1:4])
    tau = rows[:, 0] - state.launch_time_s
    e2 = float(e @ e)
    var_white = p.mag_noise_sigma_gauss ** 2 + (2.0 / 3.0) * e2 * p.gyro_arw_rad_sqrt_s ** 2 * tau
    var_drift = (2.0 / 3.0) * e2 * (p.gyro_bias_sigma_rad_s * tau) ** 2 if p.drift_weighting else 0.0
    data = af.FitData(C, h, var_white, 1.0 / (var_white + var_drift), G)
    fit = fit_psi(data, state.C_isf_af, e, p.distortion_model, P_prior=state.P_consider,
                  estimate_errors=p.estimate_errors)
    # the diversity is measured at the fitted psi only where the fit determines it: an unobservable fit's
    # psi is arbitrary (the same samples in another order give another; the gate rejects it on its
    # condition number), so there the closed-form 2-D fit of the undistorted model stands in
    determined = fit.ok and fit.condition_number <= p.gate.max_condition_number
    psi_for_div = fit.psi_rad if determined else af.psi_closed_form(np.einsum("nji,nj->ni", C @ state.C_isf_af, h),
                                                                    e, data.weight)
    diversity = orientation_diversity(C @ state.C_isf_af, psi_for_div, e)
    # the gate judges what the data determine (white + gyro terms); the levelling-tilt share does
    # not shrink with more samples, it is reported in the sigma instead
    ok = fit.ok and fit.P_psi_c[0, 0] > 0.0 and math.isfinite(fit.psi_sigma_gate_rad)
    psi_sigma_fit = fit.psi_sigma_gate_rad if ok else math.inf
    psi_sigma = math.sqrt(fit.P_psi_c[0, 0]) if ok else math.inf
    reason = af.gate_reason(fit, n, diversity, psi_sigma_fit, p.gate)
    sol = state.solution
    if reason == "":
        K = N_GYRO_CONSIDER
        beta = np.array([fit.c_hat[K], fit.c_hat[K + 1], 0.0])
        sol = Solution(time_s, fit, psi_sigma, diversity, af.r3(fit.psi_rad).T,
                       (np.eye(3) - skew(beta)) @ state.C_isf_af.T, fit.c_hat[:K].copy(),
                       last_sample_s=float(rows[-1, 0]))
        if state.first_solution is not None:
            sol = replace(sol, wander_var_rad2=max(_wander_var(state, state.first_solution, sol),
                                                   state.solution.wander_var_rad2))
    return replace(state, last_solve_s=time_s, last_fit=fit, last_diversity_rad=diversity,
                   last_gate_reason=reason, solution=sol,
                   first_solution=state.first_solution if state.first_solution is not None else sol)


def _heading_now(state: AzimuthState, sol: Solution) -> tuple[float, float]:
    """Heading of the body x axis and its sigma (fit and gyro terms only: no ARW, no field
    model) that ``sol`` gives for the state's current propagated attitude."""
    C = (np.eye(3) - skew(state.G_gyro @ sol.c_gyro)) @ state.C_isf_sf
    hd, hs, _ = af.direction_azimuth_and_sigma(state.params.C_body_from_sensor.T[:, 0], sol.C_nf_af, sol.C_af_isf,
                                               C, state.G_gyro, sol.fit.P_psi_c, 0.0)
    return hd, hs


def _wander_var(state: AzimuthState, ref: Solution, new: Solution) -> float:
    """A's own consistency check (issue 18 item 3): the heading variance its re-solves showed
    beyond what its model allows.

    ``ref`` used a subset of the samples ``new`` uses (nested data), so under the fit's model the
    two estimates of the same heading (same propagated attitude, now) differ by d with
    var(d) = sigma_ref^2 - sigma_new^2 (the later estimate is the earlier one plus independent
    information: the difference of nested linear least-squares estimates). Measured: A's later solutions move
    by more than that (e.g. 1.8 deg in 25 s of level flight while its sigma went 1.63 -> 1.42 deg):
    errors its model does not have (gyro bias instability, Earth rate, an attitude random walk
    fitted as white noise) pull the fit. The excess d^2 - (sigma_ref^2 - sigma_new^2), when
    positive, is an error of at least that variance the sigma did not carry; it is added to the
    output variance (kept for the rest of the flight: the cause does not go away). It cannot
    say which solution is off, so it widens the current one: on stressed flights (gyro bias walk
    25x the consumer grade) the sigma then reached ~2x the error; an error both solutions share
    (the propagation's own drift) it does not see.

    Only a significant excess counts: d^2 > ``params.consistency_chi2`` x var(d) (a chi-square test,
    1 dof). A single d is a draw, so d^2 exceeds var(d) on 32 % of the checks of a consistent fit;
    counting every excess (session 6) widened consistent solutions, and the flight-long maximum
    over ~1 check a second made that the rule: measured on 24 consumer-grade aligned flights of
    bench/azimuth_accuracy (A alone, 30 s), the checks' d^2 / var(d) had mean 1.16 and 5 % above
    3.84 (what a consistent model gives) while 15 of 23 flights were widened. A d with var(d) <= 0
    (the later fit's sigma not below the first's: the linearisation moved) is an excess as it is."""
    hd_ref, hs_ref = _heading_now(state, ref)
    hd_new, hs_new = _heading_now(state, new)
    d = af.wrap_pi(hd_new - hd_ref)
    var_d = max(hs_ref * hs_ref - hs_new * hs_new, 0.0)
    if d * d <= state.params.consistency_chi2 * var_d:
        return 0.0
    return max(0.0, d * d - var_d)


def azimuth_propagate(strapdown: StrapdownState, G_gyro: np.ndarray, C_isf_sf: np.ndarray,
                      gyro_corrected_rad_s: np.ndarray, time_s: float, params: StrapdownParams
                      ) -> tuple[StrapdownState, np.ndarray, np.ndarray]:
    """Step 1 for one sample: C_ISF<-SF by the strapdown of the bias-corrected rate and the
    sensitivity G (3 x 12) to the gyro errors. Returns (strapdown, C_isf_sf, G); C and G are the
    inputs (unchanged) when the sample was not integrated. The compiled twin:
    core/azimuth_propagation.hpp (estimators.core.azimuth_propagate, the same signature)."""
    sd, diag = strapdown_step(strapdown, gyro_corrected_rad_s, time_s, params)
    if not diag.integrated:
        return sd, C_isf_sf, G_gyro
    # G: bias columns -int C dt, T columns int C[:, i] w_j dt (trapezoid)
    C1 = dcm_from_quat(sd.q_ref_from_sensor)
    w0, w1 = strapdown.gyro_prev_rad_s, sd.gyro_prev_rad_s
    h = 0.5 * diag.dt_s
    G = G_gyro.copy()
    G[:, :3] -= h * (C_isf_sf + C1)
    G[:, 3:] += h * (C_isf_sf[:, :, None] * w0 + C1[:, :, None] * w1).reshape(3, 9)
    return sd, C1, G


def azimuth_step(state: AzimuthState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                 mag_gauss: np.ndarray | None, time_s: float, propagate=azimuth_propagate, fit_psi=af.fit_psi,
                 orientation_diversity=af.orientation_diversity_rad, output_numbers=None
                 ) -> tuple[AzimuthState, AzimuthOutput]:
    """One IMU sample in flight (FC time ``time_s``); ``mag_gauss`` None when there is none.
    ``propagate``: step 1's implementation (``azimuth_propagate`` or the core's twin); ``fit_psi`` and
    ``orientation_diversity``: the re-solve's (``azimuth_fit``'s or estimators.core's); ``output_numbers``:
    step 5's (``azimuth_output_numbers``, None, or estimators.core.azimuth_output_numbers)."""
    if state.phase == "prelaunch":
        raise ValueError("azimuth_step before azimuth_launch")
    if state.phase == "failed":
        return state, AzimuthOutput(time_s, "failed", state.reason, False)
    p = state.params
    g = np.asarray(gyro_rad_s, float)
    sd, C_isf_sf, G = propagate(state.strapdown, state.G_gyro, state.C_isf_sf, g - state.gyro_bias_rad_s, time_s,
                                p.strapdown)
    upd = {"strapdown": sd, "G_gyro": G, "C_isf_sf": C_isf_sf}
    u_new = None
    # flight direction from the boost window (inclined case)
    if state.boost is not None and state.u_sf is None:
        a = np.asarray(accel_m_s2, float)
        b = boost_step(state.boost, a, C_isf_sf.T, time_s, p.boost) if a.shape == (3,) else state.boost
        upd["boost"] = b
        if b.done:
            u_new, why = boost_direction(b, p.boost)
            if u_new is None:
                upd["u_reason"] = "flight direction: " + why
                upd["boost"] = None
    # magnetometer sample into the fit
    if mag_gauss is not None:
        h = np.asarray(mag_gauss, float)
        if (h.shape == (3,) and time_s - state.launch_time_s >= p.mag_skip_after_launch_s
                and time_s - state.last_mag_s >= p.mag_decimation_s - 1e-9
                and len(state.samples) < p.max_fit_samples and np.all(np.isfinite(h))):
            upd["samples"] = state.samples + (MagRecord(float(time_s), h.copy(), C_isf_sf.T.copy(), G.copy()),)
            upd["last_mag_s"] = float(time_s)
    st = fast_replace(state, **upd)  # per sample: AzimuthState has no __post_init__ (records.fast_replace)
    if u_new is not None:
        st = _with_checks(st, u_new)
    period = p.resolve_period_s if st.solution is not None else p.resolve_period_unsolved_s
    if time_s - st.last_solve_s >= period and len(st.samples) > 0:
        st = _solve(st, time_s, fit_psi, orientation_diversity)
    return st, _output(st, C_isf_sf, time_s, output_numbers)


def azimuth_status(st: AzimuthState) -> str:
    """The status ``azimuth_step`` gives for ``st`` (in flight or failed): it changes only when a
    solve or a solve's result changes the state, never by a sample's propagation or storage."""
    if st.phase == "failed":
        return "failed"
    if st.solution is None:
        return "collecting" if st.last_fit is None else "withheld"
    return "solved" if st.last_gate_reason == "" else "holding"


def azimuth_output(st: AzimuthState, time_s: float, output_numbers=None) -> AzimuthOutput:
    """The output ``azimuth_step`` returned with ``st`` at its last sample ``time_s`` (computed
    when asked: the Pipeline's hot path steps A without building an output per sample)."""
    if st.phase == "failed":
        return AzimuthOutput(time_s, "failed", st.reason, False)
    return _output(st, st.C_isf_sf, time_s, output_numbers)


def _output(st: AzimuthState, C_isf_sf: np.ndarray, time_s: float, output_numbers=None) -> AzimuthOutput:
    """``output_numbers``: step 5's numbers (``azimuth_output_numbers`` or the core's twin,
    estimators.core.azimuth_output_numbers: the same signature)."""
    nums = (output_numbers or azimuth_output_numbers)(st, st.G_gyro, C_isf_sf, time_s)
    return output_from_numbers(st, time_s, len(st.samples), nums)


def azimuth_output_numbers(st: AzimuthState, G_gyro: np.ndarray, C_isf_sf: np.ndarray, time_s: float) -> tuple:
    """Step 5's numbers for the propagated G and C_ISF<-SF at ``time_s``: (roll, pitch, q_nav_from_body,
    heading, heading_sigma, azimuth, azimuth_sigma, launch_azimuth), NaN where there is none (no
    solution: the attitude only; no flight direction: no azimuth). The compiled twin:
    core/azimuth_output.hpp."""
    p = st.params
    sol = st.solution
    C_sf_body = p.C_body_from_sensor.T
    if sol is not None:   # apply the estimated errors: C_true = (I - [err]x) C_propagated
        C_isf_sf = (np.eye(3) - skew(G_gyro @ sol.c_gyro)) @ C_isf_sf
        C_nf_sf = sol.C_nf_af @ sol.C_af_isf @ C_isf_sf
    else:
        C_nf_sf = st.C_isf_af.T @ C_isf_sf
    C_nf_body = C_nf_sf @ C_sf_body
    roll, pitch, _ = euler_from_dcm(C_nf_body)
    q = quat_from_dcm(C_nf_body)
    nan = math.nan
    if sol is None:
        return roll, pitch, q, nan, nan, nan, nan, nan
    arw_var = p.gyro_arw_rad_sqrt_s ** 2 * max(time_s - st.launch_time_s, 0.0)
    hd, hs, _ = af.direction_azimuth_and_sigma(C_sf_body[:, 0], sol.C_nf_af, sol.C_af_isf, C_isf_sf, G_gyro,
                                               sol.fit.P_psi_c, arw_var)
    fm2 = p.field_model_sigma_rad ** 2 + sol.wander_var_rad2
    # in-run gyro bias (issue 18 item 3): the fit's c_gyro is one bias change over its samples; after
    # its last sample (max_fit_samples reached, or the magnetometer withheld) nothing measures the
    # heading and the bias is free to move again by its prior sigma: (sigma_b (t - t_last))^2 of the
    # heading and azimuth variance (they turn with the gyros; psi_s, fixed at launch, does not)
    gap = time_s - sol.last_sample_s if math.isfinite(sol.last_sample_s) else 0.0
    run_var = (p.gyro_bias_sigma_rad_s * max(gap, 0.0)) ** 2
    hs = math.sqrt(hs ** 2 + fm2 + run_var)
    if st.u_sf is None:
        return roll, pitch, q, hd, hs, nan, nan, nan
    if np.array_equal(st.u_sf, C_sf_body[:, 0]):   # aligned case: u is the body x axis
        az, az_s = hd, hs
    else:
        u = st.u_sf
        if st.du_dbeta_sf is not None:   # the measured up carries the estimated tilt error too
            u = u - st.du_dbeta_sf @ sol.fit.c_hat[N_GYRO_CONSIDER:N_GYRO_CONSIDER + 2]
        az, az_s, _ = af.direction_azimuth_and_sigma(u, sol.C_nf_af, sol.C_af_isf, C_isf_sf, G_gyro,
                                                     sol.fit.P_psi_c, arw_var, st.du_dbeta_sf)
        az_s = math.sqrt(az_s ** 2 + fm2 + run_var)
    az0 = af.azimuth_of(sol.C_nf_af @ sol.C_af_isf @ st.u_sf)   # C_ISF<-SF = I at launch
    return roll, pitch, q, hd, hs, az, az_s, az0


def output_from_numbers(st: AzimuthState, time_s: float, n_samples: int, nums: tuple) -> AzimuthOutput:
    """The AzimuthOutput of ``st`` (in flight, not failed) with step 5's ``nums`` (``azimuth_output_numbers``'s
    tuple) and ``n_samples`` samples kept: the status, the reason and the flags, the diagnostics."""
    p = st.params
    sol = st.solution
    roll, pitch, q, hd, hs, az, az_s, az0 = nums
    fit_last = st.last_fit
    diag = dict(n_samples=n_samples, diversity_rad=st.last_diversity_rad,
                condition_number=fit_last.condition_number if fit_last is not None else math.nan,
                normalised_residual=fit_last.s2 if fit_last is not None else math.nan,
                u_sf=st.u_sf, cross_check_rad=st.cross_check_rad, elevation_check_rad=st.elevation_check_rad)
    flags = []
    if math.isfinite(st.cross_check_rad) and st.cross_check_rad > p.cross_check_max_rad:
        flags.append(f"flight direction cross-check {math.degrees(st.cross_check_rad):.1f} deg")
    if math.isfinite(st.elevation_check_rad) and abs(st.elevation_check_rad) > p.cross_check_max_rad:
        flags.append(f"launch elevation differs from the configured one by "
                     f"{math.degrees(st.elevation_check_rad):.1f} deg")
    status = azimuth_status(st)
    if sol is None:
        reason = "; ".join([st.last_gate_reason or "no magnetometer samples yet"] + flags)
        return AzimuthOutput(time_s, status, reason, False, roll_rad=roll, pitch_rad=pitch,
                             q_nav_from_body=q, **diag)
    if status == "holding":
        flags.insert(0, "holding last solution: " + st.last_gate_reason)
    fm2 = p.field_model_sigma_rad ** 2 + sol.wander_var_rad2
    out = dict(heading_rad=hd, heading_sigma_rad=hs, roll_rad=roll, pitch_rad=pitch,
               q_nav_from_body=q, psi_s_rad=sol.fit.psi_rad,
               psi_s_sigma_rad=math.sqrt(sol.psi_sigma_rad ** 2 + fm2),
               distortion_A=sol.fit.A, distortion_b_gauss=sol.fit.b_gauss)
    if st.u_sf is None:
        return AzimuthOutput(time_s, status, "; ".join([st.u_reason] + flags), False, **out, **diag)
    return AzimuthOutput(time_s, status, "; ".join(flags), True, azimuth_rad=az,
                         azimuth_sigma_rad=az_s, launch_azimuth_rad=az0, **out, **diag)


def output_for_publishing(out: AzimuthOutput) -> dict:
    """The output with degrees and units in the keys, for the publishers (MAVLink/Zenoh edges).
    NaN where not available; ``valid`` says whether azimuth/heading may be used."""
    def deg(x: float) -> float:
        return math.degrees(x) if x is not None and math.isfinite(x) else math.nan
    return {
        "time_s": float(out.time_s), "status": out.status, "reason": out.reason, "valid": out.valid,
        "azimuth_deg": deg(out.azimuth_rad), "azimuth_sigma_deg": deg(out.azimuth_sigma_rad),
        "launch_azimuth_deg": deg(out.launch_azimuth_rad),
        "heading_deg": deg(out.heading_rad), "heading_sigma_deg": deg(out.heading_sigma_rad),
        "roll_deg": deg(out.roll_rad), "pitch_deg": deg(out.pitch_rad),
        "psi_s_deg": deg(out.psi_s_rad), "psi_s_sigma_deg": deg(out.psi_s_sigma_rad),
        "n_samples": int(out.n_samples), "orientation_diversity_deg": deg(out.diversity_rad),
        "condition_number": float(out.condition_number), "normalised_residual": float(out.normalised_residual),
        "flight_direction_cross_check_deg": deg(out.cross_check_rad),
        "launch_elevation_check_deg": deg(out.elevation_check_rad),
    }


class AzimuthEstimator:
    """Thin holder of an ``AzimuthState`` for callers that prefer an object (same results)."""

    def __init__(self, params: AzimuthParams):
        self.state = azimuth_init(params)

    def prelaunch(self, gyro_rad_s, accel_m_s2, time_s) -> None:
        self.state = azimuth_prelaunch_step(self.state, gyro_rad_s, accel_m_s2, time_s)

    def launch(self, launch_time_s) -> str:
        self.state, reason = azimuth_launch(self.state, launch_time_s)
        return reason

    def step(self, gyro_rad_s, accel_m_s2, mag_gauss, time_s) -> AzimuthOutput:
        self.state, out = azimuth_step(self.state, gyro_rad_s, accel_m_s2, mag_gauss, time_s)
        return out


# --- solving outside the per-sample step (the daemon runs the fit in a worker process) -------

def azimuth_solve(state: AzimuthState, time_s: float, fit_psi=af.fit_psi,
                  orientation_diversity=af.orientation_diversity_rad) -> AzimuthState:
    """Re-solve psi_s (and the distortions) with the samples kept so far and gate the result.

    ``azimuth_step`` does this itself every ``resolve_period_s``; a caller that sets that period
    to infinity may instead run this pure function on a snapshot of the state elsewhere (a worker
    process) and merge the result with ``azimuth_apply_solve``. ``fit_psi``, ``orientation_diversity``:
    the solve's implementations (``azimuth_fit``'s or the core's twins in estimators.core)."""
    return _solve(state, time_s, fit_psi, orientation_diversity)


SOLVE_FIELDS = ("last_solve_s", "last_fit", "last_diversity_rad", "last_gate_reason", "solution", "first_solution")
"""The fields ``azimuth_solve`` writes; nothing else of the state changes in a solve."""


def azimuth_solve_result(solved: AzimuthState) -> dict:
    """What a solve produced (small and picklable: no sample records)."""
    return {k: getattr(solved, k) for k in SOLVE_FIELDS}


def azimuth_apply_solve(state: AzimuthState, result: dict) -> AzimuthState:
    """Merge a solve computed on an older snapshot into the current state; the samples that
    arrived meanwhile are kept for the next solve."""
    return replace(state, **{k: result[k] for k in SOLVE_FIELDS})
