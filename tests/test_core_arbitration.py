"""The heading arbitration in the compiled core equals its Python reference (issue 19 items 1-2):
service/heading_arbitration.py ``arbitrate`` against core/heading_arbitration.hpp through
service/arbitration_core.py.

GIVEN the calls a Pipeline made into the arbitration (recorded at the Pipeline, the arbitration in the
reference) on
- simulated flights (sim.offline): inclined_rail (rest, rail launch, flight), any_motion magnet_nearby
  (a stationary extra field for 20 s: C's and B's magnetometer updates gated out) and
  runway_gnss_denied with the GNSS lost at 90 s (the FC's attitude stops being trusted: the 'fc'
  source is lost and the fused set changes, blended);
- the real logs in ../shared/data replayed as ``azimuthd replay`` runs them (skipped when absent);
- edge inputs driven directly: no candidate, a NaN reading, a source appearing and disappearing,
  wrap-around at +-pi, time going back, a gap longer than max_age_s, coasting and the re-anchor,
  a consistent majority, correlated groups, a discredited set, and a seeded random walk through all
  of them; values the core does not take as they stand (answered by the reference) and refused
  arguments,
WHEN the reference and the core take the same calls, each from its own previous state,
THEN after every call the state, the output, its events (messages identical) and every aiding record
agree (tests/parity_compare.py: strings, codes and flags identical, numbers to 1e-9 relative), and a
Pipeline on the core backend gives the same solutions and events as with the arbitration in the
reference. A comparison here fails when a value differs beyond 1e-9 relative (the mutation test)."""
from __future__ import annotations

import dataclasses
import math
import random
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from parity_compare import differences  # noqa: E402
from pipeline_recording import fly, run_with_backend, select_core_backend  # noqa: E402
from test_core_polar_heading import ANY_MOTION, DATA, _sim, _solutions_differences  # noqa: E402

from service import arbitration_core as ac  # noqa: E402
from service import heading_arbitration as ha  # noqa: E402
from service.aiding import NotOffered  # noqa: E402
from service.heading_arbitration import ArbitrationParams, ArbitrationState, SourceReading  # noqa: E402

pytestmark = pytest.mark.skipif(not ac.ARBITRATION_AVAILABLE, reason="compiled core without the heading arbitration")

D = math.radians
MAG, FCREF = "magnetometer", "fc_reference"


class Twin:
    """The reference and the core side by side: each call to both (each from its own previous state),
    everything compared after it; ``fallbacks`` counts the calls the core handed to the reference."""

    def __init__(self, label: str, core_params=None):
        self.label, self.core_params = label, core_params
        self.ref = self.core = ArbitrationState()
        self.k, self.kinds, self.fallbacks = 0, {}, 0

    def __call__(self, readings, t, params=ArbitrationParams(), rate=None, not_offered=()):
        self.ref, out_r = ha.arbitrate(self.ref, readings, t, params, rate, not_offered)
        before = _FALLBACKS[0]
        self.core, out_c = ac.arbitrate(self.core, readings, t, params if self.core_params is None else self.core_params,
                                        rate, not_offered)
        self.fallbacks += _FALLBACKS[0] - before
        where = f"{self.label} call {self.k} (t={t})"
        bad = differences(self.ref, self.core, f"{where} state") + differences(out_r, out_c, f"{where} output")
        assert not bad, bad[:4]
        self.k += 1
        for key in [out_r.source if out_r.source in ("coast", "none") else "fused",
                    *(e.kind for e in out_r.events), *(r.why_not or "fused" for r in out_r.records.values())]:
            self.kinds[key] = self.kinds.get(key, 0) + 1
        return out_r


_FALLBACKS = [0]


class _CountedReference:
    """service/arbitration_core.py's reference (its ``_ha``), counting the calls handed to it."""

    def __getattr__(self, name):
        return getattr(ha, name)

    @staticmethod
    def arbitrate(*a, **k):
        _FALLBACKS[0] += 1
        return ha.arbitrate(*a, **k)


@pytest.fixture(autouse=True)
def _count_fallbacks(monkeypatch):
    monkeypatch.setattr(ac, "_ha", _CountedReference())


# --- the calls a Pipeline makes into the arbitration --------------------------------------------------

SIMS = {
    "inclined_rail": lambda: _sim("inclined_rail", 30.0, 100.0, seed=3, overrides={"launcher": {"rest_s": 8.0}}),
    "magnet_nearby": lambda: _sim("any_motion_magnet_nearby", 70.0, 50.0, cfg=ANY_MOTION),
    "gnss_lost": lambda: _sim("runway_gnss_denied", 130.0, 50.0,
                              overrides={"gnss": {"lost_at_s": 90.0}, "launcher": {"rest_s": 20.0}}),
}
LOGS = ("arducopter-rtl-midflight.bin", "arducopter-flight.tlog", "px4-quad-no-gnss.ulg",
        "px4-vtol-airspeed-small.ulg")
NO_SITE = ("px4-quad-no-gnss.ulg",)
_INPUTS: dict = {}
_CACHE: dict = {}


def _recording(calls: list):
    """The selected backend with the arbitration in the reference, every call appended to ``calls``."""
    from service import core_backend
    b = core_backend.select()
    real = ha.arbitrate

    def rec(state, readings, t, params=ArbitrationParams(), rate=None, not_offered=()):
        calls.append((list(readings), t, params, rate, tuple(not_offered)))
        return real(state, readings, t, params, rate, not_offered)
    return dataclasses.replace(b, arbitrate=rec)


def _fly(name: str):
    return fly(name, SIMS, _INPUTS, DATA, NO_SITE)


@pytest.fixture(scope="module", params=[*SIMS, *LOGS])
def recorded(request):
    """The flight with the arbitration in the reference: its calls, what it gave, its Pipeline."""
    name = request.param
    if name not in _CACHE:
        calls: list = []
        out, pipe = run_with_backend(_fly, name, _recording(calls))
        _CACHE[name] = {"calls": calls, "out": out, "pipeline": pipe}
    return name, _CACHE[name]


# what each flight must have exercised (not a run that stayed in one branch)
EXERCISED = {
    "inclined_rail": {"fused", "acquired", "source_change", "correlated", "no_reference", "none"},
    "magnet_nearby": {"fused", "acquired", "source_change", "correlated", "excluded"},
    "gnss_lost": {"fused", "acquired", "source_change", "correlated", "no_reference"},
    "arducopter-rtl-midflight.bin": {"fused", "acquired", "source_change", "correlated", "no_reference"},
    # RAW_IMU at ~2.7 Hz: method B cannot propagate, the output is lost and re-acquired after gaps
    "arducopter-flight.tlog": {"fused", "acquired", "lost", "reset", "none", "no_propagation", "sigma_out_of_range"},
    "px4-quad-no-gnss.ulg": {"fused", "acquired", "none", "no_reference"},
    # 6.5 s on the ground: no heading source at all
    "px4-vtol-airspeed-small.ulg": {"none", "no_estimate"},
}


def test_arbitration_core_equals_reference_on_what_the_pipeline_feeds(recorded):
    name, rec = recorded
    calls = rec["calls"]
    if not calls:
        pytest.skip(f"{name}: the replay never reaches the arbitration")
    twin = Twin(name)
    for readings, t, params, rate, no in calls:
        twin(readings, t, params, rate, no)
    assert twin.fallbacks == 0          # the core took every call (none handed to the reference)
    need = EXERCISED[name]
    assert need <= set(twin.kinds), (need, twin.kinds)


def test_pipeline_runs_the_arbitration_in_the_core(recorded, monkeypatch):
    # GIVEN the flight recorded above (the arbitration in the reference, everything else as selected),
    # WHEN it runs on the default core backend, THEN the arbitration is the core's, and the solutions
    # (or the replay's rows), the events and the final arbitration state are the same
    from service import core_backend
    name, rec = recorded
    if name not in ("magnet_nearby", "gnss_lost", "arducopter-rtl-midflight.bin"):
        pytest.skip("three flights are enough for the wiring (a disturbance; a source lost; a start in flight)")
    backend = select_core_backend(monkeypatch)
    assert backend.arbitrate is ac.arbitrate
    before = _FALLBACKS[0]
    out, p = run_with_backend(_fly, name, backend)
    assert _FALLBACKS[0] == before
    assert (out.get("events"), len(out.get("solutions", out.get("time_s")))) == \
        (rec["out"].get("events"), len(rec["out"].get("solutions", rec["out"].get("time_s"))))
    bad = _solutions_differences(rec["out"], out, name)
    bad += differences(rec["pipeline"].arb, p.arb, "arbitration state")
    bad += differences(rec["pipeline"].aiding, p.aiding, "aiding records")
    assert not bad, bad[:5]


def test_the_comparison_fails_on_a_small_difference(recorded):
    # the mutation check: the core given a blend rate 1e-6 relative off fails the comparison on a flight
    # whose source changes leave an offset to bleed
    name, rec = recorded
    if name != "gnss_lost":
        pytest.skip("one flight is enough")
    p = ArbitrationParams()
    twin = Twin(name, core_params=dataclasses.replace(p, blend_rate_rad_s=p.blend_rate_rad_s * (1.0 + 1e-6)))
    with pytest.raises(AssertionError, match="offset_rad"):
        for readings, t, params, rate, no in rec["calls"]:
            twin(readings, t, params, rate, no)


# --- edge inputs, driven directly ---------------------------------------------------------------------

def R(name, hdg_deg, sig_deg, t, group="", valid=True, consistent=True, **kw):
    return SourceReading(name, D(hdg_deg) if math.isfinite(hdg_deg) else hdg_deg, D(sig_deg), valid, t, group,
                         consistent, **kw)


def test_no_candidate_nan_reading_and_sources_coming_and_going():
    tw = Twin("edges")
    tw([], 0.0)                                                                  # nothing at all
    tw([R("azimuth", 10.0, 1.0, 0.0, valid=False, why_not="no fit yet", why_code="no_estimate")], 0.0)
    tw([R("azimuth", math.nan, 1.0, 0.1)], 0.1)                                  # a NaN reading only
    tw([R("azimuth", 10.0, 1.0, 0.2), R("fc", math.nan, 2.0, 0.2, (MAG, FCREF))], 0.2, rate=0.0)
    tw([R("azimuth", 10.2, 1.0, 0.3), R("fc", 11.0, 2.0, 0.3, (MAG, FCREF))], 0.3, rate=0.01)   # fc appears
    tw([R("azimuth", 10.3, 1.0, 0.4)], 0.4, rate=0.0,
       not_offered=(NotOffered("fc", "no_reference", "FC attitude not trusted"),))  # fc disappears
    tw([R("heading_filter", 12.0, 3.0, 0.5, MAG)], 0.5, rate=0.0,
       not_offered=(NotOffered("azimuth", "no_estimate", "lost"),))              # A gone, C comes
    tw([R("heading_filter", 12.0, 3.0, 0.6, MAG, why_not="x", consistent=False, why_code="inconsistent")], 0.6)
    tw([], 0.7)                                                                  # lost
    tw([R("heading_filter", 12.0, 3.0, 0.8, MAG)], 0.8)                          # acquired again
    tw([R("heading_filter", 12.0, 50.0, 0.9, MAG), R("fc", 12.0, 0.0, 0.9), R("azimuth", 1.0, 1.0, 0.9, valid=False)],
       0.9)                                                                      # sigma out of range, not valid
    tw([R("heading_filter", 12.0, 3.0, 0.1, MAG)], 1.0)                          # stale
    assert {"none", "lost", "acquired", "source_change", "non_finite", "no_reference", "no_estimate",
            "inconsistent", "sigma_out_of_range", "stale", "not_valid"} <= set(tw.kinds), tw.kinds
    assert tw.fallbacks == 0


def test_wrap_around_at_pi_and_at_zero():
    # readings on both sides of 0 = 360 deg and of 180 deg, a fusion across the wrap, the reference
    # propagated across it, and a source change whose jump crosses it
    tw = Twin("wrap")
    t = 0.0
    for k in range(60):
        t = 0.05 * k
        h = 359.0 + 0.1 * k                               # turns through 360 -> 0
        tw([R("azimuth", h % 360.0, 1.0, t), R("heading_filter", (h + 0.8) % 360.0 - 360.0 * (k % 2), 2.0, t, MAG)],
           t, rate=D(2.0))
    for k in range(60):
        t = 3.0 + 0.05 * k
        h = 179.5 + 0.02 * k * (-1) ** k                  # about +-180
        rs = [R("azimuth", h, 1.0, t), R("synthetic_ahrs", -h if k % 3 else h - 360.0, 1.5, t, MAG)]
        tw(rs[: 1 + k % 2], t, rate=0.0)
    assert tw.kinds.get("source_change", 0) >= 10 and tw.fallbacks == 0, tw.kinds


def test_time_going_back_a_gap_and_a_repeated_time():
    tw = Twin("time")
    tw([R("azimuth", 40.0, 1.0, 10.0)], 10.0)
    tw([R("azimuth", 40.5, 1.0, 10.1), R("fc", 42.0, 2.0, 10.1, (MAG, FCREF))], 10.1, rate=0.0)
    tw([R("azimuth", 40.4, 1.0, 9.9), R("fc", 41.0, 2.0, 9.9, (MAG, FCREF))], 9.9, rate=0.0)      # back in time
    tw([R("azimuth", 40.4, 1.0, 9.9)], 9.9, rate=0.0)                                            # the same time
    tw([R("azimuth", 70.0, 1.0, 20.0), R("fc", 71.0, 2.0, 20.0, (MAG, FCREF))], 20.0, rate=0.1)   # a gap: reset
    tw([R("azimuth", 70.1, 1.0, 20.05)], 20.05, rate=math.nan)                                   # a NaN rate
    assert {"reset", "source_change"} <= set(tw.kinds) and tw.fallbacks == 0, tw.kinds


def test_coast_reanchor_majority_and_discredited():
    p = ArbitrationParams(reinit_after_s=0.5)
    tw = Twin("rules")
    tw([R("azimuth", 100.0, 0.5, 0.0)], 0.0, p)
    for k in range(1, 10):       # the one source jumps away: coasting, then the re-anchor after 0.5 s
        tw([R("azimuth", 140.0, 0.5, 0.1 * k)], 0.1 * k, p, 0.0)
    assert tw.kinds.get("coast", 0) >= 4 and tw.kinds.get("reset", 0) == 1, tw.kinds
    # B and C (independent) come in agreeing with each other, 40 deg from A: a consistent majority
    out = tw([R("azimuth", 140.0, 0.5, 1.0), R("synthetic_ahrs", 180.0, 1.0, 1.0, FCREF),
              R("heading_filter", 180.5, 1.2, 1.0, MAG)], 1.0, p, 0.0)
    assert [e.kind for e in out.events] == ["majority", "reset"], out.events
    # the FC's compass yaw shares C's magnetometer: not fused beside it (covariance intersection)
    out = tw([R("synthetic_ahrs", 180.0, 1.0, 1.1, FCREF), R("heading_filter", 180.5, 1.2, 1.1, MAG),
              R("fc", 180.2, 1.3, 1.1, (MAG,))], 1.1, p, 0.0)
    assert out.records["fc"].why_not == "correlated", out.records
    # the fused set offered as inconsistent: re-anchored at once on A (discredited), no coasting
    out = tw([R("azimuth", 200.0, 0.3, 1.2), R("synthetic_ahrs", 180.0, 1.0, 1.2, FCREF, consistent=False),
              R("heading_filter", 180.0, 1.2, 1.2, MAG, consistent=False)], 1.2, p, 0.0)
    assert out.source == "azimuth" and [e.kind for e in out.events] == ["reset"], out
    assert tw.fallbacks == 0


def test_correlated_groups_decorrelated_alike():
    tw = Twin("groups")
    rs = [R("azimuth", 50.0, 1.0, 0.0), R("synthetic_ahrs", 50.5, 1.5, 0.0, (MAG, FCREF)),
          R("heading_filter", 50.2, 1.4, 0.0, MAG), R("fc", 50.1, 1.6, 0.0, (MAG, FCREF)),
          R("other", 49.8, 2.0, 0.0, ("x", "")), R("more", 49.9, 2.0, 0.0, ("x",))]
    tw(rs, 0.0)
    for k in range(1, 12):       # nine readings at most: the majority's subsets stop at the first 8
        t = 0.1 * k
        tw([dataclasses.replace(r, time_s=t) for r in rs] + [R(f"extra{j}", 50.0 + j, 1.0, t) for j in range(k % 4)],
           t, rate=0.0)
    assert tw.kinds.get("correlated", 0) >= 20 and tw.fallbacks == 0, tw.kinds


def test_random_walk_through_every_branch():
    # GIVEN a seeded walk: sources present or not, valid or not, consistent or not, NaN, out-of-range
    # sigmas, stale readings, jumps, groups, times forward, repeated and backward, rates None, 0, NaN
    # THEN the two agree after every call, and every branch was taken
    names = ("azimuth", "synthetic_ahrs", "heading_filter", "fc", "other")
    groups = ("", MAG, (MAG, FCREF), (FCREF,), ("x", ""))
    total: dict = {}
    for seed in range(12):
        rng = random.Random(seed)
        p = ArbitrationParams(reinit_after_s=rng.choice([0.3, 2.0]))
        tw = Twin(f"walk {seed}")
        t, base = 0.0, rng.uniform(0.0, 2.0 * math.pi)
        for _ in range(300):
            t += rng.choice([0.02, 0.1, 0.0, -0.05, 0.7, 0.25])
            base += rng.gauss(0.0, 0.05)
            present = [n for n in names if rng.random() < 0.7]
            rs = []
            for n in present:
                h = base + rng.gauss(0.0, 0.02) + (rng.choice([0.0, 0.5, -2.0]) if rng.random() < 0.2 else 0.0)
                h = h % (2.0 * math.pi) if rng.random() < 0.3 else h
                h = math.nan if rng.random() < 0.05 else h
                s = -0.1 if rng.random() < 0.03 else rng.choice([0.01, 0.02, 0.05, 0.3, 1.0])
                rs.append(SourceReading(n, h, s, rng.random() > 0.1, t - rng.choice([0.0, 0.0, 0.1, 0.6]),
                                        rng.choice(groups), rng.random() > 0.1, why_not=rng.choice(["", "because"]),
                                        why_code=rng.choice(["", "no_reference"]),
                                        source_innovation_rad=rng.random()))
            no = tuple(NotOffered(n, "superseded", "A") for n in names if n not in present and rng.random() < 0.5)
            tw(rs, t, p, rng.choice([None, 0.0, 0.1, math.nan, -0.3]), no)
        assert tw.fallbacks == 0
        for k, v in tw.kinds.items():
            total[k] = total.get(k, 0) + v
    assert {"fused", "coast", "none", "acquired", "source_change", "reset", "majority", "lost", "gated_out",
            "correlated", "stale", "non_finite", "sigma_out_of_range", "not_valid", "no_reference", "inconsistent",
            "superseded"} <= set(total), total


# --- what the core does not take as it stands: the reference answers, alike ----------------------------

def test_values_the_core_does_not_take_are_answered_by_the_reference():
    base = [R("azimuth", 10.0, 1.0, 0.0), R("fc", 10.5, 2.0, 0.0, (MAG, FCREF))]
    cases = {
        "a float32 heading": ([dataclasses.replace(base[0], heading_rad=np.float32(0.2)), base[1]], 0.0),
        "an int time": (base, 0),
        "a sigma too large an int to square exactly": ([dataclasses.replace(base[0], sigma_rad=2 ** 27), base[1]], 0.0),
        "a group in a list": ([base[0], dataclasses.replace(base[1], group=[MAG])], 0.0),
        "two readings of one name": ([base[0], dataclasses.replace(base[1], name="azimuth")], 0.0),
        "a name that is no str": ([base[0], dataclasses.replace(base[1], name=7)], 0.0),
        "readings in a generator's place": ((r for r in ()), 0.0),
    }
    for what, (rs, t) in cases.items():
        before = _FALLBACKS[0]
        try:
            sr, out_r = ha.arbitrate(ArbitrationState(), list(rs) if what.startswith("readings") else rs, t)
        except Exception as exc:      # the reference refuses it: the core path refuses it alike
            with pytest.raises(type(exc)):
                ac.arbitrate(ArbitrationState(), rs, t)
        else:
            sc, out_c = ac.arbitrate(ArbitrationState(), rs, t)
            assert not differences(sr, sc) + differences(out_r, out_c), what
        assert _FALLBACKS[0] == before + 1, what
    # a state made by hand with a fusion and no sources: the reference divides by zero, so does this
    hand = ArbitrationState(time_s=0.0, fused_rad=D(10.2), fused_var_rad2=0.01)
    with pytest.raises(ZeroDivisionError):
        ha.arbitrate(hand, base, 0.1)
    with pytest.raises(ZeroDivisionError):
        ac.arbitrate(hand, base, 0.1)
    # an int time in the state and sources in a list: taken / answered alike
    for st in (ArbitrationState(time_s=0, fused_rad=1.0, fused_var_rad2=0.01, sources=("azimuth",)),
               dataclasses.replace(ArbitrationState(), sources=["azimuth"], fused_rad=0.17, time_s=0.0)):
        sr, out_r = ha.arbitrate(st, base, 0.05)
        sc, out_c = ac.arbitrate(st, base, 0.05)
        assert not differences(sr, sc) + differences(out_r, out_c)


def test_arguments_and_codes_refused_alike():
    rs = [R("azimuth", 10.0, 1.0, 0.0)]
    for t in (math.nan, math.inf):
        with pytest.raises(ValueError, match="time_s must be finite"):
            ha.arbitrate(ArbitrationState(), rs, t)
        with pytest.raises(ValueError, match="time_s must be finite"):
            ac.arbitrate(ArbitrationState(), rs, t)
    for f in (ha.arbitrate, ac.arbitrate):
        with pytest.raises(TypeError):
            f(ArbitrationState(), rs, None)
        # a why_code that is no aiding code, a NotOffered without a code: AidingRecord refuses both
        with pytest.raises(ValueError, match="why_not must be one of"):
            f(ArbitrationState(), [R("azimuth", 10.0, 1.0, 0.0, valid=False, why_code="broken")], 0.0)
        with pytest.raises(ValueError, match="contradicts"):
            f(ArbitrationState(), rs, 0.0, not_offered=(NotOffered("fc", ""),))


def test_the_backend_selects_the_arbitration(monkeypatch, caplog):
    import logging

    from service import core_backend
    monkeypatch.delenv("AZIMUTHD_CORE", raising=False)
    assert core_backend.select({}).arbitrate is ac.arbitrate
    assert core_backend.select({"AZIMUTHD_CORE": "python"}).arbitrate is ha.arbitrate
    monkeypatch.setattr(core_backend, "_said", set())
    monkeypatch.setattr(ac, "ARBITRATION_AVAILABLE", False)
    with caplog.at_level(logging.WARNING, logger="azimuthd.core"):
        b = core_backend.select({})
    assert b.name == "core" and b.arbitrate is ha.arbitrate
    assert "compiled core without the heading arbitration (an older build): it runs the Python reference" in \
        [r.getMessage() for r in caplog.records]
