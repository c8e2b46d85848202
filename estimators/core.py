"""The compiled core's Python face (estimators._core, built from core/ by scikit-build-core).

The Python implementations in estimators/ stay the reference: every function here has the same
signature and returns the same values as the reference it names (tests/test_core_*.py run both
on the same recorded flights and require equality). Two call forms:

- drop-in per-sample steps (``strapdown_step``, ``levelling_step``) for callers that still step
  one sample at a time;
- batch calls (``strapdown_propagate``, ``levelling_accumulate``): typed N x 3 numpy arrays in,
  one C++ loop, arrays out; no per-sample Python.

``AVAILABLE`` says whether the extension imported; ``IMPORT_ERROR`` says why not (the service
logs it and runs the Python reference: service/core_backend.py). Pure: no I/O, no clocks.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from estimators import levelling as _lev
from estimators import strapdown as _sd
from estimators.levelling import LevellingState
from estimators.strapdown import StrapdownDiag, StrapdownParams, StrapdownState

try:
    from estimators import _core
    AVAILABLE, IMPORT_ERROR = True, ""
except ImportError as exc:  # a build that failed or a foreign platform: the reference runs
    _core, AVAILABLE, IMPORT_ERROR = None, False, f"{type(exc).__name__}: {exc}"

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
