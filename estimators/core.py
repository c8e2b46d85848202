"""The compiled core's Python face (estimators._core, built from core/ by scikit-build-core).

The Python implementations in estimators/ stay the reference: every function here has the same
signature and returns the same values as the reference it names (tests/test_core_*.py run both
on the same recorded flights and require equality). Two call forms:

- drop-in per-sample steps (``strapdown_step``, ``levelling_step``, method B's
  ``synthetic_ahrs_step`` / ``_output`` / ``_unseen``, the magnetometer usability's
  ``mag_usability_step`` / ``_stale``, method A's ``azimuth_propagate``, method C's attitude filter
  ``polar_attitude_init`` / ``_init_at`` / ``_step`` / ``_estimate`` / ``_unseen`` and its zero-rate
  update ``attitude_zero_rate_update``, method C's heading filter ``polar_heading_init`` / ``_step`` /
  ``_unseen`` / ``_estimate`` / ``_attitude`` and ``heading_zero_rate_update``) for callers that still step one sample or event at a time
  (the held forms keep the state in the core between calls); the
  IMU input checks' decisions (``input_checks_core``, whose Python face is service/input_checks.py
  CoreImuInputChecks: a service module);
- batch calls (``strapdown_propagate``, ``levelling_accumulate``): typed N x 3 numpy arrays in,
  one C++ loop, arrays out; no per-sample Python.

``AVAILABLE`` says whether the extension imported; ``IMPORT_ERROR`` says why not (the service
logs it and runs the Python reference: service/core_backend.py). Pure: no I/O, no clocks.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from estimators import levelling as _lev
from estimators import mag_disturbance as _md
from estimators import mag_usability as _mu
from estimators import polar_attitude as _pa
from estimators import polar_heading as _ph
from estimators import strapdown as _sd
from estimators import synthetic_ahrs as _sa
from estimators import zero_rate as _zr
from estimators.ahrs_kf2 import Kf2State
from estimators.air_data import AirData, AirDataState
from estimators.levelling import LevellingState
from estimators.mag_error_kf import Kf1State
from estimators.records import fast_replace
from estimators.reference_health import ReferenceHealthState
from estimators.strapdown import StrapdownDiag, StrapdownParams, StrapdownState
from estimators.synthetic_ahrs import (AirEvent, FcAttitudeEvent, FcStatusEvent, HeadingEvent, ImuEvent,
                                       SyntheticAhrsOutput, SyntheticAhrsParams, SyntheticAhrsState)

try:
    from estimators import _core
    AVAILABLE, IMPORT_ERROR = True, ""
except ImportError as exc:  # a build that failed or a foreign platform: the reference runs
    _core, AVAILABLE, IMPORT_ERROR = None, False, f"{type(exc).__name__}: {exc}"

# method B's held state (core/synthetic_ahrs.hpp): an extension built before it lacks it (the
# service then runs B's reference: service/core_backend.py)
B_AVAILABLE = AVAILABLE and hasattr(_core, "SyntheticAhrs")
# the IMU input checks' per-sample decisions (core/input_checks.hpp; the Python face is
# service/input_checks.py CoreImuInputChecks): an extension built before them lacks them
CHECKS_AVAILABLE = AVAILABLE and hasattr(_core, "InputChecks")
input_checks_core = _core.InputChecks if CHECKS_AVAILABLE else None

# core/strapdown.hpp StrapdownCode
INTEGRATED, FIRST_SAMPLE, NON_FINITE, TIME_NOT_INCREASING, GAP = 0, 1, 2, 3, 4
_NO_PREV = np.zeros(3)


def strapdown_reason(code: int, dt_s: float) -> str:
    """The reference's StrapdownDiag.reason for a core code (estimators/strapdown.py)."""
    if code == INTEGRATED:
        return ""
    if code == FIRST_SAMPLE:
        return "first sample"
    if code == NON_FINITE:
        return "non-finite sample"
    if code == TIME_NOT_INCREASING:
        return f"time not increasing (dt={dt_s:.6f} s)"
    return f"gap of {dt_s:.3f} s not integrated"


def _prev(state: StrapdownState) -> tuple[bool, float, np.ndarray]:
    has = state.time_s is not None and state.gyro_prev_rad_s is not None
    return (has, float(state.time_s) if has else 0.0,
            np.asarray(state.gyro_prev_rad_s, float) if has else _NO_PREV)


def strapdown_step(state: StrapdownState, gyro_rad_s: np.ndarray, time_s: float,
                   params: StrapdownParams = StrapdownParams()) -> tuple[StrapdownState, StrapdownDiag]:
    """estimators.strapdown.strapdown_step, in the core (same arguments, same results)."""
    w = np.asarray(gyro_rad_s, dtype=float)
    if w.shape != (3,):
        return state, StrapdownDiag(False, "non-finite sample")
    has, t_prev, g_prev = _prev(state)
    code, dt, q = _core.strapdown_step(state.q_ref_from_sensor, has, t_prev, g_prev, w, float(time_s),
                                       params.max_dt_s)
    if code == INTEGRATED:
        return StrapdownState(q, time_s, w), StrapdownDiag(True, "", dt)
    if code in (FIRST_SAMPLE, GAP):
        return StrapdownState(state.q_ref_from_sensor, time_s, w), StrapdownDiag(False, strapdown_reason(code, dt), dt)
    return state, StrapdownDiag(False, strapdown_reason(code, dt), dt)


class HeldDiag(NamedTuple):
    """StrapdownDiag's fields for the held path (a tuple: built per sample at a tenth of the cost
    of the frozen dataclass)."""
    integrated: bool
    reason: str = ""
    dt_s: float = 0.0


class HeldStrapdown:
    """A StrapdownState held in the core between samples (what ``strapdown_step_held`` steps in
    place): it reads like a StrapdownState (q_ref_from_sensor, time_s, gyro_prev_rad_s), and
    ``to_state()`` gives the reference's record. Not a pure value: the owner replaces it, never
    shares it."""

    __slots__ = ("_c",)

    def __init__(self, state: StrapdownState):
        has, t_prev, g_prev = _prev(state)
        self._c = _core.Strapdown(np.asarray(state.q_ref_from_sensor, float), has, t_prev, g_prev)

    @property
    def q_ref_from_sensor(self) -> np.ndarray:
        return self._c.q_ref_from_sensor

    @property
    def time_s(self) -> float | None:
        return self._c.time_prev_s if self._c.has_prev else None

    @property
    def gyro_prev_rad_s(self) -> np.ndarray | None:
        return self._c.gyro_prev_rad_s if self._c.has_prev else None

    def to_state(self) -> StrapdownState:
        return StrapdownState(self.q_ref_from_sensor, self.time_s, self.gyro_prev_rad_s)

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldStrapdown, (self.to_state(),)


def strapdown_step_held(state: StrapdownState | HeldStrapdown, gyro_rad_s: np.ndarray, time_s: float,
                        params: StrapdownParams = StrapdownParams()) -> tuple[HeldStrapdown, HeldDiag]:
    """estimators.strapdown.strapdown_step with the state held in the core (a StrapdownState is
    taken in on the first call): one C++ call per sample, the same results (the diagnostics as a
    HeldDiag with StrapdownDiag's fields)."""
    if not isinstance(state, HeldStrapdown):
        state = HeldStrapdown(state)
    w = np.asarray(gyro_rad_s, dtype=float)
    if w.shape != (3,):
        return state, HeldDiag(False, "non-finite sample")
    wx, wy, wz = w.tolist()
    code, dt = state._c.step3(wx, wy, wz, time_s, params.max_dt_s)
    return state, HeldDiag(True, "", dt) if code == INTEGRATED else HeldDiag(False, strapdown_reason(code, dt), dt)


def strapdown_propagate(state: StrapdownState, gyro_rad_s: np.ndarray, time_s: np.ndarray,
                        params: StrapdownParams = StrapdownParams(), use_core: bool = True
                        ) -> tuple[StrapdownState, np.ndarray, np.ndarray, np.ndarray]:
    """N bias-corrected rate samples ((N, 3) rad/s, (N,) s) through the one propagation.

    Returns (state after the last, q_ref_from_sensor after each sample (N, 4), code per sample
    (N,) int8 (INTEGRATED ... GAP; ``strapdown_reason`` words it), dt_s per sample (N,)).
    ``use_core=False`` runs the Python reference sample by sample (same results)."""
    g = np.ascontiguousarray(gyro_rad_s, dtype=float)
    t = np.ascontiguousarray(time_s, dtype=float)
    if g.ndim != 2 or g.shape[1] != 3 or t.shape != (g.shape[0],):
        raise ValueError(f"gyro_rad_s must be (N, 3) and time_s (N,), got {g.shape} and {t.shape}")
    if use_core:
        has, t_prev, g_prev = _prev(state)
        q, codes, dts, has, t_prev, g_prev, q_last = _core.strapdown_propagate(
            state.q_ref_from_sensor, has, t_prev, g_prev, g, t, params.max_dt_s)
        out = StrapdownState(q_last, t_prev, g_prev) if has else StrapdownState(q_last, state.time_s, None)
        return (out if len(codes) else state), q, codes, dts
    n = g.shape[0]
    q, codes, dts = np.empty((n, 4)), np.empty(n, np.int8), np.empty(n)
    words = {"": INTEGRATED, "first sample": FIRST_SAMPLE, "non-finite sample": NON_FINITE}
    for k in range(n):
        state, d = _sd.strapdown_step(state, g[k], float(t[k]), params)
        q[k], dts[k] = state.q_ref_from_sensor, d.dt_s
        codes[k] = words.get(d.reason, TIME_NOT_INCREASING if d.reason.startswith("time") else GAP)
    return state, q, codes, dts


# --- the rest accumulator (estimators/levelling.py levelling_step) ---------------------------

def levelling_pack(s: LevellingState) -> np.ndarray:
    """LevellingState -> the core's flat float64 vector (core/bindings.cpp pack/unpack)."""
    b, st = s.batch, s.batch_stats
    return np.array([
        s.n, *s.accel_mean_m_s2.tolist(), *s.accel_m2.tolist(), *s.gyro_mean_rad_s.tolist(), *s.gyro_m2.tolist(),
        math.nan if s.t_first_s is None else s.t_first_s, math.nan if s.t_last_s is None else s.t_last_s,
        1.0 if b else 0.0, *((b[0], b[1], *b[2], *b[3]) if b else (0.0,) * 8),
        s.nb, 1.0 if st else 0.0, *((*st[0], *st[1], *st[2], *st[3]) if st else (0.0,) * 12)])


def levelling_unpack(p: np.ndarray) -> LevellingState:
    """The core's flat vector -> LevellingState (the reference's field types: ints, lists, tuples)."""
    v = p.tolist()
    t_first = None if math.isnan(v[13]) else v[13]
    t_last = None if math.isnan(v[14]) else v[14]
    batch = (v[16], int(v[17]), v[18:21], v[21:24]) if v[15] else ()
    stats = (v[26:29], v[29:32], v[32:35], v[35:38]) if v[25] else ()
    return LevellingState(int(v[0]), p[1:4].copy(), p[4:7].copy(), p[7:10].copy(), p[10:13].copy(),
                          t_first, t_last, batch, int(v[24]), stats)


def levelling_accumulate(state: LevellingState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                         time_s: np.ndarray | None = None, batch_s: float = _lev.LevellingParams.batch_s,
                         use_core: bool = True) -> tuple[LevellingState, np.ndarray]:
    """N samples ((N, 3) rad/s and m/s^2, (N,) s or None = untimed) into the rest accumulator.

    Returns (state after, accepted per sample (N,) bool: a non-finite sample is skipped, as in
    the reference). ``use_core=False`` runs the Python reference sample by sample."""
    g = np.ascontiguousarray(gyro_rad_s, dtype=float)
    a = np.ascontiguousarray(accel_m_s2, dtype=float)
    n = g.shape[0] if g.ndim == 2 else -1
    t = np.full(max(n, 0), math.nan) if time_s is None else np.ascontiguousarray(time_s, dtype=float)
    if g.ndim != 2 or g.shape[1] != 3 or a.shape != g.shape or t.shape != (n,):
        raise ValueError(f"gyro and accel must be (N, 3) and time_s (N,), got {g.shape}, {a.shape}, {t.shape}")
    if use_core:
        packed, used = _core.levelling_accumulate(levelling_pack(state), g, a, t, batch_s)
        return levelling_unpack(packed), used
    used = np.empty(n, bool)
    for k in range(n):
        before = state
        tk = float(t[k])
        state = _lev.levelling_step(state, g[k], a[k], tk if math.isfinite(tk) else None, batch_s)
        used[k] = state is not before
    return state, used


def levelling_step(state: LevellingState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                   time_s: float | None = None, batch_s: float = _lev.LevellingParams.batch_s) -> LevellingState:
    """estimators.levelling.levelling_step, in the core (same arguments, same results)."""
    g = np.asarray(gyro_rad_s, float).reshape(1, 3)
    a = np.asarray(accel_m_s2, float).reshape(1, 3)
    t = np.array([math.nan if time_s is None else time_s], float)
    packed, used = _core.levelling_accumulate(levelling_pack(state), g, a, t, batch_s)
    return levelling_unpack(packed) if used[0] else state


# --- method B, the synthetic AHRS (estimators/synthetic_ahrs.py), variant b2 --------------------
# The state is held in the core between events (HeldSyntheticAhrs): one C++ call per event, the
# reference's SyntheticAhrsState built only when asked (to_state: a copy, a test). Variant b1 is not
# ported: the reference runs it (a held state is handed back as the reference's record).

_B_OUT_FIELDS = ("time_s", "valid", "roll_rad", "pitch_rad", "heading_rad", "roll_sigma_rad", "pitch_sigma_rad",
                 "heading_sigma_rad", "reference_trusted", "reference_reason", "air_correction_active",
                 "air_off_reason", "kf1_learning", "gyro_bias_rad_s", "mag_fused", "mag_rejected", "mag_gated",
                 "air_fused", "air_rejected", "ref_fused", "kf1_rejected", "imu_integrated_s", "imu_not_integrated_s")
_STALE = object()


def _fields(obj) -> dict:
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def _kf1_numbers(k: Kf1State) -> dict:
    return {"x": k.x, "P": k.P, "field_norm_gauss": k.field_norm_gauss, "time_s": k.time_s,
            "n_updates": k.n_updates, "n_rejected_chi2": k.n_rejected_chi2, "n_rejected_rate": k.n_rejected_rate}


def _state_dict(s: SyntheticAhrsState) -> dict:
    d = _fields(s)
    d["air"] = _fields(s.air)
    d["air_last"] = None if s.air_last is None else _fields(s.air_last)
    d["health"] = _fields(s.health)
    d["kf2"] = None if s.kf2 is None else _fields(s.kf2)
    d["kf1_learn"] = _kf1_numbers(s.kf1_learn)
    d["kf1_applied"] = None if s.kf1_applied is None else _kf1_numbers(s.kf1_applied)
    return d


class HeldSyntheticAhrs:
    """A SyntheticAhrsState (variant b2) held in the core, stepped in place by
    ``synthetic_ahrs_step``; it reads like the reference's state where the service reads it
    (``air_last``, ``kf1_learn``) and ``to_state()`` gives the reference's record. Not a pure value:
    the owner replaces it, never shares it. An event the reference refuses (ValueError) leaves it
    as it was, as the reference's immutable state is left."""

    __slots__ = ("_c", "_params", "_cp", "_kf1_learn", "_kf1_applied", "_air")

    def __init__(self, state: SyntheticAhrsState, params: SyntheticAhrsParams):
        if state.b1 is not None:
            raise ValueError("variant b1 is not in the core: the reference runs it")
        self._c = _core.SyntheticAhrs(_state_dict(state))
        self._kf1_learn, self._kf1_applied = state.kf1_learn, state.kf1_applied  # flight_count, meta
        self._params, self._cp = params, _core.SyntheticAhrsParams(params)
        self._air = _STALE

    def _p(self, params: SyntheticAhrsParams):
        """The converted params (converted again when the owner replaced them, e.g. exclude_fc_yaw)."""
        if params is not self._params:
            self._params, self._cp = params, _core.SyntheticAhrsParams(params)
        return self._cp

    @property
    def air_last(self) -> AirData | None:
        if self._air is _STALE:
            d = self._c.air_last()
            self._air = None if d is None else AirData(**d)
        return self._air

    @property
    def kf1_learn(self) -> Kf1State:
        return fast_replace(self._kf1_learn, **self._c.kf1_learn())

    def to_state(self) -> SyntheticAhrsState:
        d = self._c.get_state(self._cp)
        kf2 = d["kf2"]
        d.update(air=AirDataState(**d["air"]), air_last=self.air_last, health=ReferenceHealthState(**d["health"]),
                 kf2=None if kf2 is None else Kf2State(**kf2), kf1_learn=self.kf1_learn,
                 kf1_applied=self._kf1_applied, b1=None)
        return SyntheticAhrsState(**d)

    @classmethod
    def _restore(cls, state: SyntheticAhrsState, params: SyntheticAhrsParams) -> "HeldSyntheticAhrs":
        return cls(state, params)

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record
        return HeldSyntheticAhrs._restore, (self.to_state(), self._params)


def _b_output(t: tuple, state: HeldSyntheticAhrs, params: SyntheticAhrsParams) -> SyntheticAhrsOutput:
    out = object.__new__(SyntheticAhrsOutput)  # a frozen record without __post_init__ (records.fast_replace)
    d = out.__dict__
    d.update(zip(_B_OUT_FIELDS, t))
    d["variant"] = params.variant
    d["kf1_applied_flights"] = None if state._kf1_applied is None else state._kf1_applied.flight_count
    return out


def _v3(x) -> tuple[bool, float, float, float]:
    """(usable, x, y, z) of a 3-vector event field; a missing or malformed one is not usable."""
    if x is None:
        return False, _NAN, _NAN, _NAN
    a = np.asarray(x, dtype=float)
    if a.shape != (3,):
        return False, _NAN, _NAN, _NAN
    x0, x1, x2 = a.tolist()
    return True, x0, x1, x2


_NAN = math.nan


def synthetic_ahrs_step(state: SyntheticAhrsState | HeldSyntheticAhrs, event, params: SyntheticAhrsParams,
                        output: bool = True) -> tuple[SyntheticAhrsState | HeldSyntheticAhrs,
                                                      SyntheticAhrsOutput | None]:
    """estimators.synthetic_ahrs.synthetic_ahrs_step with the state held in the core (a
    SyntheticAhrsState is taken in on the first call); the same results. Variant b1 runs the
    reference. A malformed magnetometer field (not 3 values) counts as no sample (the reference
    also skips it, except before KF2 starts, where it raises)."""
    if params.variant != "b2":
        if isinstance(state, HeldSyntheticAhrs):
            state = state.to_state()
        return _sa.synthetic_ahrs_step(state, event, params, output)
    t = float(event.time_s)
    if not math.isfinite(t):
        raise ValueError(f"event time_s must be finite, got {event.time_s!r}")
    if not isinstance(state, HeldSyntheticAhrs):
        state = HeldSyntheticAhrs(state, params)
    cp = state._p(params)
    c = state._c
    if isinstance(event, ImuEvent):
        ok, gx, gy, gz = _v3(event.gyro_sensor_rad_s)
        if not ok:
            gx = _NAN
        has_mag, mx, my, mz = _v3(event.mag_sensor_gauss)
        out = c.imu(cp, gx, gy, gz, has_mag, mx, my, mz, t, output)
    elif isinstance(event, AirEvent):
        diff, temp = event.press_diff_pa, event.temperature_k
        state._air = _STALE
        out = c.air(cp, float(event.press_abs_pa), diff is not None, _NAN if diff is None else float(diff),
                    temp is not None, _NAN if temp is None else float(temp), t, output)
    elif isinstance(event, FcAttitudeEvent):
        _, r, p, y = _v3(event.euler_rad)
        out = c.fc_attitude(cp, r, p, y, t, output)
    elif isinstance(event, FcStatusEvent):
        s, a, h = event.system_status, event.attitude_ok, event.horiz_pos_ok
        out = c.fc_status(cp, s is not None, 0 if s is None else int(s), -1 if a is None else int(bool(a)),
                          -1 if h is None else int(bool(h)), t, output)
    elif isinstance(event, HeadingEvent):  # B1's heading source: nothing in b2
        out = c.output(cp) if output else None
    else:
        raise ValueError(f"unknown event type {type(event).__name__}")
    return state, (None if out is None else _b_output(out, state, params))


def synthetic_ahrs_output(state: SyntheticAhrsState | HeldSyntheticAhrs,
                          params: SyntheticAhrsParams) -> SyntheticAhrsOutput | None:
    """estimators.synthetic_ahrs.synthetic_ahrs_output for either state."""
    if not isinstance(state, HeldSyntheticAhrs):
        return _sa.synthetic_ahrs_output(state, params)
    out = state._c.output(state._p(params))
    return None if out is None else _b_output(out, state, params)


def synthetic_ahrs_unseen(state: SyntheticAhrsState | HeldSyntheticAhrs, unseen_s: float,
                          params: SyntheticAhrsParams) -> SyntheticAhrsState | HeldSyntheticAhrs:
    """estimators.synthetic_ahrs.synthetic_ahrs_unseen for either state."""
    if not isinstance(state, HeldSyntheticAhrs):
        return _sa.synthetic_ahrs_unseen(state, unseen_s, params)
    state._c.unseen(state._p(params), float(unseen_s))
    state._air = _STALE
    return state


def synthetic_ahrs_takeoff(state: SyntheticAhrsState | HeldSyntheticAhrs,
                           params: SyntheticAhrsParams) -> SyntheticAhrsState | HeldSyntheticAhrs:
    """estimators.synthetic_ahrs.synthetic_ahrs_takeoff for either state (a held state from a build
    without it goes through the reference's record, taken in again at its next step)."""
    if not isinstance(state, HeldSyntheticAhrs):
        return _sa.synthetic_ahrs_takeoff(state, params)
    if not hasattr(state._c, "takeoff"):
        return _sa.synthetic_ahrs_takeoff(state.to_state(), params)
    state._c.takeoff(state._p(params))
    return state


# --- magnetometer usability (estimators/mag_usability.py) ----------------------------------------
# The state is held in the core between filter steps (HeldMagUsability); the reference's
# MagUsabilityState is built only when asked (to_state: a copy, a test).

MAG_USABILITY_AVAILABLE = AVAILABLE and hasattr(_core, "MagUsability")


class HeldMagUsability:
    """A MagUsabilityState held in the core, stepped in place by ``mag_usability_step`` /
    ``mag_usability_stale``; it reads like the reference's state where the service reads it
    (``usable``, ``reason``) and ``to_state()`` gives the reference's record. Not a pure value: the
    owner replaces it, never shares it."""

    __slots__ = ("_c", "_params", "_cp")

    def __init__(self, state: _mu.MagUsabilityState):
        self._c = _core.MagUsability(state)
        self._params = self._cp = None

    def _p(self, params: _mu.MagUsabilityParams):
        if params is not self._params:
            self._params, self._cp = params, _core.MagUsabilityParams(params)
        return self._cp

    @property
    def usable(self) -> bool | None:
        return self._c.usable

    @property
    def reason(self) -> str:
        return self._c.reason

    def to_state(self) -> _mu.MagUsabilityState:
        return _mu.MagUsabilityState(**self._c.get_state())

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldMagUsability, (self.to_state(),)


def _gyro3(gyro_body_rad_s) -> tuple[bool, bool, float, float, float]:
    """(motion known, 3 values, x, y, z) of the reference's optional gyro argument."""
    if gyro_body_rad_s is None:
        return False, False, _NAN, _NAN, _NAN
    w = np.asarray(gyro_body_rad_s, float)
    if w.shape != (3,):
        return True, False, _NAN, _NAN, _NAN
    x, y, z = w.tolist()
    return True, True, x, y, z


def _mag_verdict(t: tuple) -> _mu.MagVerdict:
    return _mu.MagVerdict(*t)


def mag_usability_step(state: _mu.MagUsabilityState | HeldMagUsability, time_s: float, mag_body_gauss,
                       roll_rad: float | None, pitch_rad: float | None, params: _mu.MagUsabilityParams,
                       gyro_body_rad_s=None, hard_iron_gauss=None) -> tuple[HeldMagUsability, _mu.MagVerdict]:
    """estimators.mag_usability.mag_usability_step with the state held in the core (a
    MagUsabilityState is taken in on the first call); the same results."""
    m = np.asarray(mag_body_gauss, float)
    ml = m.tolist() if m.shape == (3,) else ()   # the finiteness test on Python floats
    if not (ml and all(map(math.isfinite, ml))) or not math.isfinite(time_s):
        raise ValueError(f"mag_body_gauss must be 3 finite values and time_s finite, got {mag_body_gauss!r}, {time_s!r}")
    if not isinstance(state, HeldMagUsability):
        state = HeldMagUsability(state)
    mx, my, mz = ml
    tilt = roll_rad is not None and pitch_rad is not None and math.isfinite(roll_rad) and math.isfinite(pitch_rad)
    known, ok, wx, wy, wz = _gyro3(gyro_body_rad_s)
    has_hi = hard_iron_gauss is not None
    hx, hy, hz = np.asarray(hard_iron_gauss, float).tolist() if has_hi else (_NAN, _NAN, _NAN)
    v = state._c.step(state._p(params), float(time_s), mx, my, mz, tilt, roll_rad if tilt else _NAN,
                      pitch_rad if tilt else _NAN, known, ok, wx, wy, wz, has_hi, hx, hy, hz)
    return state, _mag_verdict(v)


def mag_usability_stale(state: _mu.MagUsabilityState | HeldMagUsability, time_s: float,
                        params: _mu.MagUsabilityParams, gyro_body_rad_s=None
                        ) -> tuple[HeldMagUsability, _mu.MagVerdict | None]:
    """estimators.mag_usability.mag_usability_stale with the state held in the core."""
    if not isinstance(state, HeldMagUsability):
        state = HeldMagUsability(state)
    known, ok, wx, wy, wz = _gyro3(gyro_body_rad_s)
    v = state._c.stale(state._p(params), float(time_s), known, ok, wx, wy, wz)
    return state, None if v is None else _mag_verdict(v)


# --- method A's per-sample propagation (estimators/azimuth.py azimuth_propagate) -----------------

AZIMUTH_AVAILABLE = AVAILABLE and hasattr(_core, "azimuth_propagate")


def azimuth_propagate(strapdown: StrapdownState, G_gyro: np.ndarray, C_isf_sf: np.ndarray,
                      gyro_corrected_rad_s: np.ndarray, time_s: float, params: StrapdownParams
                      ) -> tuple[StrapdownState, np.ndarray, np.ndarray]:
    """estimators.azimuth.azimuth_propagate in the core (core/azimuth_propagation.hpp): the same
    arguments and results (the strapdown, then G and C_ISF<-SF, in one C++ call)."""
    w = np.asarray(gyro_corrected_rad_s, dtype=float)
    if w.shape != (3,):
        return strapdown, C_isf_sf, G_gyro
    wx, wy, wz = w.tolist()
    has, t_prev, g_prev = _prev(strapdown)
    code, _dt, q, G, C = _core.azimuth_propagate(strapdown.q_ref_from_sensor, has, t_prev, g_prev, G_gyro, C_isf_sf,
                                                 wx, wy, wz, float(time_s), params.max_dt_s)
    if code == INTEGRATED:
        return StrapdownState(q, time_s, w), C, G
    if code in (FIRST_SAMPLE, GAP):
        return StrapdownState(strapdown.q_ref_from_sensor, time_s, w), C_isf_sf, G_gyro
    return strapdown, C_isf_sf, G_gyro


# --- magnetic disturbances in motion (estimators/mag_disturbance.py) ----------------------------
# The state is held in the core between filter steps (HeldMagDisturbance); the reference's
# MagDisturbanceState is built only when asked (to_state: a copy, a test).

MAG_DISTURBANCE_AVAILABLE = AVAILABLE and hasattr(_core, "MagDisturbance")


class HeldMagDisturbance:
    """A MagDisturbanceState held in the core, stepped in place by ``mag_disturbance_step``; it
    reads like the reference's state where the service reads it (``hard_iron_gauss``,
    ``P_hard_iron``, ``n_relearns``, ``relearning``, ``reason``) and ``to_state()`` gives the
    reference's record. Not a pure value: the owner replaces it, never shares it."""

    __slots__ = ("_c", "_params", "_cp", "_t")

    def __init__(self, state: _md.MagDisturbanceState):
        self._c = _core.MagDisturbance(state)
        self._params = self._cp = None
        self._t = state.time_s  # the last sample's time (the reference refuses an earlier one)

    def _p(self, params: _md.MagDisturbanceParams):
        if params is not self._params:
            self._params, self._cp = params, _core.MagDisturbanceParams(params)
        return self._cp

    hard_iron_gauss = property(lambda self: self._c.hard_iron_gauss)
    P_hard_iron = property(lambda self: self._c.P_hard_iron)
    n_relearns = property(lambda self: self._c.n_relearns)
    relearning = property(lambda self: self._c.relearning)
    reason = property(lambda self: self._c.reason)

    def to_state(self) -> _md.MagDisturbanceState:
        return _md.MagDisturbanceState(**self._c.get_state())

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldMagDisturbance, (self.to_state(),)


def mag_disturbance_step(state: _md.MagDisturbanceState | HeldMagDisturbance, time_s: float, mag_body_gauss,
                         q_P_from_body, params: _md.MagDisturbanceParams
                         ) -> tuple[HeldMagDisturbance, _md.MagDisturbanceVerdict]:
    """estimators.mag_disturbance.mag_disturbance_step with the state held in the core (a
    MagDisturbanceState is taken in on the first call); the same results. A refused sample
    (ValueError, the reference's message) leaves the state as it was."""
    m = np.asarray(mag_body_gauss, float)
    q = np.asarray(q_P_from_body, float)
    # the finiteness test on Python floats (np.all(np.isfinite(...)) costs more than the step)
    ml, ql = (m.tolist(), q.tolist()) if m.shape == (3,) and q.shape == (4,) else ((), ())
    if not (ml and all(map(math.isfinite, ml)) and all(map(math.isfinite, ql)) and math.isfinite(time_s)):
        raise ValueError(f"mag_body_gauss (3), q_P_from_body (4) and time_s must be finite, got "
                         f"{mag_body_gauss!r}, {q_P_from_body!r}, {time_s!r}")
    if not isinstance(state, HeldMagDisturbance):
        state = HeldMagDisturbance(state)
    t = float(time_s)
    if state._t is not None and t - state._t < 0.0:
        raise ValueError(f"time_s must not decrease ({state._t} -> {t})")
    mx, my, mz = ml
    qw, qx, qy, qz = ql
    v = state._c.step(state._p(params), t, mx, my, mz, qw, qx, qy, qz)
    state._t = state._c.time_s   # the last new sample's (a held repeat is dated at its first appearance)
    return state, _md.MagDisturbanceVerdict(*v)


# --- method C's attitude filter (estimators/polar_attitude.py) ------------------------------------
# The state is held in the core between filter steps (HeldPolarAttitude); the reference's
# PolarAttitudeState is built only when asked (to_state: a copy, a test, the zero-rate update at
# rest). The arguments are checked here as the reference checks them (the same messages); the core
# gets plain floats and hands back a code, worded here as the reference words its diagnostics.

POLAR_AVAILABLE = AVAILABLE and hasattr(_core, "PolarAttitude")

# core/polar_attitude.hpp Code and Why
_PA_SAMPLE, _PA_LEVELLING, _PA_LEVELLED, _PA_NON_FINITE, _PA_RESTARTED, _PA_TIME, _PA_GAP, _PA_UPDATE = range(8)
_PA_FUSED, _PA_GATED_OUT, _PA_NOT_SETTLED, _PA_RELEVELLED = range(4)
_PA_PLAIN = _pa.PolarAttitudeDiag()
_PA_FIXED = {_PA_LEVELLING: _pa.PolarAttitudeDiag(reason="levelling"),
             _PA_LEVELLED: _pa.PolarAttitudeDiag(reason="levelled"),
             _PA_NON_FINITE: _pa.PolarAttitudeDiag(reason="non-finite sample"),
             _PA_RESTARTED: _pa.PolarAttitudeDiag(reason="increments restarted")}
_PA_UPDATE_WHY = {_PA_FUSED: "", _PA_GATED_OUT: "specific-force residual gated out",
                  _PA_NOT_SETTLED: "specific-force residual not settled after a gated-out run"}
_PA_DIAG_FIELDS = tuple(f.name for f in dataclasses.fields(_pa.PolarAttitudeDiag))


class HeldPolarAttitude:
    """A PolarAttitudeState held in the core, stepped in place by ``polar_attitude_step`` /
    ``polar_attitude_unseen``; it reads like the reference's state where the service reads it
    (``initialised``, ``time_s``, ``q_P_from_body``, ``x_hat``, ``P``, the counters) and
    ``to_state()`` gives the reference's record. Not a pure value: the owner replaces it, never
    shares it."""

    __slots__ = ("_c", "_params", "_cp")

    def __init__(self, state):
        self._c = state if POLAR_AVAILABLE and isinstance(state, _core.PolarAttitude) else \
            _core.PolarAttitude(_fields(state))
        self._params = self._cp = None

    def _p(self, params: _pa.PolarAttitudeParams):
        """The converted params (converted again when the owner replaced them)."""
        if params is not self._params:
            self._params, self._cp = params, _core.PolarAttitudeParams(params)
        return self._cp

    initialised = property(lambda self: self._c.initialised)
    time_s = property(lambda self: self._c.time_s)
    q_P_from_body = property(lambda self: self._c.q_P_from_body)
    x_hat = property(lambda self: self._c.x_hat)
    P = property(lambda self: self._c.P)
    n_updates = property(lambda self: self._c.n_updates)
    n_rejected = property(lambda self: self._c.n_rejected)
    n_relevels = property(lambda self: self._c.n_relevels)

    def to_state(self) -> _pa.PolarAttitudeState:
        return _pa.PolarAttitudeState(**self._c.get_state())

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldPolarAttitude, (self.to_state(),)


def _held_pa(state) -> HeldPolarAttitude:
    return state if isinstance(state, HeldPolarAttitude) else HeldPolarAttitude(state)


def _bias_args(gyro_bias_rad_s, gyro_bias_sigma_rad_s) -> tuple:
    """polar_attitude_init's checks (the reference's messages) -> the core's bias arguments."""
    bx = by = bz = 0.0
    if gyro_bias_rad_s is not None:
        b = np.asarray(gyro_bias_rad_s, float)
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise ValueError(f"gyro_bias_rad_s must be 3 finite numbers, got {gyro_bias_rad_s!r}")
        bx, by, bz = b.tolist()
    if gyro_bias_sigma_rad_s is not None and not (math.isfinite(gyro_bias_sigma_rad_s)
                                                  and gyro_bias_sigma_rad_s > 0.0):
        raise ValueError(f"gyro_bias_sigma_rad_s must be finite and > 0, got {gyro_bias_sigma_rad_s!r}")
    has_s = gyro_bias_sigma_rad_s is not None
    return (gyro_bias_rad_s is not None, bx, by, bz, has_s, float(gyro_bias_sigma_rad_s) if has_s else 0.0)


def polar_attitude_init(params: _pa.PolarAttitudeParams = _pa.PolarAttitudeParams(), gyro_bias_rad_s=None,
                        gyro_bias_sigma_rad_s: float | None = None) -> HeldPolarAttitude:
    """estimators.polar_attitude.polar_attitude_init, held in the core (same arguments and checks)."""
    return HeldPolarAttitude(_core.PolarAttitude.init(*_bias_args(gyro_bias_rad_s, gyro_bias_sigma_rad_s)))


def polar_attitude_init_at(time_s: float, roll_rad: float, pitch_rad: float, tilt_sigma_rad: float,
                           params: _pa.PolarAttitudeParams = _pa.PolarAttitudeParams(), gyro_bias_rad_s=None,
                           gyro_bias_sigma_rad_s: float | None = None) -> HeldPolarAttitude:
    """estimators.polar_attitude.polar_attitude_init_at, held in the core (same arguments and checks)."""
    for name, v in (("time_s", time_s), ("roll_rad", roll_rad), ("pitch_rad", pitch_rad)):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    if not (math.isfinite(tilt_sigma_rad) and tilt_sigma_rad > 0.0):
        raise ValueError(f"tilt_sigma_rad must be finite and > 0, got {tilt_sigma_rad!r}")
    bias = _bias_args(gyro_bias_rad_s, gyro_bias_sigma_rad_s)
    held = HeldPolarAttitude(_core.PolarAttitude.init_at(_core.PolarAttitudeParams(params), float(time_s),
                                                         float(roll_rad), float(pitch_rad), float(tilt_sigma_rad),
                                                         *bias))
    return held


def polar_attitude_unseen(state, unseen_s: float, params: _pa.PolarAttitudeParams = _pa.PolarAttitudeParams()
                          ) -> HeldPolarAttitude:
    """estimators.polar_attitude.polar_attitude_unseen for either state (held in the core after it)."""
    if not (math.isfinite(unseen_s) and unseen_s >= 0.0):
        raise ValueError(f"unseen_s must be finite and >= 0, got {unseen_s!r}")
    state = _held_pa(state)
    state._c.unseen(state._p(params), float(unseen_s))
    return state


def _pa_diag(t: tuple, params: _pa.PolarAttitudeParams) -> _pa.PolarAttitudeDiag:
    code = t[0]
    if code != _PA_UPDATE:
        if code == _PA_TIME:
            return _pa.PolarAttitudeDiag(reason=f"time not increasing (dt={t[1]:.6f} s)")
        if code == _PA_GAP:
            return _pa.PolarAttitudeDiag(reason=f"gap of {t[1]:.3f} s not integrated; attitude sigma widened")
        return _PA_FIXED[code]
    _, _, fused, z, ratio, settle, raised, why, moved = t
    if why == _PA_RELEVELLED:
        reason = (f"re-levelled at rest: tilt corrected by {math.degrees(moved):.1f} deg from the accelerometer "
                  f"after {params.relevel_rest_s:.1f} s of gated-out updates")
    else:
        reason = _PA_UPDATE_WHY[why]
    out = object.__new__(_pa.PolarAttitudeDiag)  # a frozen record without __post_init__ (records.fast_replace)
    out.__dict__.update(zip(_PA_DIAG_FIELDS, (True, fused, z, ratio, reason, settle, raised,
                                              why == _PA_RELEVELLED, moved)))
    return out


def polar_attitude_step(state, time_s: float, gyro_body_rad_s, accel_body_m_s2,
                        params: _pa.PolarAttitudeParams = _pa.PolarAttitudeParams()
                        ) -> tuple[HeldPolarAttitude, _pa.PolarAttitudeDiag]:
    """estimators.polar_attitude.polar_attitude_step with the state held in the core (a
    PolarAttitudeState is taken in on the first call); the same results."""
    w = np.asarray(gyro_body_rad_s, dtype=float)
    f = np.asarray(accel_body_m_s2, dtype=float)
    if w.shape != (3,) or f.shape != (3,):
        return state, _pa.PolarAttitudeDiag(reason="gyro and accel must have shape (3,)")
    state = _held_pa(state)
    wx, wy, wz = w.tolist()
    fx, fy, fz = f.tolist()
    d = state._c.step(state._p(params), float(time_s), wx, wy, wz, fx, fy, fz)
    return state, (_PA_PLAIN if d == 0 else _pa_diag(d, params))


_AE_FIELDS = tuple(f.name for f in dataclasses.fields(_pa.AttitudeEstimate))


def polar_attitude_estimate(state) -> _pa.AttitudeEstimate | None:
    """estimators.polar_attitude.polar_attitude_estimate for either state."""
    if not isinstance(state, HeldPolarAttitude):
        return _pa.polar_attitude_estimate(state)
    t = state._c.estimate()
    if t is None:
        return None
    out = object.__new__(_pa.AttitudeEstimate)  # a frozen record without __post_init__
    out.__dict__.update(zip(_AE_FIELDS, t))
    return out


def attitude_zero_rate_update(state, rate: _zr.RestRate, params: _zr.ZeroRateParams = _zr.ZeroRateParams()):
    """estimators.zero_rate.attitude_zero_rate_update for either state: on a held state the core's
    (core/zero_rate.hpp, what the filter chain runs), else (an older build) the reference's update on
    the held state's record, put back in the core when it fused."""
    if not isinstance(state, HeldPolarAttitude):
        return _zr.attitude_zero_rate_update(state, rate, params)
    if ZERO_RATE_AVAILABLE:
        return attitude_zero_rate_update_core(state, rate, params)
    st, diag = _zr.attitude_zero_rate_update(state.to_state(), rate, params)
    if diag.fused:
        state._c.set_state(_fields(st))
    return state, diag


# --- method C's heading filter (estimators/polar_heading.py) ---------------------------------------
# Held in the core between filter steps (HeldPolarHeading) as C's attitude filter is. The core reads
# the reference's HeadingInputs itself; an input it does not take as it stands (not a number, an
# array of another shape, a zero quaternion) comes back untouched and the reference answers it on the
# held state's record (whatever the reference does with it, the same). Diagnostics come back as
# codes, worded here as the reference words them.

POLAR_HEADING_AVAILABLE = AVAILABLE and hasattr(_core, "PolarHeading")

# core/polar_heading.hpp Code and Why
(_PH_PLAIN, _PH_NON_FINITE, _PH_TIME, _PH_NON_FINITE_MAG, _PH_PITCH, _PH_FIELD_WEAK, _PH_MEASURED,
 _PH_BAD_DECLINATION, _PH_BAD_RESIDUAL, _PH_BAD_FIELD_MODEL) = range(10)
_PH_FUSED, _PH_INITIALISED, _PH_RESET, _PH_GATED_OUT = range(4)
_PH_SIMPLE = (_ph.HeadingDiag(source_available=False), _ph.HeadingDiag(source_available=True))
_PH_REASON = {_PH_NON_FINITE: "non-finite input", _PH_NON_FINITE_MAG: "non-finite magnetometer",
              _PH_PITCH: "pitch beyond max_abs_pitch_rad"}
_PH_DIAG_FIELDS = tuple(f.name for f in dataclasses.fields(_ph.HeadingDiag))


class HeldPolarHeading:
    """A PolarHeadingState held in the core, stepped in place by ``polar_heading_step`` /
    ``polar_heading_unseen``; it reads like the reference's state (every PolarHeadingState field, so
    the reference's own functions read it too) and ``to_state()`` gives the reference's record. Not a
    pure value: the owner replaces it, never shares it."""

    __slots__ = ("_c", "_params", "_cp")

    def __init__(self, state):
        self._c = state if POLAR_HEADING_AVAILABLE and isinstance(state, _core.PolarHeading) else \
            _core.PolarHeading(_fields(state))
        self._params = self._cp = None

    def _p(self, params: _ph.PolarHeadingParams):
        """The converted params (converted again when the owner replaced them)."""
        if params is not self._params:
            self._params, self._cp = params, _core.PolarHeadingParams(params)
        return self._cp

    initialised = property(lambda self: self._c.initialised)
    time_s = property(lambda self: self._c.time_s)
    x = property(lambda self: self._c.x)
    P = property(lambda self: self._c.P)
    last_mag_time_s = property(lambda self: self._c.last_mag_time_s)
    source_available = property(lambda self: self._c.source_available)
    rejected_since_s = property(lambda self: self._c.rejected_since_s)
    n_fused = property(lambda self: self._c.n_fused)
    n_rejected = property(lambda self: self._c.n_rejected)
    n_resets = property(lambda self: self._c.n_resets)
    r_corr_avg_rad2 = property(lambda self: self._c.r_corr_avg_rad2)
    r_uncal_rad2 = property(lambda self: self._c.r_uncal_rad2)
    field_mismatch_gauss2 = property(lambda self: self._c.field_mismatch_gauss2)
    field_mismatch_time_s = property(lambda self: self._c.field_mismatch_time_s)
    platform = property(lambda self: self._c.platform)
    q_P_from_body = property(lambda self: self._c.q_P_from_body)
    gyro_bias_prev_rad_s = property(lambda self: self._c.gyro_bias_prev_rad_s)

    def to_state(self) -> _ph.PolarHeadingState:
        return _ph.PolarHeadingState(**self._c.get_state())

    def to_dict(self) -> dict:
        return self.to_state().to_dict()

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldPolarHeading, (self.to_state(),)


def _held_ph(state) -> HeldPolarHeading:
    return state if isinstance(state, HeldPolarHeading) else HeldPolarHeading(state)


def polar_heading_init(heading_rad: float | None = None, sigma_rad: float | None = None,
                       params: _ph.PolarHeadingParams = _ph.PolarHeadingParams(),
                       gyro_bias_yz_rad_s=None) -> HeldPolarHeading:
    """estimators.polar_heading.polar_heading_init, held in the core (same arguments and checks)."""
    by = bz = 0.0
    if gyro_bias_yz_rad_s is not None:
        b = np.asarray(gyro_bias_yz_rad_s, float)
        if b.shape != (2,) or not np.all(np.isfinite(b)):
            raise ValueError(f"gyro_bias_yz_rad_s must be 2 finite numbers, got {gyro_bias_yz_rad_s!r}")
        by, bz = b.tolist()
    has_b = gyro_bias_yz_rad_s is not None
    cp = _core.PolarHeadingParams(params)
    if heading_rad is None:
        return HeldPolarHeading(_core.PolarHeading.init(cp, False, 0.0, 0.0, has_b, by, bz))
    if not (math.isfinite(heading_rad) and sigma_rad is not None and math.isfinite(sigma_rad)
            and sigma_rad > 0.0):
        raise ValueError(f"heading_rad and sigma_rad > 0 must be finite, got {heading_rad}, {sigma_rad}")
    return HeldPolarHeading(_core.PolarHeading.init(cp, True, float(heading_rad), float(sigma_rad), has_b, by, bz))


def polar_heading_unseen(state, unseen_s: float, params: _ph.PolarHeadingParams = _ph.PolarHeadingParams()
                         ) -> HeldPolarHeading:
    """estimators.polar_heading.polar_heading_unseen for either state (held in the core after it)."""
    if not (math.isfinite(unseen_s) and unseen_s >= 0.0):
        raise ValueError(f"unseen_s must be finite and >= 0, got {unseen_s!r}")
    state = _held_ph(state)
    state._c.unseen(state._p(params), float(unseen_s))
    return state


def _ph_diag(t: tuple, u: _ph.HeadingInputs, params: _ph.PolarHeadingParams) -> _ph.HeadingDiag:
    code, sa, dt, H, z, nu, S, ratio, jump, why = t
    if code == _PH_MEASURED:
        if why == _PH_INITIALISED:
            vals = (True, True, True, H, z, 0.0, S, 0.0, False, 0.0, "initialised from source")
        elif why == _PH_RESET:
            vals = (True, False, True, H, z, nu, S, ratio, True, jump,
                    "re-initialised from the source after continuous rejection")
        else:
            vals = (True, why == _PH_FUSED, True, H, z, nu, S, ratio, False, 0.0,
                    "innovation gated out" if why == _PH_GATED_OUT else "")
        out = object.__new__(_ph.HeadingDiag)  # a frozen record without __post_init__
        out.__dict__.update(zip(_PH_DIAG_FIELDS, vals))
        return out
    if code == _PH_TIME:
        return _ph.HeadingDiag(reason=f"time not increasing (dt={dt:.6f} s)")
    if code == _PH_FIELD_WEAK:
        return _ph.HeadingDiag(measured=False, source_available=False, horizontal_field_gauss=H,
                               reason=f"horizontal field {H:.4f} G < {params.min_horizontal_field_gauss} G")
    if code == _PH_BAD_RESIDUAL:
        raise ValueError(f"mag_residual_sigma_gauss must be finite and >= 0 or None, got "
                         f"{u.mag_residual_sigma_gauss!r}")
    if code == _PH_BAD_FIELD_MODEL:
        raise ValueError(f"field_model_ned_gauss must be 3 finite numbers (NED, gauss), not all 0, or None, "
                         f"got {u.field_model_ned_gauss!r}")
    return _ph.HeadingDiag(reason=_PH_REASON[code], source_available=sa)


def polar_heading_step(state, u: _ph.HeadingInputs, params: _ph.PolarHeadingParams = _ph.PolarHeadingParams()
                       ) -> tuple[HeldPolarHeading, _ph.HeadingDiag]:
    """estimators.polar_heading.polar_heading_step with the state held in the core (a
    PolarHeadingState is taken in on the first call); the same results."""
    state = _held_ph(state)
    d = state._c.step(state._p(params), u)
    if d is None:  # an input the core does not take as it stands: the reference answers it
        st, diag = _ph.polar_heading_step(state.to_state(), u, params)
        state._c.set_state(_fields(st))
        return state, diag
    return state, (_PH_SIMPLE[d] if d.__class__ is int else _ph_diag(d, u, params))


def polar_heading_estimate(state) -> _ph.HeadingEstimate:
    """estimators.polar_heading.polar_heading_estimate for either state."""
    if not isinstance(state, HeldPolarHeading):
        return _ph.polar_heading_estimate(state)
    t = state._c.estimate()
    if t is None:
        return _ph.HeadingEstimate(math.nan, math.inf, state._c.source_available, False)
    return _ph.HeadingEstimate(t[0], t[1], t[2], True)


def polar_heading_attitude(state, heading_rad: float | None = None) -> np.ndarray | None:
    """estimators.polar_heading.polar_heading_attitude for either state (a heading that is not a
    finite number: the reference on the held state's record, which answers it)."""
    if not isinstance(state, HeldPolarHeading):
        return _ph.polar_heading_attitude(state, heading_rad)
    c = state._c
    if heading_rad.__class__ is float and math.isfinite(heading_rad):
        return c.attitude(heading_rad)   # None there outside the platform formulation, as below
    if not (c.platform and c.initialised and c.q_P_from_body is not None):
        return None
    if heading_rad is None:
        heading_rad = polar_heading_estimate(state).heading_rad
    if not (isinstance(heading_rad, (float, int)) and math.isfinite(heading_rad)):
        return _ph.polar_heading_attitude(state.to_state(), heading_rad)
    return c.attitude(float(heading_rad))


def heading_zero_rate_update(state, rate: _zr.RestRate, params: _zr.ZeroRateParams = _zr.ZeroRateParams()):
    """estimators.zero_rate.heading_zero_rate_update for either state: on a held state the core's
    (core/zero_rate.hpp), else (an older build) the reference's update on the held state's record."""
    if not isinstance(state, HeldPolarHeading):
        return _zr.heading_zero_rate_update(state, rate, params)
    if ZERO_RATE_AVAILABLE:
        return heading_zero_rate_update_core(state, rate, params)
    st, diag = _zr.heading_zero_rate_update(state.to_state(), rate, params)
    if diag.fused:
        state._c.set_state(_fields(st))
    return state, diag


# --- the Pipeline's per-sample hot path (service/hot_path.py, core/hot_path.hpp) -------------------
# SampleState: the Pipeline's per-sample fields (its attributes of those names are properties over
# it); AzimuthRun: method A's per-sample state for one run; hot_run: a batch's quiet samples.

HOT_PATH_AVAILABLE = AVAILABLE and hasattr(_core, "hot_run")
if HOT_PATH_AVAILABLE:
    SampleState = _core.SampleState
    AzimuthRun = _core.AzimuthRun
    hot_run = _core.hot_run
    if hasattr(_core, "HotPath"):   # hot_run with the Pipeline's fixed inputs bound once (service/hot_path.py)
        HotPath, HOT_QUIET, HOT_UNREAD = _core.HotPath, _core.HOT_QUIET, _core.HOT_UNREAD


AZIMUTH_OUTPUT_AVAILABLE = HOT_PATH_AVAILABLE and hasattr(_core, "azimuth_output_numbers")
"""Method A's output numbers in the core (core/azimuth_output.hpp) and its filter-step sample on a held run."""


def azimuth_output_cfg(st) -> tuple:
    """What method A's output needs of the AzimuthState ``st`` (in flight) beside G and C_ISF<-SF: fixed
    between two solves (core/bindings_hot_path.cpp azimuth_cfg_in reads it)."""
    p, sol = st.params, st.solution
    C_sf_body = p.C_body_from_sensor.T
    if sol is None:
        return (False, st.C_isf_af, C_sf_body, None, None, None, None, 0.0, 0.0, 0.0, 0.0, 0.0, None, False, None,
                None)
    from estimators.azimuth import N_GYRO_CONSIDER as K
    u = st.u_sf
    return (True, st.C_isf_af, C_sf_body, sol.C_nf_af, sol.C_af_isf, sol.c_gyro, sol.fit.P_psi_c,
            p.gyro_arw_rad_sqrt_s ** 2, float(st.launch_time_s), p.field_model_sigma_rad ** 2 + sol.wander_var_rad2,
            float(sol.last_sample_s), p.gyro_bias_sigma_rad_s, u,
            u is not None and bool(np.array_equal(u, C_sf_body[:, 0])), st.du_dbeta_sf,
            sol.fit.c_hat[K:K + 2] if st.du_dbeta_sf is not None else (0.0, 0.0))


def azimuth_output_numbers(st, G_gyro: np.ndarray, C_isf_sf: np.ndarray, time_s: float) -> tuple:
    """estimators.azimuth.azimuth_output_numbers in the core (core/azimuth_output.hpp): the same arguments and tuple."""
    return _core.azimuth_output_numbers(azimuth_output_cfg(st), G_gyro, C_isf_sf, float(time_s))


def mag_hard_iron_residual(state, mag_body_gauss, q_P_from_body, soft_iron: float) -> float | None:
    """service/pipeline.py Pipeline._mag_hard_iron_residual on a MagDisturbance state held in the
    core (HeldMagDisturbance: the hard iron's covariance read there, core/bindings_hot_path.cpp): the
    same figure to rounding, None without that covariance or a horizontal field. The caller checks
    MAG_HARD_IRON_RESIDUAL_AVAILABLE (an older build: the reference runs)."""
    return _core.mag_hard_iron_residual(state._c, mag_body_gauss, q_P_from_body, soft_iron)


MAG_HARD_IRON_RESIDUAL_AVAILABLE = AVAILABLE and hasattr(_core, "mag_hard_iron_residual")
GROUND_AVAILABLE = HOT_PATH_AVAILABLE and hasattr(_core, "GroundState")
"""The ground (pre-launch) path in the core (core/ground.hpp: GroundState, hot_run's ground run)."""
if GROUND_AVAILABLE:
    GroundState = _core.GroundState


# --- method A's re-solve (estimators/azimuth_fit.py fit_psi, core/azimuth_fit.hpp) ---------------
# The stored samples go in as contiguous arrays, the whole solve (profile scan, Gauss-Newton, the
# covariances, the joint error estimate) runs in one C++ call; the FitResult is built here.

FIT_AVAILABLE = AVAILABLE and hasattr(_core, "azimuth_fit")
_MODEL_CODE = {"none": 0, "seed7": 1, "full12": 2}


def fit_psi(data, C_isf_af: np.ndarray, e_ned: np.ndarray, model: str = "seed7", grid_points: int = 36,
            max_iterations: int = 20, tol_rad: float = 1e-12, P_prior: np.ndarray | None = None,
            estimate_errors: bool = False):
    """estimators.azimuth_fit.fit_psi in the core: the same arguments and the same FitResult."""
    from estimators import azimuth_fit as _af
    if model not in _af.MODELS:
        raise ValueError(f"model must be one of {_af.MODELS}, got {model!r}")
    h = np.asarray(data.h_sf_gauss, float)
    N = len(h)
    p = _af.n_unknowns(model)
    K = 0 if data.G_gyro is None else data.G_gyro.shape[2]
    o = _core.azimuth_fit(data.C_sf_from_isf, h, data.var_white_gauss2, data.weight, data.G_gyro, C_isf_af,
                          e_ned, _MODEL_CODE[model], int(grid_points), int(max_iterations), float(tol_rad),
                          P_prior, bool(estimate_errors))
    if not o["ok"]:
        reason = (f"{N} samples give {3 * N} equations for {p} unknowns" if o["code"] == 1 else
                  f"{o['n_bad']} of {N} samples not finite" if o["code"] == 3 else "least squares did not converge")
        return _af.FitResult(False, model, math.nan, np.full(p, math.nan), np.eye(3), np.zeros(3),
                             np.full((p, p), math.nan), np.zeros((p, K + _af.N_TILT)), math.nan, math.nan,
                             math.inf, N, 0, reason)
    theta = o["theta"]
    psi, A, b = _af.unpack(model, theta)
    return _af.FitResult(True, model, psi, theta, A, b, o["cov_white"], o["S"], o["s2"], o["residual_rms"],
                         o["cond"], N, o["iterations"], c_hat=o["c_hat"], P_psi_c=o["P_psi_c"],
                         psi_sigma_gate_rad=o["psi_sigma_gate"])


DIVERSITY_AVAILABLE = AVAILABLE and hasattr(_core, "orientation_diversity")


def orientation_diversity_rad(C_sf_from_af: np.ndarray, psi_rad: float, e_ned: np.ndarray) -> float:
    """estimators.azimuth_fit.orientation_diversity_rad in the core: the same number from one O(N^2) C++
    loop, without the reference's N x N array (at A's 1500 samples it cost more than the core's fit)."""
    return _core.orientation_diversity(C_sf_from_af, float(psi_rad), e_ned)


# --- method D's deviation RLS (estimators/mag_deviation.py, core/mag_deviation.hpp) ---------------
# The state is held in the core between observations (HeldDeviation); it reads like the reference's
# DeviationState (coeffs, P, n, resid_sq_sum, n_resid, the coverage counts, to_dict), so the
# reference's functions, the daemon's file and the tests read it unchanged.

DEVIATION_AVAILABLE = AVAILABLE and hasattr(_core, "Deviation")


class HeldDeviation:
    """A DeviationState held in the core. Not a pure value: ``deviation_step`` steps a copy (the
    reference's step returns a new state, the caller's old one stays as it was)."""

    __slots__ = ("_c",)

    def __init__(self, state):
        if isinstance(state, HeldDeviation):
            self._c = state._c.copy()
            return
        for name in ("heading_counts", "roll_counts", "pitch_counts"):
            if getattr(state, name) is None:
                raise ValueError(f"deviation state without {name}")
        self._c = _core.Deviation(state.coeffs, state.P, int(state.n), state.resid_sq_sum, int(state.n_resid),
                                  state.heading_counts, state.roll_counts, state.pitch_counts)

    coeffs = property(lambda self: self._c.coeffs)
    P = property(lambda self: self._c.P)
    n = property(lambda self: self._c.n)
    resid_sq_sum = property(lambda self: self._c.resid_sq_sum)
    n_resid = property(lambda self: self._c.n_resid)
    heading_counts = property(lambda self: self._c.heading_counts)
    roll_counts = property(lambda self: self._c.roll_counts)
    pitch_counts = property(lambda self: self._c.pitch_counts)

    def to_state(self):
        from estimators.mag_deviation import DeviationState
        return DeviationState(self.coeffs, self.P, int(self.n), self.resid_sq_sum, int(self.n_resid),
                              self.heading_counts, self.roll_counts, self.pitch_counts)

    def to_dict(self) -> dict:
        return self.to_state().to_dict()


def deviation_step(state, mag_body_gauss, field_ned_gauss, heading_rad: float, roll_rad: float, pitch_rad: float,
                   params=None):
    """estimators.mag_deviation.deviation_step in the core: takes the reference's state or a held one,
    returns (a held state, DeviationDiag) with the reference's numbers and reasons."""
    from estimators import mag_deviation as _dv
    params = _dv.DeviationParams() if params is None else params
    m = np.asarray(mag_body_gauss, float)
    F = np.asarray(field_ned_gauss, float)
    if m.shape != (3,) or F.shape != (3,):
        raise ValueError("mag_body_gauss and field_ned_gauss must have shape (3,)")
    new = HeldDeviation(state)
    code, e = new._c.step(m, F, float(heading_rad), float(roll_rad), float(pitch_rad), params.forgetting_factor,
                          params.roll_limit_rad, params.pitch_limit_rad, params.heading_bins, params.roll_bins,
                          params.pitch_bins)
    if code == 1:
        return state, _dv.DeviationDiag(False, reason="non-finite input")
    if code == 2:
        return state, _dv.DeviationDiag(False, reason="outside the calibration roll/pitch limits")
    return new, _dv.DeviationDiag(True, residual_gauss=e)


def corrected_mag(state, mag_body_gauss, heading_rad: float, roll_rad: float, pitch_rad: float) -> np.ndarray:
    """estimators.mag_deviation.corrected_mag (a held state in the core; the reference's in the reference)."""
    if not isinstance(state, HeldDeviation):
        from estimators import mag_deviation as _dv
        return _dv.corrected_mag(state, mag_body_gauss, heading_rad, roll_rad, pitch_rad)
    return state._c.corrected(np.asarray(mag_body_gauss, float), float(heading_rad), float(roll_rad),
                              float(pitch_rad))


def residual_sigma_gauss(state) -> np.ndarray:
    """estimators.mag_deviation.residual_sigma_gauss (either state)."""
    if not isinstance(state, HeldDeviation):
        from estimators import mag_deviation as _dv
        return _dv.residual_sigma_gauss(state)
    return state._c.residual_sigma()


def deviation_coverage(state, params=None):
    """estimators.mag_deviation.deviation_coverage (either state)."""
    from estimators import mag_deviation as _dv
    params = _dv.DeviationParams() if params is None else params
    if not isinstance(state, HeldDeviation):
        return _dv.deviation_coverage(state, params)
    return _dv.Coverage(*state._c.coverage(params.min_samples_per_bin))


# --- method C's rest detection (estimators/zero_rate.py rest_step) ---------------------------------
# Held in the core between filter steps (HeldZeroRate, core/zero_rate.hpp); the reference's
# ZeroRateState is built only when asked (to_state: a copy, a test).

ZERO_RATE_AVAILABLE = AVAILABLE and hasattr(_core, "ZeroRate")


class HeldZeroRate:
    """A ZeroRateState held in the core, stepped in place by ``rest_step``; it reads like the
    reference's state where the service reads it (``time_s``) and ``to_state()`` gives the reference's
    record. Not a pure value: the owner replaces it, never shares it."""

    __slots__ = ("_c", "_params", "_cp")

    def __init__(self, state: _zr.ZeroRateState):
        self._c = _core.ZeroRate(state)
        self._params = self._cp = None

    def _p(self, params: _zr.ZeroRateParams):
        if params is not self._params:
            self._params, self._cp = params, _core.ZeroRateParams(params)
        return self._cp

    time_s = property(lambda self: self._c.time_s)

    def to_state(self) -> _zr.ZeroRateState:
        return _zr.ZeroRateState(**self._c.get_state())

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldZeroRate, (self.to_state(),)


def rest_step(state: _zr.ZeroRateState | HeldZeroRate, time_s: float, gyro_body_rad_s, accel_body_m_s2,
              params: _zr.ZeroRateParams = _zr.ZeroRateParams()) -> tuple[HeldZeroRate, _zr.RestRate | None]:
    """estimators.zero_rate.rest_step with the state held in the core (a ZeroRateState is taken in on
    the first call); the same results."""
    w = np.asarray(gyro_body_rad_s, float)
    f = np.asarray(accel_body_m_s2, float)
    if w.shape != (3,) or f.shape != (3,):
        raise ValueError(f"gyro_body_rad_s and accel_body_m_s2 must have shape (3,), got {w.shape}, {f.shape}")
    if not isinstance(state, HeldZeroRate):
        state = HeldZeroRate(state)
    r = state._c.step(state._p(params), float(time_s), *w.tolist(), *f.tolist())
    return state, None if r is None else _zr.RestRate(*r)


def _zr_diag(code: int, ratio: float, not_ready: str) -> _zr.ZeroRateDiag:
    if code == 0:
        return _zr.ZeroRateDiag(True, ratio)
    return _zr.ZeroRateDiag(reason=not_ready) if code == 1 else _zr.ZeroRateDiag(test_ratio=ratio,
                                                                                 reason="rest rate gated out")


def attitude_zero_rate_update_core(state, rate: _zr.RestRate, params: _zr.ZeroRateParams = _zr.ZeroRateParams()):
    """estimators.zero_rate.attitude_zero_rate_update in the core (core/zero_rate.hpp) on the held state:
    what the filter chain runs (tests/test_core_zero_rate.py proves it equal to the reference)."""
    state = _held_pa(state)
    code, ratio = _core.attitude_zero_rate_update(state._c, rate, _core.ZeroRateParams(params))
    return state, _zr_diag(code, ratio, "attitude filter not levelled")


def heading_zero_rate_update_core(state, rate: _zr.RestRate, params: _zr.ZeroRateParams = _zr.ZeroRateParams()):
    """estimators.zero_rate.heading_zero_rate_update in the core (core/zero_rate.hpp) on the held state."""
    state = _held_ph(state)
    code, ratio = _core.heading_zero_rate_update(state._c, rate, _core.ZeroRateParams(params))
    return state, _zr_diag(code, ratio, "heading filter not in the platform formulation")


# --- method C's filter step with its magnetometer chain (core/filter_chain.hpp) -------------------
# service/pipeline.py Pipeline._filter_chain_python (the reference) as one C++ call on the held states.

FILTER_CHAIN_AVAILABLE = (ZERO_RATE_AVAILABLE and hasattr(_core, "filter_chain") and POLAR_AVAILABLE
                          and POLAR_HEADING_AVAILABLE and MAG_DISTURBANCE_AVAILABLE and MAG_USABILITY_AVAILABLE
                          and DEVIATION_AVAILABLE)


class ChainOut(NamedTuple):
    """What the Pipeline needs of a filter step after the chain."""
    att: object            # AttitudeEstimate or None
    mag_s: object          # the magnetometer for B (sensor axes) or None
    mag_raw: bool          # undisturbed and usable (D learns on the measured field)
    hdiag: object          # HeadingDiag, None when the heading filter did not step (no tilt)
    events: list           # [(kind, text)] in the reference's order
    mag_status: object     # the Pipeline's new mag_status, None: unchanged
    dev_hard_iron_changed: bool
    dev_in_use: object     # None / False / True


def filter_chain_step(att: HeldPolarAttitude, att_params, zr: HeldZeroRate, zr_params, md: HeldMagDisturbance,
                      md_params, mu: HeldMagUsability, mu_params, hdg: HeldPolarHeading, hdg_params,
                      dev: HeldDeviation | None, t: float, gyro_b, accel_b, mag_b, C_body_from_sensor,
                      fc_tilt, fc_sigma_tilt_rad: float, fc_tilt_max_age_s: float, declination_rad: float,
                      declination_sigma_rad: float, field_model_ned_gauss, dev_apply: bool, dev_min_coverage: float,
                      dev_min_samples_per_bin: int, dev_hard_iron_changed: bool, dev_in_use) -> ChainOut:
    """One filter step of method C in the core on the held states (each stepped in place). ``fc_tilt``:
    (time_s, roll, pitch) of the FC's ATTITUDE while method B trusts it, else None."""
    r = _core.filter_chain(att._c, att._p(att_params), zr._c, zr._p(zr_params), md._c, md._p(md_params), mu._c,
                           mu._p(mu_params), hdg._c, hdg._p(hdg_params), None if dev is None else dev._c, t, gyro_b,
                           accel_b, mag_b, C_body_from_sensor, fc_tilt, fc_sigma_tilt_rad, fc_tilt_max_age_s,
                           declination_rad, declination_sigma_rad, field_model_ned_gauss, dev_apply, dev_min_coverage,
                           dev_min_samples_per_bin, dev_hard_iron_changed, dev_in_use)
    e, d = r[0], r[3]
    if e is not None:
        est = object.__new__(_pa.AttitudeEstimate)  # a frozen record without __post_init__
        est.__dict__.update(zip(_AE_FIELDS, e))
        e = est
    if d is not None:
        d = _PH_SIMPLE[d] if d.__class__ is int else _ph_diag(d, None, hdg_params)
    md._t = md._c.time_s
    return ChainOut(e, r[1], r[2], d, r[4], r[5], r[6], r[7])


# --- the filter step's solution numbers (core/solution.hpp) ----------------------------------------
# service/pipeline.py Pipeline._solution (the reference) reads C's roll/pitch, their sigmas, the heading
# rate and C's heading from the held filters: here in one C++ call.

SOLUTION_AVAILABLE = POLAR_AVAILABLE and POLAR_HEADING_AVAILABLE and hasattr(_core, "solution_numbers")


def solution_numbers(att: HeldPolarAttitude, hdg: HeldPolarHeading, time_s: float, prev, rates_body) -> tuple | None:
    """None before C's attitude filter levelled, else (roll, pitch, roll sigma, pitch sigma, yaw of its
    q_P_from_body, heading rate or None, C's heading: None before its first, else (heading, published
    variance, source_available, rejected_since_s, last_mag_time_s)). ``prev``: (time, yaw of q_P_from_body)
    of the last solution or None; ``rates_body``: the body rates less the gyro bias (rad/s, (3,))."""
    x, y, z = rates_body.tolist()
    if prev is None:
        return _core.solution_numbers(att._c, hdg._c, time_s, False, 0.0, 0.0, x, y, z)
    return _core.solution_numbers(att._c, hdg._c, time_s, True, prev[0], prev[1], x, y, z)
