"""Magnetic disturbances while the vehicle moves: a magnet attached (a new hard iron, learnt again)
and a magnet nearby (the field departs from the recent undisturbed one: rejected). Issue 18 item 4.

Two questions, answered from different evidence so the one cannot be mistaken for the other:

1. **Is the hard iron still what we think? (body-fixed disturbance)** The Earth's field is fixed in
   the navigation frame, so between two magnetometer samples the body-frame field only turns with
   the body: with C_10 = C_BP(t1) C_PB(t0) (the attitude filter's attitude, any P azimuth drift
   over the pair is negligible) and the hard iron b,

       m1 - b = C_10 (m0 - b)   =>   z = m1 - C_10 m0 = (I - C_10) b + e,

   linear in b and free of the heading, the field model and the declination. A 3-state Kalman filter
   (b random walk) fuses one such pair whenever the body has turned ``pair_min_angle_rad`` since
   the pair's first sample (b along the turn axis is unobservable from one pair; turns about other
   axes supply it). e per axis: noise of both samples, the soft iron the pair leaves (an
   uncompensated s_s ~1 % of |m| per sample, the pair's difference of two such errors) and the
   gyro-integrated turn's error (``turn_error_fraction`` of the angle, times |m|):
       R = (2 s_m^2 + 2 (s_s |m|)^2 + (f_turn angle |m|)^2) I.
   A magnet ATTACHED makes the pairs inconsistent (NIS > ``pair_gate_chi2``) while the body turns:
   after ``relearn_after_pairs`` consecutive such pairs the hard-iron covariance is widened to
   ``relearn_sigma_gauss`` (a new hard iron is learnt, not rejected forever) and the magnetometer is
   "re-learning its hard iron" until every axis' sigma is below ``learnt_sigma_gauss`` and the last
   pair was consistent. A magnet NEARBY that stays put adds a field fixed in the navigation frame:
   the pairs stay consistent and the hard iron is left alone.

2. **Is the field still the Earth's? (navigation-frame disturbance, VQF-style)** The corrected field
   m_c = m - b levelled with the full attitude, m_P = C_PB m_c, gives a norm |m_c| and a dip
   atan2(m_P_z, |m_P_xy|) that do not depend on the heading. Both are low-passed
   (``current_tau_s``) and compared with the RECENT UNDISTURBED field (norm_ref, dip_ref, learnt
   with ``reference_tau_s`` only while undisturbed): | |m_c| / norm_ref - 1 | <= ``norm_tolerance``
   and |dip - dip_ref| <= ``dip_tolerance_rad`` (what an attitude-dependent soft iron, the hard-iron
   residual and a tilt error of a degree or two leave). Disturbed: rejected with the figures; usable
   again after ``min_undisturbed_s`` inside the tolerances. The reference starts from the first
   samples that agree with the MODEL (``model_norm_gauss``, ``model_dip_rad`` within
   ``model_norm_tolerance`` / ``model_dip_tolerance_rad``), and a new field is accepted as the
   reference only when it agrees with the model as well and has been steady
   (``new_field_after_s`` of samples within the tolerances of each other while the body turned:
   e.g. the vehicle moved into a building), never just because it lasted: a magnet lying beside
   the vehicle for minutes is still not the Earth's field.

A repeat of the previous vector is the same sample handed on again (RAW_IMU carries the compass's
latest reading at the IMU rate, a log reader holds its MAG onto the IMU samples; a live sensor's
noise makes two fresh readings differ), not a new one: it is dated at its first appearance, so it
neither forms a pair nor moves the low-passed field, and its verdict is the last fresh sample's.
Paired with the attitude of a later IMU sample, a reading held for up to a compass period is turned
by rate x age: in ArduPlane SITL (a 10 Hz MAG held onto a 100 Hz IMU, 84 % repeats) every banked
turn's pair then failed the NIS gate (|nu| 0.05-0.25 G) and the hard iron was "re-learnt" three
times on a clean magnetometer (the heading coasted on the gyros ~85 s); with repeats skipped, 0.

Pure: ``mag_disturbance_step(state, time_s, mag_body_gauss, q_P_from_body, params) ->
(state, verdict)``; ``verdict.mag_corrected_gauss`` is m - b (None while not usable).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.rotations import dcm_from_quat
from estimators.mag_usability import field_norm_dip


@dataclass(frozen=True)
class MagDisturbanceParams:
    model_norm_gauss: float
    """|B| of the field model at the site (gauss)."""
    model_dip_rad: float
    """Dip of the field model, positive down (rad)."""
    model_norm_tolerance: float = 0.25
    model_dip_tolerance_rad: float = math.radians(12.0)
    """What the reference may differ from the model (the same bounds as estimators/mag_usability)."""
    mag_noise_gauss: float = 0.003
    """Per-sample magnetometer noise (gauss, per axis)."""
    hard_iron_prior_sigma_gauss: float = 0.016
    """Per-axis sigma of the hard iron at start (0 mean): what a compass calibration leaves (as
    polar_heading's ``uncalibrated_hard_iron_gauss``; the daemon passes its config value)."""
    hard_iron_walk_gauss_rt_s: float = 1e-5
    """Random walk of the hard iron (gauss/sqrt(s)): slow thermal drift."""
    soft_iron_fraction: float = 0.01
    """Per-axis soft iron left uncompensated, as a fraction of |m| (in each pair's error)."""
    turn_error_fraction: float = 0.005
    """Error of the gyro-integrated turn between a pair's samples, a fraction of its angle (scale
    factor and misalignment of a consumer gyro, 3e-3 each)."""
    pair_min_angle_rad: float = math.radians(30.0)
    """A pair is formed once the body has turned this much since its first sample (|I - C_10| =
    2 sin(angle/2): 0.52 at 30 deg, so one pair resolves b to ~2 sigma of its error)."""
    pair_max_interval_s: float = 2.0
    """... within this time; otherwise the first sample is replaced (no pair: too little turn)."""
    pair_gate_chi2: float = 16.27
    """NIS (3 dof, 99.9 %) above which a pair is inconsistent with the hard iron."""
    relearn_after_pairs: int = 3
    """Consecutive inconsistent pairs that mean the hard iron changed (a magnet attached)."""
    relearn_sigma_gauss: float = 0.5
    """Per-axis sigma the hard iron is widened to when it changed (a magnet can be anything)."""
    learnt_sigma_gauss: float = 0.05
    """A re-learnt hard iron is used again once every axis' sigma is below this (10 % of a 0.5 G
    field; what is left widens the published heading sigma: the caller's consider term)."""
    current_tau_s: float = 0.1
    """Low-pass of the current norm and dip (s): single noisy samples do not trip the test."""
    reference_tau_s: float = 20.0
    """Time constant of the recent-undisturbed reference (s)."""
    norm_tolerance: float = 0.10
    dip_tolerance_rad: float = math.radians(8.0)
    min_undisturbed_s: float = 0.5
    """Inside the tolerances this long before the field is used again."""
    new_field_after_s: float = 20.0
    """A steady new field that agrees with the model becomes the reference after this long (s) of
    samples with the body turning (``new_field_min_rate_rad_s``)."""
    new_field_min_rate_rad_s: float = math.radians(10.0)

    def __post_init__(self) -> None:
        for name, v in self.__dict__.items():
            if name == "model_dip_rad":
                if not (math.isfinite(v) and abs(v) <= math.pi / 2):
                    raise ValueError(f"model_dip_rad must be in [-pi/2, pi/2], got {v!r}")
            elif name == "relearn_after_pairs":
                if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                    raise ValueError(f"relearn_after_pairs must be an int >= 1, got {v!r}")
            elif not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


def mag_disturbance_params_for_field(field_ned_gauss, **kw) -> MagDisturbanceParams:
    norm, dip = field_norm_dip(field_ned_gauss)
    return MagDisturbanceParams(model_norm_gauss=norm, model_dip_rad=dip, **kw)


@dataclass(frozen=True)
class MagDisturbanceState:
    hard_iron_gauss: np.ndarray = field(default_factory=lambda: np.zeros(3))
    P_hard_iron: np.ndarray | None = None
    """3x3 covariance (gauss^2); None before the first sample (then the prior)."""
    time_s: float | None = None
    anchor: tuple | None = None
    """(time_s, m_body, q_P_from_body) of a pair's first sample."""
    bad_pairs: int = 0
    relearning: bool = False
    last_pair_ok: bool = True
    n_pairs: int = 0
    n_relearns: int = 0
    norm_lp: float | None = None
    dip_lp: float | None = None
    norm_ref: float | None = None
    dip_ref: float | None = None
    undisturbed_s: float = 0.0
    disturbed: bool = True
    """No reference yet counts as disturbed (not judged)."""
    candidate: tuple | None = None
    """(norm, dip, steady seconds with turning) of a new field."""
    reason: str = "no magnetometer sample yet"
    m_last: np.ndarray | None = None
    """The last new sample (gauss, body); a repeat of it is not a new sample (module docstring)."""


@dataclass(frozen=True)
class MagDisturbanceVerdict:
    usable: bool
    reason: str
    """'' when usable; else one line: 're-learning its hard iron ...' or 'magnetic disturbance: ...'."""
    changed: bool
    """``usable`` or the kind of reason differs from the previous verdict (one event per change)."""
    mag_corrected_gauss: np.ndarray | None
    """m - b (body axes, gauss) when usable, else None."""
    hard_iron_gauss: np.ndarray
    hard_iron_sigma_gauss: float
    """Largest per-axis sigma of the hard iron (gauss)."""
    norm_ratio: float = math.nan
    """Low-passed |m - b| over the reference norm."""
    dip_diff_rad: float = math.nan
    relearned: bool = False
    """The hard iron was found changed at this sample (covariance widened)."""


def _lp(prev: float | None, x: float, dt: float, tau: float) -> float:
    if prev is None or dt <= 0.0:
        return x
    return prev + (x - prev) * min(1.0, dt / tau)


def _kind(reason: str) -> str:
    return reason.split(":")[0].split(" (")[0]


def mag_disturbance_step(state: MagDisturbanceState, time_s: float, mag_body_gauss, q_P_from_body,
                         params: MagDisturbanceParams) -> tuple[MagDisturbanceState, MagDisturbanceVerdict]:
    """One magnetometer sample (body axes, gauss) with the attitude filter's attitude in its
    platform frame. Non-finite input is the caller's to reject (ValueError)."""
    p = params
    m = np.asarray(mag_body_gauss, float)
    q = np.asarray(q_P_from_body, float)
    if m.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(m)) and np.all(np.isfinite(q))
                                                  and math.isfinite(time_s)):
        raise ValueError(f"mag_body_gauss (3), q_P_from_body (4) and time_s must be finite, got "
                         f"{mag_body_gauss!r}, {q_P_from_body!r}, {time_s!r}")
    t = float(time_s)
    dt = 0.0 if state.time_s is None else t - state.time_s
    if dt < 0.0:
        raise ValueError(f"time_s must not decrease ({state.time_s} -> {t})")
    st = state
    P = st.P_hard_iron if st.P_hard_iron is not None else np.eye(3) * p.hard_iron_prior_sigma_gauss ** 2
    b = st.hard_iron_gauss
    if st.m_last is not None and np.array_equal(m, st.m_last):
        # a held repeat (module docstring): nothing new; the last fresh sample's verdict
        usable = not st.reason
        judged = not st.relearning and st.norm_ref is not None
        return st, MagDisturbanceVerdict(usable, st.reason, False, m - b if usable else None, b.copy(),
                                         float(math.sqrt(max(np.max(np.diag(P)), 0.0))),
                                         st.norm_lp / st.norm_ref if judged else math.nan,
                                         st.dip_lp - st.dip_ref if judged else math.nan, False)
    C_PB = dcm_from_quat(q)
    relearned = False

    # 1. the hard iron, from pairs of samples the body turned between ------------------------------
    P = P + np.eye(3) * p.hard_iron_walk_gauss_rt_s ** 2 * dt
    anchor, bad, relearning, last_ok, n_pairs, n_rel = (st.anchor, st.bad_pairs, st.relearning,
                                                        st.last_pair_ok, st.n_pairs, st.n_relearns)
    turn_rate = 0.0
    if anchor is None:
        anchor = (t, m, q)
    else:
        C_10 = C_PB.T @ dcm_from_quat(anchor[2])
        angle = math.acos(max(-1.0, min(1.0, (float(np.trace(C_10)) - 1.0) / 2.0)))
        if t > anchor[0]:
            turn_rate = angle / (t - anchor[0])
        if angle >= p.pair_min_angle_rad:
            Hm = np.eye(3) - C_10
            z = m - C_10 @ anchor[1]
            mm = float(np.linalg.norm(m))
            r = (2.0 * p.mag_noise_gauss ** 2 + 2.0 * (p.soft_iron_fraction * mm) ** 2
                 + (p.turn_error_fraction * angle * mm) ** 2)
            nu = z - Hm @ b
            S = Hm @ P @ Hm.T + np.eye(3) * r
            nis = float(nu @ np.linalg.solve(S, nu))
            n_pairs += 1
            last_ok = nis <= p.pair_gate_chi2
            bad = 0 if last_ok else bad + 1
            if bad >= p.relearn_after_pairs:
                # the hard iron changed (a magnet attached): widen it and learn it again
                P = np.eye(3) * p.relearn_sigma_gauss ** 2
                bad, relearning, relearned, n_rel = 0, True, True, n_rel + 1
                S = Hm @ P @ Hm.T + np.eye(3) * r
                last_ok = False
            if last_ok or relearning:
                K = P @ Hm.T @ np.linalg.inv(S)
                b = b + K @ nu
                I_KH = np.eye(3) - K @ Hm
                P = I_KH @ P @ I_KH.T + K @ K.T * r
                P = 0.5 * (P + P.T)
            anchor = (t, m, q)
        elif t - anchor[0] > p.pair_max_interval_s:
            anchor = (t, m, q)
    sigma_b = float(math.sqrt(max(np.max(np.diag(P)), 0.0)))
    if relearning and sigma_b < p.learnt_sigma_gauss and last_ok:
        relearning = False

    # 2. the field against the recent undisturbed one (and the model) ------------------------------
    mc = m - b
    norm = float(np.linalg.norm(mc))
    mp = C_PB @ mc
    dip = math.atan2(float(mp[2]), math.hypot(float(mp[0]), float(mp[1])))
    norm_lp = _lp(st.norm_lp, norm, dt, p.current_tau_s)
    dip_lp = _lp(st.dip_lp, dip, dt, p.current_tau_s)
    model_ok = (abs(norm_lp / p.model_norm_gauss - 1.0) <= p.model_norm_tolerance
                and abs(dip_lp - p.model_dip_rad) <= p.model_dip_tolerance_rad)
    norm_ref, dip_ref, cand = st.norm_ref, st.dip_ref, st.candidate
    undist, disturbed = st.undisturbed_s, st.disturbed
    ratio, ddip = math.nan, math.nan
    if relearning:
        undist, disturbed = 0.0, True
    elif norm_ref is None:
        if model_ok:   # the first reference: samples that agree with the model
            norm_ref, dip_ref, disturbed, undist = norm_lp, dip_lp, False, p.min_undisturbed_s
    else:
        ratio, ddip = norm_lp / norm_ref, dip_lp - dip_ref
        inside = abs(ratio - 1.0) <= p.norm_tolerance and abs(ddip) <= p.dip_tolerance_rad
        if inside:
            undist += dt
            if undist >= p.min_undisturbed_s:
                disturbed = False
                k = min(1.0, dt / p.reference_tau_s)
                norm_ref += (norm_lp - norm_ref) * k
                dip_ref += (dip_lp - dip_ref) * k
            cand = None
        else:
            undist, disturbed = 0.0, True
            # a new steady field that agrees with the model may become the reference
            if cand is not None and abs(norm_lp / cand[0] - 1.0) <= p.norm_tolerance \
                    and abs(dip_lp - cand[1]) <= p.dip_tolerance_rad:
                k = min(1.0, dt / p.reference_tau_s)
                cand = (cand[0] + (norm_lp - cand[0]) * k, cand[1] + (dip_lp - cand[1]) * k,
                        cand[2] + (dt if turn_rate >= p.new_field_min_rate_rad_s else 0.0))
                if cand[2] >= p.new_field_after_s and model_ok:
                    norm_ref, dip_ref, cand, disturbed, undist = cand[0], cand[1], None, False, p.min_undisturbed_s
            else:
                cand = (norm_lp, dip_lp, 0.0)

    if relearning:
        reason = (f"re-learning its hard iron (a magnet attached?): sigma {sigma_b:.3f} G > "
                  f"{p.learnt_sigma_gauss:.3f} G or its pairs still inconsistent")
    elif norm_ref is None:
        reason = (f"magnetic disturbance: field {norm_lp:.3f} G, dip {math.degrees(dip_lp):.1f} deg not the "
                  f"model's ({p.model_norm_gauss:.3f} G, {math.degrees(p.model_dip_rad):.1f} deg)")
    elif disturbed:
        reason = (f"magnetic disturbance: field {norm_lp:.3f} G, dip {math.degrees(dip_lp):.1f} deg vs the recent "
                  f"undisturbed {norm_ref:.3f} G, {math.degrees(dip_ref):.1f} deg (tolerance "
                  f"{100 * p.norm_tolerance:.0f} %, {math.degrees(p.dip_tolerance_rad):.0f} deg)")
    else:
        reason = ""
    usable = not reason
    changed = usable != (not st.reason) or _kind(reason) != _kind(st.reason)
    new = replace(st, hard_iron_gauss=b, P_hard_iron=P, time_s=t, anchor=anchor, bad_pairs=bad,
                  relearning=relearning, last_pair_ok=last_ok, n_pairs=n_pairs, n_relearns=n_rel,
                  norm_lp=norm_lp, dip_lp=dip_lp, norm_ref=norm_ref, dip_ref=dip_ref, undisturbed_s=undist,
                  disturbed=disturbed, candidate=cand, reason=reason, m_last=m.copy())
    return new, MagDisturbanceVerdict(usable, reason, changed, mc if usable else None, b.copy(), sigma_b,
                                      ratio, ddip, relearned)
