"""Magnetometer usability: is this magnetometer fit to give a heading at all? (Issue 14/18.)

A per-sample disturbance gate (ahrs_kf2's field-norm test, polar_heading's innovation gate)
rejects single samples; this module judges the SENSOR over a window and says in one named reason
why it must not be used, so the heading filters coast on the gyros (their sigma grows) instead of
fusing a field that is not the Earth's:

- ``field norm``   median |m| over ``window_s`` against the model's |B|:
                   | |m| / |B| - 1 | > ``norm_tolerance_fraction``. An uncalibrated airframe's
                   hard iron (per-axis 1-sigma ~0.013 G: 3 sigma on three axes ~0.07 G, 14 % of
                   0.5 G) plus 1-3 % soft iron and the field model's error stay inside 0.25;
                   a sensor reading 0.87 G against 0.5 G (a motor's field, a wrong scale, an
                   axis mix-up) does not.
- ``dip``          median dip of the field levelled with the caller's roll/pitch,
                   atan2(m_down, |m_horizontal|), against the model's dip, beyond
                   ``dip_tolerance_rad`` (hard iron 0.07 G on 0.5 G tilts the field by up to
                   ~8 deg; a few deg of tilt error add to it). A wrong axis mapping or a strong
                   local source passes the norm test but not this one. Skipped when the caller
                   has no roll/pitch.
- ``frozen``       the vector identical for ``frozen_s`` WHILE the body turned enough that a live
                   sensor must have changed: the change the gyros predict, integral |m x w| dt
                   (dm/dt = -w x m for a fixed field), exceeds ``min_expected_change_gauss``. At
                   rest a quiet or noise-free sensor (ArduPilot's 1 mG RAW_IMU resolution, SITL's
                   compass without SIM_MAG_RND) repeats its reading: that is no fault.
- ``saturated``    one axis stuck at the same value for ``frozen_s`` while the gyros predict a
                   change of that axis (integral |(m x w)_i| dt > ``min_expected_change_gauss``; a
                   yaw turn leaves m_z unchanged) and the others change (a clipped axis at its full
                   scale), or |axis| >= ``full_scale_gauss`` when known.
- ``too slow``     fewer than ``min_rate_hz`` new samples per second over ``rate_window_s`` while
                   the body turned (>= ``motion_step_rad`` within that window): repeats at rest
                   cannot tell a slow sensor from a quiet one.
                   Decided: 1 Hz. A 2 Hz magnetometer (PX4's default logging) is slow but usable
                   for a heading filter: between samples the gyros carry the heading (0.01-0.2 deg/s
                   of bias), and the heading filter counts its correlated measurement errors once per
                   30 s anyway (polar_heading ``mag_error_tau_s``), so 2 Hz loses almost nothing;
                   below 1 Hz a turn between samples is only seen by the gyros for seconds and the
                   time alignment of a held sample is as coarse.

A repeat of the previous vector (the same sample held onto several IMU samples by the link or a
log reader) is not a new sample: only changes count for the rate and frozen tests.

Pure: ``mag_usability_step(state, time_s, mag_body_gauss, roll_rad, pitch_rad, params,
gyro_body_rad_s) -> (state, verdict)`` (gyro None: motion unknown, the frozen, stuck-axis and rate
tests are not judged); ``mag_usability_stale(state, time_s, params)`` when no sample came at all.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class MagUsabilityParams:
    field_norm_gauss: float
    """|B| of the model field at the site (gauss)."""
    field_dip_rad: float
    """Dip (inclination) of the model field, positive down (rad)."""
    norm_tolerance_fraction: float = 0.25
    dip_tolerance_rad: float = math.radians(12.0)
    window_s: float = 2.0
    """Norm and dip are judged on their median over this window (single disturbed samples are the
    per-sample gates' business)."""
    frozen_s: float = 3.0
    min_rate_hz: float = 1.0
    rate_window_s: float = 5.0
    full_scale_gauss: float | None = None
    """The sensor's full scale when known (|axis| >= this: saturated); None: only the stuck-axis test."""
    min_expected_change_gauss: float = 0.03
    """A reading (an axis) that stays identical while the gyros predict this much change is frozen
    (stuck): 0.03 G is ~3.5 deg of turn on a 0.5 G field, 30x ArduPilot's 1 mG resolution."""
    motion_step_rad: float = math.radians(5.0)
    """The rate test is judged only when the body turned this much within ``rate_window_s``."""
    motion_rate_floor_rad_s: float = math.radians(3.0)
    """Only rates above this count as turning: an uncalibrated MEMS gyro bias (0.1-1 deg/s) and its
    noise, integrated over minutes at rest, must not predict a change of a still vehicle's field."""

    def __post_init__(self) -> None:
        for name in ("field_norm_gauss", "norm_tolerance_fraction", "dip_tolerance_rad", "window_s",
                     "frozen_s", "min_rate_hz", "rate_window_s", "min_expected_change_gauss", "motion_step_rad",
                     "motion_rate_floor_rad_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if not (math.isfinite(self.field_dip_rad) and abs(self.field_dip_rad) <= math.pi / 2):
            raise ValueError(f"field_dip_rad must be in [-pi/2, pi/2], got {self.field_dip_rad!r}")
        if self.full_scale_gauss is not None and not (math.isfinite(self.full_scale_gauss)
                                                      and self.full_scale_gauss > 0.0):
            raise ValueError(f"full_scale_gauss must be finite and > 0 or None, got {self.full_scale_gauss!r}")


def field_norm_dip(field_ned_gauss) -> tuple[float, float]:
    """(|B| gauss, dip rad, positive down) of a field vector in NED."""
    b = np.asarray(field_ned_gauss, float)
    return float(np.linalg.norm(b)), math.atan2(float(b[2]), math.hypot(float(b[0]), float(b[1])))


def mag_usability_params_for_field(field_ned_gauss, **kw) -> MagUsabilityParams:
    """Params from the model field (NED, gauss)."""
    norm, dip = field_norm_dip(field_ned_gauss)
    return MagUsabilityParams(field_norm_gauss=norm, field_dip_rad=dip, **kw)


@dataclass(frozen=True)
class MagUsabilityState:
    last_mag: tuple | None = None
    """The last vector seen (to tell a new sample from a held repeat)."""
    changed_s: float | None = None
    """Time of the last new sample."""
    axis_changed_s: tuple = (None, None, None)
    """Per axis: time its value last changed."""
    new_times: tuple = ()
    """Times of the new samples within rate_window_s."""
    window: tuple = ()
    """(time_s, norm_ratio, dip_rad or nan) of the new samples within window_s."""
    first_s: float | None = None
    last_call_s: float | None = None
    expected_change_gauss: float = 0.0
    """The change the gyros predict for the vector since it last changed (integral |m x w| dt)."""
    axis_expected_change_gauss: tuple = (0.0, 0.0, 0.0)
    """Per axis, since that axis last changed (integral |(m x w)_i| dt)."""
    turned_rad: float = 0.0
    """Total turn angle (integral |w| dt) and the times it crossed successive motion steps."""
    motion_marks: tuple = ()
    usable: bool | None = None
    reason: str = "no magnetometer sample yet"


@dataclass(frozen=True)
class MagVerdict:
    usable: bool
    reason: str
    """'' when usable, else one line naming the test and the figures ('field norm 0.87 G vs ...')."""
    new_sample: bool
    """This call carried a new sample (not a repeat of the held one)."""
    changed: bool
    """The verdict differs from the previous one (for one event per change; never while the first
    window of samples is being checked)."""
    norm_ratio: float = math.nan
    """Window median of |m| / |B_model|."""
    dip_rad: float = math.nan
    """Window median of the measured dip."""
    rate_hz: float = math.nan


def _median(v) -> float:
    v = [x for x in v if math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def _motion(state: MagUsabilityState, t: float, m: np.ndarray, gyro_body_rad_s, params: MagUsabilityParams):
    """The change the gyros predict for the field since the previous call, dm = -(w x m) dt (a fixed
    Earth field seen from a turning body), added to the running totals; and the turn angle with its
    motion marks. An interval longer than ``rate_window_s`` (a gap) adds nothing."""
    exp_all, exp_axis = state.expected_change_gauss, state.axis_expected_change_gauss
    turned, marks = state.turned_rad, state.motion_marks
    if gyro_body_rad_s is None or state.last_call_s is None:
        return exp_all, exp_axis, turned, marks
    w = np.asarray(gyro_body_rad_s, float)
    dt = t - state.last_call_s
    if w.shape != (3,):
        return exp_all, exp_axis, turned, marks
    # 3-vectors on Python floats (np.cross / np.linalg.norm cost ~10 us a call: replay speed)
    w0, w1, w2 = float(w[0]), float(w[1]), float(w[2])
    wn = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if math.isfinite(wn) and 0.0 < dt <= params.rate_window_s and wn >= params.motion_rate_floor_rad_s:
        m0, m1, m2 = float(m[0]), float(m[1]), float(m[2])
        dm = (abs(m1 * w2 - m2 * w1) * dt, abs(m2 * w0 - m0 * w2) * dt, abs(m0 * w1 - m1 * w0) * dt)
        exp_all += math.sqrt(dm[0] * dm[0] + dm[1] * dm[1] + dm[2] * dm[2])
        exp_axis = (exp_axis[0] + dm[0], exp_axis[1] + dm[1], exp_axis[2] + dm[2])
        step = wn * dt
        if math.floor((turned + step) / params.motion_step_rad) > math.floor(turned / params.motion_step_rad):
            marks = tuple(x for x in marks if t - x < params.rate_window_s) + (t,)
        turned += step
    return exp_all, exp_axis, turned, marks


def mag_usability_step(state: MagUsabilityState, time_s: float, mag_body_gauss, roll_rad: float | None,
                       pitch_rad: float | None, params: MagUsabilityParams, gyro_body_rad_s=None,
                       hard_iron_gauss=None) -> tuple[MagUsabilityState, MagVerdict]:
    """One magnetometer sample (body axes, gauss) with the roll/pitch it is levelled with (None:
    no dip test) and the body rate since the previous call (rad/s, body axes; None: motion unknown).
    ``hard_iron_gauss``: a hard iron learnt meanwhile (estimators/mag_disturbance); the norm and
    dip tests judge m - hard_iron (the frozen, stuck-axis and rate tests the raw samples).
    Non-finite input is the caller's to reject (ValueError)."""
    m = np.asarray(mag_body_gauss, float)
    if m.shape != (3,) or not np.all(np.isfinite(m)) or not math.isfinite(time_s):
        raise ValueError(f"mag_body_gauss must be 3 finite values and time_s finite, got {mag_body_gauss!r}, {time_s!r}")
    t = float(time_s)
    mt = tuple(float(x) for x in m)
    first = state.first_s if state.first_s is not None else t
    new = state.last_mag is None or mt != state.last_mag
    motion_known = gyro_body_rad_s is not None
    exp_all, exp_axis, turned, marks = _motion(state, t, m, gyro_body_rad_s, params)
    if new:
        exp_all = 0.0
    if state.last_mag is not None:
        exp_axis = tuple(0.0 if mt[i] != state.last_mag[i] else exp_axis[i] for i in range(3))
    moving = motion_known and any(t - x < params.rate_window_s for x in marks)
    axis_changed = tuple(t if (state.last_mag is None or mt[i] != state.last_mag[i] or state.axis_changed_s[i] is None)
                         else state.axis_changed_s[i] for i in range(3))
    changed_s = t if new else state.changed_s
    new_times = tuple(x for x in state.new_times if t - x < params.rate_window_s) + ((t,) if new else ())
    window = tuple(w for w in state.window if t - w[0] < params.window_s)
    if new:
        mc = m
        if hard_iron_gauss is not None:
            mc = m - np.asarray(hard_iron_gauss, float)
        ratio = float(np.linalg.norm(mc)) / params.field_norm_gauss
        dip = math.nan
        if roll_rad is not None and pitch_rad is not None and math.isfinite(roll_rad) and math.isfinite(pitch_rad):
            # level the field: m_lev = R_y(pitch) R_x(roll) m (the same levelling as polar_heading)
            cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
            my = cr * mc[1] - sr * mc[2]
            mz1 = sr * mc[1] + cr * mc[2]
            mx = cp * mc[0] + sp * mz1
            mz = -sp * mc[0] + cp * mz1
            dip = math.atan2(mz, math.hypot(mx, my))
        window = window + ((t, ratio, dip),)
    norm_ratio = _median(w[1] for w in window)
    dip_med = _median(w[2] for w in window)
    span = min(params.rate_window_s, t - first)
    rate = (len(new_times) - 1) / span if span > 0 and len(new_times) > 1 else math.nan

    reason = ""
    if params.full_scale_gauss is not None and float(np.max(np.abs(m))) >= params.full_scale_gauss:
        reason = f"saturated: |axis| {float(np.max(np.abs(m))):.2f} G >= full scale {params.full_scale_gauss:.2f} G"
    elif motion_known and t - changed_s >= params.frozen_s and exp_all >= params.min_expected_change_gauss:
        reason = (f"frozen: identical samples for {t - changed_s:.1f} s while the gyros predict a "
                  f"{exp_all:.3f} G change")
    elif motion_known:
        stuck = [i for i in range(3) if t - axis_changed[i] >= params.frozen_s
                 and exp_axis[i] >= params.min_expected_change_gauss and t - changed_s < params.frozen_s]
        if stuck:
            reason = (f"saturated: axis {'xyz'[stuck[0]]} stuck at {mt[stuck[0]]:+.3f} G for "
                      f"{t - axis_changed[stuck[0]]:.1f} s while the others change")
    if not reason and moving and t - first >= params.rate_window_s and not (len(new_times) / params.rate_window_s >= params.min_rate_hz):
        reason = (f"too slow: {len(new_times) / params.rate_window_s:.2f} new samples/s < "
                  f"{params.min_rate_hz:.1f} Hz")
    if not reason and math.isfinite(norm_ratio) and abs(norm_ratio - 1.0) > params.norm_tolerance_fraction:
        reason = (f"field norm {norm_ratio * params.field_norm_gauss:.3f} G vs the model's "
                  f"{params.field_norm_gauss:.3f} G (off by {100 * abs(norm_ratio - 1):.0f} % > "
                  f"{100 * params.norm_tolerance_fraction:.0f} %)")
    if not reason and math.isfinite(dip_med) and abs(dip_med - params.field_dip_rad) > params.dip_tolerance_rad:
        reason = (f"dip {math.degrees(dip_med):.1f} deg vs the model's {math.degrees(params.field_dip_rad):.1f} deg "
                  f"(off by more than {math.degrees(params.dip_tolerance_rad):.0f} deg)")
    if not reason and t - first < params.window_s:
        # not judged yet: a first sample may be anything (a wrong axis mapping initialised a heading
        # before the dip test saw it): no verdict until a window of samples exists
        st = replace(state, last_mag=mt, changed_s=changed_s, axis_changed_s=axis_changed, new_times=new_times,
                     window=window, first_s=first, last_call_s=t, expected_change_gauss=exp_all,
                     axis_expected_change_gauss=exp_axis, turned_rad=turned, motion_marks=marks, usable=None,
                     reason=f"being checked ({t - first:.1f} of {params.window_s:.1f} s of samples)")
        return st, MagVerdict(False, st.reason, new, False, norm_ratio, dip_med, rate)
    usable = not reason
    changed = usable != state.usable
    st = replace(state, last_mag=mt, changed_s=changed_s, axis_changed_s=axis_changed, new_times=new_times,
                 window=window, first_s=first, last_call_s=t, expected_change_gauss=exp_all,
                 axis_expected_change_gauss=exp_axis, turned_rad=turned, motion_marks=marks, usable=usable,
                 reason=reason)
    return st, MagVerdict(usable, reason, new, changed, norm_ratio, dip_med, rate)


def mag_usability_stale(state: MagUsabilityState, time_s: float, params: MagUsabilityParams,
                        gyro_body_rad_s=None) -> tuple[MagUsabilityState, MagVerdict | None]:
    """No magnetometer sample at ``time_s``: after ``frozen_s`` without one the magnetometer is
    'no samples' (a verdict only when that changes the state, else None). The body's turn is still
    counted (against the last vector) for the frozen and rate tests of the next sample."""
    if state.last_mag is not None and gyro_body_rad_s is not None:
        exp_all, exp_axis, turned, marks = _motion(state, time_s, np.asarray(state.last_mag), gyro_body_rad_s, params)
        state = replace(state, last_call_s=time_s, expected_change_gauss=exp_all,
                        axis_expected_change_gauss=exp_axis, turned_rad=turned, motion_marks=marks)
    if state.changed_s is None or time_s - state.changed_s < params.frozen_s or state.reason.startswith("no samples"):
        return state, None
    reason = f"no samples for {time_s - state.changed_s:.1f} s"
    changed = state.usable is not False
    st = replace(state, usable=False, reason=reason)
    return st, MagVerdict(False, reason, False, changed)
