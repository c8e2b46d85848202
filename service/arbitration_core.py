"""The heading arbitration (service/heading_arbitration.py arbitrate) in the compiled core
(core/heading_arbitration.hpp, estimators._core.arbitrate): the service-side facade, beside the
reference it wraps (estimators/ imports no service module; service/phases_core.py is the same
pattern).

``arbitrate`` has the reference's signature and gives the same objects: an ArbitrationState (a pure
value, as the reference's: nothing is held between calls), an ArbitrationOutput with its
ArbitrationEvents and one AidingRecord per source, reasons and event messages worded here as the
reference words them from the core's codes and numbers. The core reads the reference's
ArbitrationState and SourceReadings as they stand; what it does not take as it stands (a number that
is not a float, a time that is not one, a name or group that is not a str, two readings of one name,
a state made by hand with a fusion and no sources) comes back untouched and the reference answers it,
which answers as it answers (tests/test_core_arbitration.py)."""
from __future__ import annotations

import math

from estimators.core import AVAILABLE, _core
from service import heading_arbitration as _ha
from service.aiding import WHY_NOT, AidingRecord
from service.heading_arbitration import ArbitrationEvent, ArbitrationOutput, ArbitrationParams, ArbitrationState

ARBITRATION_AVAILABLE = AVAILABLE and hasattr(_core, "arbitrate")

# core/heading_arbitration.hpp Why, EventKind, OutKind
_NOT_VALID, _INCONSISTENT = 1, 2
_EVENT_KIND = ("lost", "majority", "reset", "acquired", "source_change", "reset")
_FUSED, _COAST, _NO_SOURCE = range(3)
_NAN = math.nan
_params_seen: tuple = (None, None)
"""(the last ArbitrationParams converted, the core's copy): the Pipeline's never change."""


def _core_params(params: ArbitrationParams):
    """The core's copy of ``params`` (None: a priority that is not a tuple or list, the reference runs)."""
    global _params_seen
    if _params_seen[0] is not params:
        if not isinstance(params.priority, (tuple, list)):
            return None
        _params_seen = (params, _core.ArbitrationParams(params))
    return _params_seen[1]


def _why(why: int, r) -> tuple[str, str]:
    """(code, detail) of a reading whose code is the caller's (not valid, inconsistent), as the
    reference words them; ("", "") for a candidate with no reason (the record refuses it, as the
    reference's does). The core words the others (core/bindings_arbitration.cpp)."""
    if why == _NOT_VALID:
        return r.why_code or "not_valid", f"not valid: {r.why_not}" if r.why_not else "not valid"
    if why == _INCONSISTENT:
        return (r.why_code or "inconsistent",
                f"inconsistent: {r.why_not}" if r.why_not else "inconsistent with its own measurements")
    return "", ""


def _event(e: tuple, state: ArbitrationState, time_s, params: ArbitrationParams) -> ArbitrationEvent:
    kind, to, jump, dt = e
    names = "+".join(to)
    if kind == 0:
        return ArbitrationEvent(time_s, "lost", state.sources, (), 0.0, "no heading source available")
    if kind == 1:
        return ArbitrationEvent(time_s, "majority", state.sources, to, 0.0,
                                f"published heading disagrees with a consistent majority ({names}): re-acquired from it")
    if kind == 2:
        return ArbitrationEvent(time_s, "reset", state.sources, to, jump,
                                f"heading re-acquired from {names} after {dt:.1f} s without output: "
                                f"jump {math.degrees(jump):+.2f} deg (not blended: the heading was unknown meanwhile)")
    if kind == 3:
        return ArbitrationEvent(time_s, "acquired", (), to, 0.0, f"heading from {names}")
    return ArbitrationEvent(time_s, _EVENT_KIND[kind], state.sources, to, jump,
                            f"heading source {'+'.join(state.sources) or 'none'} -> {names}: "
                            f"jump {math.degrees(jump):+.2f} deg, blended at <= "
                            f"{math.degrees(params.blend_rate_rad_s):.1f} deg/s")


_make_record = AidingRecord._make
"""An AidingRecord built without its checks (a tenth of the cost), for a code the caller gave (a
reading's ``why_code``, a NotOffered's ``why_not``) that is one of WHY_NOT (not "": none of these is
fused): a code that is not goes through AidingRecord's checks, which refuse it as the reference's do."""


def _record(r, time_s, p: tuple) -> AidingRecord:
    """The record of a reading whose code is the caller's (``why_code``): one that is not of WHY_NOT
    (or none) goes through AidingRecord's checks."""
    candidate, used, why, nis, innov, innov_var, ratio, last = p
    code, detail = _why(why, r)
    values = (r.name, time_s, code, detail, candidate, used, last, r.heading_rad, r.sigma_rad, innov, innov_var, ratio,
              r.source_innovation_rad, r.source_innovation_variance_rad2, r.source_test_ratio)
    if code and code.__class__ is str and code in WHY_NOT:
        return _make_record(values)
    return AidingRecord(*values)


def _not_offered_record(n, time_s, last: float) -> AidingRecord:
    why = n.why_not
    if why and why.__class__ is str and why in WHY_NOT:
        return _make_record((n.source, time_s, why, n.detail, False, False, last, _NAN, _NAN, _NAN, _NAN, _NAN,
                             _NAN, _NAN, _NAN))
    return AidingRecord(n.source, time_s, why, n.detail, time_last_fused_s=last)


def _frozen(cls, **fields):
    """A frozen dataclass record without running its __init__ (no __post_init__ to skip: the
    ArbitrationState and ArbitrationOutput have none), as estimators/core.py builds its records."""
    out = object.__new__(cls)
    out.__dict__.update(fields)
    return out


def arbitrate(state: ArbitrationState, readings: list, time_s: float,
              params: ArbitrationParams = ArbitrationParams(),
              heading_rate_rad_s: float | None = None,
              not_offered: tuple = ()) -> tuple[ArbitrationState, ArbitrationOutput]:
    """service.heading_arbitration.arbitrate in the core (same arguments, same results)."""
    if not math.isfinite(time_s):
        raise ValueError(f"time_s must be finite, got {time_s}")
    cp = _core_params(params) if isinstance(time_s, float) else None
    res = None if cp is None else _core.arbitrate(cp, state, readings, time_s, heading_rate_rad_s, not_offered,
                                                  AidingRecord)
    if res is None:   # a value the core does not take as it stands: the reference answers it
        return _ha.arbitrate(state, readings, time_s, params, heading_rate_rad_s, not_offered)
    (fused, var, offset, sources, gated_since, last), kind, heading, sigma, names, out_offset, events, per, no_last = res
    records = {}
    for n, t_last in zip(not_offered, no_last):
        records[n.source] = _not_offered_record(n, time_s, t_last)
    for r, p in zip(readings, per):
        records[r.name] = p if p.__class__ is AidingRecord else _record(r, time_s, p)
    evs = tuple(_event(e, state, time_s, params) for e in events) if events else ()
    if kind == _FUSED:
        st = _frozen(ArbitrationState, time_s=time_s, fused_rad=fused, fused_var_rad2=var, offset_rad=offset,
                     sources=names, gated_since_s=None, last_fused_s=last)
        source = "+".join(names)
    elif kind == _COAST:
        st = _frozen(ArbitrationState, time_s=time_s, fused_rad=fused, fused_var_rad2=var, offset_rad=offset,
                     sources=state.sources, gated_since_s=gated_since, last_fused_s=state.last_fused_s)
        source = "coast"
    else:
        st = _frozen(ArbitrationState, time_s=time_s, fused_rad=None, fused_var_rad2=math.inf, offset_rad=0.0,
                     sources=(), gated_since_s=None, last_fused_s=state.last_fused_s)
        return st, _frozen(ArbitrationOutput, heading_rad=None, sigma_rad=math.inf, source="none", valid=False,
                           offset_rad=0.0, events=evs, records=records)
    return st, _frozen(ArbitrationOutput, heading_rad=heading, sigma_rad=sigma, source=source, valid=True,
                       offset_rad=out_offset, events=evs, records=records)
