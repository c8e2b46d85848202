"""Heading arbitration: one published heading, its sigma and its source, from the available
heading sources (azimuth method A, synthetic AHRS B, heading filter C, the FC's own when trusted).

Pure (no I/O, no clock): ``arbitrate(state, readings, time_s, params, heading_rate_rad_s=None,
not_offered=()) -> (state, output)``; the daemon calls it once per output cycle. Every source,
offered or not, gets one aiding record in ``output.records`` (service/aiding.py: its innovation
against the reference, test ratio, fused or the stable code of why not, time of its last fusion).

The rule
--------
1. Candidates: readings that are ``valid``, finite, with 0 < sigma <= ``max_sigma_rad`` and no
   older than ``max_age_s``.
2. Reference: the previous fused heading propagated to now with the heading rate (from the
   gyros, when the caller gives it; variance + (rate_sigma dt)^2, + (max_turn_rate (dt -
   rate_max_dt))^2 over an interval longer than a rate sample covers), else held with the variance
   grown by (max_turn_rate dt)^2. On the first call (or after every source was lost) the
   reference is the best candidate (smallest sigma, then ``priority``). So it is after an
   interval longer than ``max_age_s`` without a call (an input gap: neither the rate given now
   nor the old fusion says anything about the turn during the gap): a 'reset' event reports the
   jump from the held heading, and the jump is not blended (step 6): the heading was unknown.
3. Gate: a candidate passes if its normalised innovation against the reference,
   wrap(h_i - ref)^2 / (sigma_i^2 + sigma_ref^2), is <= ``gate_chi2`` (chi-square, 1 dof).
4. Correlated sources: readings that share a ``group`` (e.g. B and C both use the magnetometer;
   B's magnetometer errors and alignment are learnt against the FC's yaw) are not independent, and
   their correlation is not known. Fusing them as independent (1/var = sum 1/var_i) understates the
   variance: two readings that both carry the same error e (var s^2) fuse to var s^2/2 while the
   error is still e. With an unknown correlation the consistent rule is covariance intersection
   (Julier & Uhlmann 1997): var_CI^-1 = w var_1^-1 + (1 - w) var_2^-1, mean likewise weighted,
   w in [0, 1] chosen to minimise var_CI. For scalars var_CI(w) = 1 / (w/v1 + (1-w)/v2) is
   monotonic in w, so its minimum is at an end: w = 1 if v1 < v2 -- CI of scalar readings IS
   "take the smaller-variance reading". Hence: per shared group only the smallest-sigma passing
   reading is fused, and the fused sigma of readings that share a group is never below the
   smallest of their sigmas (the bound the tests check). A reading may be in several groups
   (``group`` a tuple of names); the selection is greedy in rank order: a reading is fused if it
   shares no group with a better reading already chosen. Readings in no common group are fused as
   independent (step 5).
5. Fusion: inverse-variance weighting in the circular domain about the reference,
       h = ref + sum(w_i wrap(h_i - ref)) / sum(w_i),  w_i = 1/sigma_i^2,  var = 1/sum(w_i).
6. No silent jumps: when the set of fused sources changes, the jump between the new fusion and
   the old set evaluated now (its readings when every one of them is still offered, else the
   old fusion propagated: the reference) is reported as an event and absorbed into an offset; the
   published heading is fused + offset, and the offset decays to zero at no more than
   ``blend_rate_rad_s``. The published sigma is sqrt(var + offset^2) while blending.
7. If candidates exist but none passes the gate, the output coasts on the reference (source
   "coast") for up to ``reinit_after_s``; then it re-anchors on the best candidate: a 'reset'
   event with the jump, blended like any other change. It re-anchors at once, without coasting,
   when every source of the previous fusion is now offered as inconsistent (``consistent``
   False): the reference is their propagated heading, and a gate against it would hold the output
   on what their inconsistency discredits (method A dropped for disagreeing with B: coasting on A's
   heading published A's error at A's sigma for 2 s more).
8. No candidates: the output is invalid (heading None), event 'lost'.

Why this cannot lock onto a wrong source (issue 18: the output followed a diverged B, and the
correct C then failed the gate against the published heading for good):
- a reading says whether it is fit to be a candidate at all (``valid`` False with ``why_not``:
  a source that lost its reference, e.g. method B with neither a trusted FC nor air data) and
  whether its own filter agrees with its own measurements (``consistent`` False with
  ``why_not``: e.g. its recent magnetometer updates were gated out); neither kind is a candidate;
- candidates are also checked against EACH OTHER, not only against the published heading: the
  largest set of mutually consistent candidates (pairwise NIS <= ``gate_chi2``), counted by
  independent evidence (readings that share a group count once), is the majority. If the
  published heading's passing set is smaller (in independent evidence) than a majority it does
  not belong to, the output re-anchors on that majority at once (a 'reset' event: "re-acquired
  from a consistent majority", blended like any change), instead of coasting on the wrong value.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from service.aiding import AidingRecord

TWO_PI = 2.0 * math.pi


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % TWO_PI - math.pi


def _wrap_2pi(a: float) -> float:
    a = a % TWO_PI
    return 0.0 if a >= TWO_PI else a


@dataclass(frozen=True)
class SourceReading:
    name: str
    """'azimuth' | 'synthetic_ahrs' | 'heading_filter' | 'fc' | any other source name."""
    heading_rad: float
    sigma_rad: float
    valid: bool
    time_s: float
    """Time of the reading, same clock as the ``time_s`` given to ``arbitrate``."""
    group: str | tuple = ""
    """Name(s) of the error sources or references this reading shares with others (a str, or a
    tuple of str for several): readings with a group in common are treated as correlated with an
    unknown coefficient (covariance intersection: only the better one is fused)."""
    consistent: bool = True
    """False: the source's own filter disagrees with its own measurements (not a candidate)."""
    why_not: str = ""
    """Why the reading is not valid or not consistent (its aiding record's ``detail``)."""
    why_code: str = ""
    """The aiding record's code for ``valid`` / ``consistent`` False (service/aiding.WHY_NOT;
    default 'not_valid' / 'inconsistent')."""
    source_innovation_rad: float = math.nan
    """The source's own last measurement innovation, variance and gate ratio (aiding record's
    ``source_*``); NaN where the source computes none."""
    source_innovation_variance_rad2: float = math.nan
    source_test_ratio: float = math.nan

    @property
    def groups(self) -> tuple:
        g = self.group
        return tuple(x for x in ((g,) if isinstance(g, str) else tuple(g)) if x)


@dataclass(frozen=True)
class ArbitrationParams:
    gate_chi2: float = 9.0
    """Gate on the normalised innovation against the reference (3 sigma)."""
    max_age_s: float = 0.5
    """Older readings are not candidates."""
    max_sigma_rad: float = math.radians(45.0)
    """Readings less certain than this are not candidates."""
    blend_rate_rad_s: float = math.radians(2.0)
    """Largest rate at which a source-change offset is bled off (rad/s)."""
    rate_sigma_rad_s: float = math.radians(0.5)
    """Sigma of the caller's heading rate (rad/s), for propagating the reference."""
    rate_max_dt_s: float = 0.1
    """The caller's heading rate carries the reference over at most this interval (s; the filters'
    longest integration step, as method B's and C's ``max_dt_s``): over a longer one (inputs at a
    few Hz, a gap) the rate is one sample, not the turn made meanwhile, and the part beyond is as
    unseen as without a rate (the variance grows by (max_turn_rate (dt - this))^2)."""
    max_turn_rate_rad_s: float = math.radians(60.0)
    """Without a heading rate, the reference variance grows by (this * dt)^2."""
    reinit_after_s: float = 2.0
    """Continuous rejection of every candidate for this long re-anchors (a 'reset' event)."""
    priority: tuple = ("azimuth", "heading_filter", "synthetic_ahrs", "fc")
    """Tie-break between equally certain sources (first wins)."""

    def __post_init__(self) -> None:
        for name in ("gate_chi2", "max_age_s", "max_sigma_rad", "blend_rate_rad_s", "rate_sigma_rad_s",
                     "rate_max_dt_s", "max_turn_rate_rad_s", "reinit_after_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class ArbitrationEvent:
    time_s: float
    kind: str
    """'acquired' | 'source_change' | 'reset' | 'majority' (the reset that follows it says the jump) | 'lost'."""
    from_sources: tuple
    to_sources: tuple
    jump_rad: float
    """New fusion minus the old one at the same instant (what the offset absorbs)."""
    message: str


@dataclass(frozen=True)
class ArbitrationState:
    time_s: float | None = None
    fused_rad: float | None = None
    fused_var_rad2: float = math.inf
    offset_rad: float = 0.0
    sources: tuple = ()
    gated_since_s: float | None = None
    last_fused_s: tuple = ()
    """((name, time_s), ...): when each source was last fused (its aiding record's time_last_fused_s)."""

    def to_dict(self) -> dict:
        return dict(self.__dict__, sources=list(self.sources), last_fused_s=[list(p) for p in self.last_fused_s])

    @classmethod
    def from_dict(cls, d: dict) -> "ArbitrationState":
        return cls(**dict(d, sources=tuple(d["sources"]),
                          last_fused_s=tuple(tuple(p) for p in d.get("last_fused_s", ()))))


@dataclass(frozen=True)
class ArbitrationOutput:
    heading_rad: float | None
    """Published heading in [0, 2pi), None when no source is available."""
    sigma_rad: float
    source: str
    """'+'-joined names of the fused sources, 'coast', or 'none'."""
    valid: bool
    offset_rad: float = 0.0
    events: tuple = ()
    records: dict = field(default_factory=dict)
    """name -> AidingRecord (service/aiding.py), for every reading and every ``not_offered`` source:
    fused or why not (code and detail), innovation against the reference, test ratio = NIS / gate."""


def _rank(r: SourceReading, params: ArbitrationParams) -> tuple:
    pri = params.priority.index(r.name) if r.name in params.priority else len(params.priority)
    return (r.sigma_rad, pri, r.name)


def _fuse(readings: list, ref: float) -> tuple[float, float]:
    sw = 0.0
    s = 0.0
    for r in readings:
        w = 1.0 / (r.sigma_rad * r.sigma_rad)
        sw += w
        s += w * _wrap_pi(r.heading_rad - ref)
    return _wrap_2pi(ref + s / sw), 1.0 / sw


def _evidence(readings: list) -> int:
    """Independent evidence in a set of readings: readings that share a group count once
    (connected components of the 'shares a group' relation)."""
    rs = list(readings)
    seen, n = set(), 0
    for i in range(len(rs)):
        if i in seen:
            continue
        n += 1
        stack = [i]
        seen.add(i)
        while stack:
            j = stack.pop()
            for k in range(len(rs)):
                if k not in seen and set(rs[j].groups) & set(rs[k].groups):
                    seen.add(k)
                    stack.append(k)
    return n


def _majority(cands: list, params: ArbitrationParams) -> list:
    """The largest set (by independent evidence, then size) of candidates that are pairwise
    consistent: wrap(h_i - h_j)^2 / (s_i^2 + s_j^2) <= gate_chi2. Brute force over subsets (a
    handful of sources)."""
    n = len(cands)
    ok = [[i == j or _wrap_pi(cands[i].heading_rad - cands[j].heading_rad) ** 2
           / (cands[i].sigma_rad ** 2 + cands[j].sigma_rad ** 2) <= params.gate_chi2 for j in range(n)]
          for i in range(n)]
    best, best_key = [], (0, 0)
    for mask in range(1, 1 << min(n, 8)):
        idx = [i for i in range(n) if mask >> i & 1]
        if all(ok[i][j] for i in idx for j in idx):
            sub = [cands[i] for i in idx]
            key = (_evidence(sub), len(sub))
            if key > best_key:
                best, best_key = sub, key
    return best


def _decorrelate(readings: list, params: ArbitrationParams) -> list:
    """Covariance intersection for scalar readings that share a group (docstring step 4): in rank
    order, keep a reading only if it shares no group with a reading already kept."""
    kept, taken = [], set()
    for r in sorted(readings, key=lambda r: _rank(r, params)):
        g = set(r.groups)
        if g & taken:
            continue
        kept.append(r)
        taken |= g
    return sorted(kept, key=lambda r: r.name)


def arbitrate(state: ArbitrationState, readings: list, time_s: float,
              params: ArbitrationParams = ArbitrationParams(),
              heading_rate_rad_s: float | None = None,
              not_offered: tuple = ()) -> tuple[ArbitrationState, ArbitrationOutput]:
    """``not_offered``: NotOffered entries (service/aiding.py) for the sources the caller did not
    offer this step and why: they only get their aiding record."""
    if not math.isfinite(time_s):
        raise ValueError(f"time_s must be finite, got {time_s}")
    dt = 0.0 if state.time_s is None else max(0.0, time_s - state.time_s)
    per = {}
    cands = []
    for r in readings:
        reason, code = "", ""
        if not r.valid:
            reason = f"not valid: {r.why_not}" if r.why_not else "not valid"
            code = r.why_code or "not_valid"
        elif not r.consistent:
            reason = f"inconsistent: {r.why_not}" if r.why_not else "inconsistent with its own measurements"
            code = r.why_code or "inconsistent"
        elif not (math.isfinite(r.heading_rad) and math.isfinite(r.sigma_rad) and math.isfinite(r.time_s)):
            reason, code = "non-finite", "non_finite"
        elif not 0.0 < r.sigma_rad <= params.max_sigma_rad:
            reason, code = f"sigma {math.degrees(r.sigma_rad):.1f} deg out of range", "sigma_out_of_range"
        elif time_s - r.time_s > params.max_age_s:
            reason, code = f"stale ({time_s - r.time_s:.2f} s)", "stale"
        per[r.name] = {"candidate": not reason, "nis": math.nan, "used": False, "reason": reason, "code": code}
        if not reason:
            cands.append(r)
    events = []

    if not cands:
        if state.sources or state.fused_rad is not None:
            events.append(ArbitrationEvent(time_s, "lost", state.sources, (), 0.0,
                                           "no heading source available"))
        st = ArbitrationState(time_s=time_s, last_fused_s=state.last_fused_s)
        return st, ArbitrationOutput(None, math.inf, "none", False, 0.0, tuple(events),
                                     _records(readings, not_offered, per, time_s, params, st.last_fused_s))

    # --- reference -----------------------------------------------------------------------------
    # not called for longer than a reading may be old (an input gap): the old fusion says nothing
    # about the turn during the gap, so start over from the candidates (no blending of that jump)
    stale = state.fused_rad is not None and dt > params.max_age_s
    anchored = state.fused_rad is None or stale
    if anchored:
        best = min(cands, key=lambda r: _rank(r, params))
        ref, ref_var = best.heading_rad, best.sigma_rad ** 2
    elif heading_rate_rad_s is not None and math.isfinite(heading_rate_rad_s):
        ref = _wrap_2pi(state.fused_rad + heading_rate_rad_s * dt)
        ref_var = (state.fused_var_rad2 + (params.rate_sigma_rad_s * dt) ** 2
                   + (params.max_turn_rate_rad_s * max(0.0, dt - params.rate_max_dt_s)) ** 2)
    else:
        ref = state.fused_rad
        ref_var = state.fused_var_rad2 + (params.max_turn_rate_rad_s * dt) ** 2

    gate_ref = [ref, ref_var]
    """The reference of the last gate: the aiding records' innovations are against it."""

    def gate(ref_h, ref_v, anchor_name=None):
        gate_ref[:] = ref_h, ref_v
        ok = []
        for r in cands:
            innov = 0.0 if r.name == anchor_name else _wrap_pi(r.heading_rad - ref_h)
            nis = innov ** 2 / (r.sigma_rad ** 2 + ref_v)
            per[r.name].update(nis=nis, innov=innov, innov_var=r.sigma_rad ** 2 + ref_v)
            if nis <= params.gate_chi2:
                ok.append(r)
            else:
                per[r.name]["reason"] = f"gated out (NIS {nis:.1f})"
                per[r.name]["code"] = "gated_out"
        return ok

    passing = gate(ref, ref_var, best.name if anchored else None)
    gated_since = None
    kind = "source_change"
    majority = _majority(cands, params)
    if (not anchored and len(majority) >= 2 and not set(majority) & set(passing)
            and _evidence(majority) > _evidence(passing)):
        # the published heading disagrees with a consistent majority it is no part of: re-anchor
        best = min(majority, key=lambda r: _rank(r, params))
        for r in cands:
            per[r.name]["reason"] = per[r.name]["code"] = ""
        passing = gate(best.heading_rad, best.sigma_rad ** 2, best.name)
        kind = "reset"
        events.append(ArbitrationEvent(
            time_s, "majority", state.sources, tuple(sorted(r.name for r in majority)), 0.0,
            f"published heading disagrees with a consistent majority "
            f"({'+'.join(sorted(r.name for r in majority))}): re-acquired from it"))
    elif not passing:
        gated_since = state.gated_since_s if state.gated_since_s is not None else time_s
        inconsistent = {r.name for r in readings if r.valid and not r.consistent}
        discredited = bool(state.sources) and set(state.sources) <= inconsistent
        if time_s - gated_since < params.reinit_after_s and not discredited:
            # coast on the propagated reference
            for r in cands:
                per[r.name]["used"] = False
            st = ArbitrationState(time_s=time_s, fused_rad=ref, fused_var_rad2=ref_var,
                                  offset_rad=_bleed(state.offset_rad, dt, params), sources=state.sources,
                                  gated_since_s=gated_since, last_fused_s=state.last_fused_s)
            pub = _wrap_2pi(ref + st.offset_rad)
            return st, ArbitrationOutput(pub, math.sqrt(ref_var + st.offset_rad ** 2), "coast", True,
                                         st.offset_rad, (),
                                         _records(readings, not_offered, per, time_s, params, st.last_fused_s,
                                                  *gate_ref))
        # re-anchor on the best candidate
        best = min(cands, key=lambda r: _rank(r, params))
        for r in cands:
            per[r.name]["reason"] = per[r.name]["code"] = ""
        passing = gate(best.heading_rad, best.sigma_rad ** 2, best.name)
        gated_since = None
        kind = "reset"

    used = _decorrelate(passing, params)
    fused, var = _fuse(used, ref)
    names = tuple(r.name for r in used)
    for r in passing:
        if r in used:
            per[r.name]["used"] = True
        else:
            per[r.name]["reason"] = f"correlated with a better source (group {'+'.join(r.groups)})"
            per[r.name]["code"] = "correlated"

    offset = _bleed(state.offset_rad, dt, params)
    if stale:
        jump = _wrap_pi(fused - state.fused_rad)
        offset = 0.0
        events.append(ArbitrationEvent(
            time_s, "reset", state.sources, names, jump,
            f"heading re-acquired from {'+'.join(names)} after {dt:.1f} s without output: "
            f"jump {math.degrees(jump):+.2f} deg (not blended: the heading was unknown meanwhile)"))
    elif anchored:
        events.append(ArbitrationEvent(time_s, "acquired", (), names, 0.0,
                                       f"heading from {'+'.join(names)}"))
    elif names != state.sources or kind == "reset":
        # the old set evaluated now: its readings if every one of them is still finite and fresh,
        # else the reference (the old fusion propagated). A subset of the old set is not the old
        # set: taking it made a round trip A+B -> A+fc (B withdrawn) -> A+B leave A - fused(A+B)
        # in the offset, and a set that alternated every step ratcheted the offset up (make run,
        # 2026-12-02: +14 deg in 1 s while A's and B's sigmas crossed)
        old = [r for r in readings if r.name in state.sources and math.isfinite(r.heading_rad)
               and math.isfinite(r.sigma_rad) and r.sigma_rad > 0 and time_s - r.time_s <= params.max_age_s]
        whole = len(old) == len(state.sources)
        old_now = _fuse(_decorrelate(old, params), ref)[0] if whole and kind != "reset" else ref
        jump = _wrap_pi(fused - old_now)
        offset = _wrap_pi(offset - jump)
        events.append(ArbitrationEvent(
            time_s, kind, state.sources, names, jump,
            f"heading source {'+'.join(state.sources) or 'none'} -> {'+'.join(names)}: "
            f"jump {math.degrees(jump):+.2f} deg, blended at <= "
            f"{math.degrees(params.blend_rate_rad_s):.1f} deg/s"))
    last_fused = tuple(sorted({**dict(state.last_fused_s), **{n: time_s for n in names}}.items()))
    st = ArbitrationState(time_s=time_s, fused_rad=fused, fused_var_rad2=var, offset_rad=offset,
                          sources=names, gated_since_s=gated_since, last_fused_s=last_fused)
    return st, ArbitrationOutput(_wrap_2pi(fused + offset), math.sqrt(var + offset * offset),
                                 "+".join(names), True, offset, tuple(events),
                                 _records(readings, not_offered, per, time_s, params, last_fused, *gate_ref))


def _records(readings: list, not_offered, per: dict, time_s: float, params: ArbitrationParams,
             last_fused_s: tuple, ref_rad: float = math.nan, ref_var_rad2: float = math.nan) -> dict:
    """One AidingRecord per reading and per ``not_offered`` source (service/aiding.py). A
    candidate's innovation is the one its gate used; a reading that is no candidate but has a
    finite heading and sigma is compared with the same reference (as PX4 reports a rejected
    observation's innovation), NaN without a reference (no candidate at all)."""
    last = dict(last_fused_s)
    out = {}
    for n in not_offered:
        out[n.source] = AidingRecord(n.source, time_s, n.why_not, n.detail,
                                     time_last_fused_s=last.get(n.source, math.nan))
    for r in readings:
        v = per[r.name]
        innov, innov_var = v.get("innov", math.nan), v.get("innov_var", math.nan)
        if (not v["candidate"] and math.isfinite(ref_rad) and math.isfinite(r.heading_rad)
                and math.isfinite(r.sigma_rad)):
            innov, innov_var = _wrap_pi(r.heading_rad - ref_rad), r.sigma_rad ** 2 + ref_var_rad2
        ratio = innov * innov / innov_var / params.gate_chi2 if innov_var > 0.0 else math.nan
        used = bool(v["used"])
        out[r.name] = AidingRecord(
            r.name, time_s, "" if used else v["code"], "" if used else v["reason"], bool(v["candidate"]), used,
            last.get(r.name, math.nan), r.heading_rad, r.sigma_rad, innov, innov_var, ratio,
            r.source_innovation_rad, r.source_innovation_variance_rad2, r.source_test_ratio)
    return out


def _bleed(offset: float, dt: float, params: ArbitrationParams) -> float:
    step = params.blend_rate_rad_s * dt
    if abs(offset) <= step:
        return 0.0
    return offset - math.copysign(step, offset)
