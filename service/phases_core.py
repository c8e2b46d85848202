"""The flight phases (service/phases.py phase_step) held in the compiled core (core/phases.hpp,
estimators._core.Phases): the service-side facade, beside the reference it wraps. It lives in
service/ because the phases do: estimators/ imports no service module (estimators/core.py holds
the estimators' facades and what they share: the extension, the levelling accumulator's packing)."""
from __future__ import annotations

import dataclasses

import numpy as np

from estimators import levelling as _lev
from estimators.core import AVAILABLE, _core, levelling_pack, levelling_unpack
from service import phases

# --- the flight phases (service/phases.py phase_step) ----------------------------------------------
# Held in the core between IMU samples (HeldPhaseState): pre-launch blocks, levelling, take-off,
# the started-in-flight rule, every sample on the ground. The core words the events itself, as the
# reference does (core/phases.hpp: printf's %.Nf, and Python's own texts of the :g thresholds). An
# input the core does not take as it stands (not a float64 (3,) array, a time that is not a float,
# evidence that is not numbers / None) comes back untouched and the reference answers it on the held
# state's record.

PHASES_AVAILABLE = AVAILABLE and hasattr(_core, "Phases")
_PHASE_NAMES = ("boot", "pre-launch", "launch", "in-flight")
_SP = None
_PHASE_FIELDS: tuple = ()
_LEV_FIELDS = ("block", "level_block", "pending_block", "noisy_run")
_RESULT_FIELDS = ("level", "pending_level")


def _sp():
    """service.phases (the reference)."""
    global _SP, _PHASE_FIELDS, _DEFAULT_PHASE_PARAMS
    if _SP is None:
        _SP, _PHASE_FIELDS = phases, tuple(f.name for f in dataclasses.fields(phases.PhaseState))
        _DEFAULT_PHASE_PARAMS = phases.PhaseParams()
    return _SP


_DEFAULT_PHASE_PARAMS = None


def _phase_fields(state) -> dict:
    """A PhaseState's fields as the core takes them (levelling accumulators packed)."""
    _sp()
    d = {name: getattr(state, name) for name in _PHASE_FIELDS}
    for k in _LEV_FIELDS:
        if d[k] is not None:
            d[k] = levelling_pack(d[k])
    return d


def _lev_result(t: tuple | None) -> _lev.LevellingResult | None:
    """The core's passing levelling (core/bindings_phases.cpp result_out) -> the reference's record."""
    if t is None:
        return None
    return _lev.LevellingResult(True, "", *t)


class HeldPhaseState:
    """A PhaseState held in the core, stepped in place by ``phase_step``; it reads like the
    reference's state (every PhaseState field; the ones the Pipeline reads per sample straight from
    the core, the rest through ``to_state()``), and ``to_state()`` gives the reference's record. Not a
    pure value: the owner replaces it, never shares it."""

    __slots__ = ("_c", "_params", "_cp", "phase", "started_in_flight", "_lv", "_level", "_level_block")

    def __init__(self, state=None):
        self._c = _core.Phases(_phase_fields(_sp().PhaseState() if state is None else state))
        self._params = self._cp = None
        self._lv = -1
        self._sync()

    def _sync(self) -> None:
        """The phase and the started-in-flight flag (Python attributes: read several times a sample)."""
        self.phase = _PHASE_NAMES[self._c.phase]
        self.started_in_flight = self._c.started_in_flight

    def _p(self, params):
        """The converted params (converted again when the owner replaced them)."""
        if params is not self._params:
            self._params, self._cp = params, _core.PhaseParams(params)
        return self._cp

    def _levels(self) -> None:
        if self._lv != self._c.level_version:
            lb = self._c.level_block
            self._level = _lev_result(self._c.level)
            self._level_block = None if lb is None else levelling_unpack(lb)
            self._lv = self._c.level_version

    @property
    def level(self) -> _lev.LevellingResult | None:
        self._levels()
        return self._level

    @property
    def level_block(self) -> LevellingState | None:
        self._levels()
        return self._level_block

    block_start_s = property(lambda self: self._c.block_start_s)
    block_passed_s = property(lambda self: self._c.block_passed_s)
    launch_time_s = property(lambda self: self._c.launch_time_s)
    level_time_s = property(lambda self: self._c.level_time_s)
    start_time_s = property(lambda self: self._c.start_time_s)
    moved_rad = property(lambda self: self._c.moved_rad)
    launch_evidence = property(lambda self: self._c.launch_evidence)
    in_flight_evidence = property(lambda self: self._c.in_flight_evidence)

    def __getattr__(self, name: str):  # the other PhaseState fields (not read per sample)
        if name.startswith("_") or name not in _PHASE_FIELDS:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(self.to_state(), name)

    def to_state(self):
        d = self._c.get_state()
        for k in _LEV_FIELDS:
            if d[k] is not None:
                d[k] = levelling_unpack(d[k])
        for k in _RESULT_FIELDS:
            d[k] = _lev_result(d[k])
        return _sp().PhaseState(**d)

    def set_state(self, state) -> None:
        self._c.set_state(_phase_fields(state))
        self._sync()

    def __reduce__(self):  # copy.deepcopy / pickle: through the reference's record (exact)
        return HeldPhaseState, (self.to_state(),)


def phase_step(state, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, time_s: float, params=None,
               evidence=None) -> tuple[HeldPhaseState, list[tuple[str, str]]]:
    """service.phases.phase_step with the state held in the core (a PhaseState is taken in on the
    first call); the same results and events. ``params`` None: the reference's default PhaseParams()."""
    if params is None:
        _sp()
        params = _DEFAULT_PHASE_PARAMS
    held = state if isinstance(state, HeldPhaseState) else HeldPhaseState(state)
    r = held._c.step(held._p(params), gyro_rad_s, accel_m_s2, time_s, evidence)
    if r.__class__ is int:  # no event: the phase did not change
        return held, []
    if r is None:  # an input the core does not take as it stands: the reference answers it
        st, events = _sp().phase_step(held.to_state(), gyro_rad_s, accel_m_s2, time_s, params, evidence)
        held.set_state(st)
        return held, events
    held._sync()
    return held, r
