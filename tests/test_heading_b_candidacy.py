"""Method B is a heading candidate only while it can propagate and has a reference (issue 18 item 3:
"a source that lost its reference (no FC, no air data) is not a candidate"), and says why not
(service/heading_sources.SyntheticAhrsHealth, its aiding record's code).

- Inputs too slow: B integrates an IMU interval only up to ``kf2.max_dt_s`` (0.1 s). GIVEN a flight
  whose RAW_IMU comes every 0.37 s for 15 s (../shared/data/arducopter-flight.tlog's rate) THEN B is
  no candidate ('no_propagation', in words) while more than half of its IMU intervals of the last
  5 s were held across, and is one again once its inputs are back at 100 Hz; one gap alone (1 s,
  or 10 s as heading_consistency's outage) is not this.
  Before: B was offered throughout (on the tlog: 97 deg RMS off at a ~27 deg sigma).
- No reference: GIVEN no trusted FC attitude, B stays a candidate while it fuses air data and for
  ``B_REFERENCE_MAX_AGE_S`` after its last air-data fusion, then 'no_reference', and a candidate
  again when air data is fused again.
Reference and core (the output's IMU time integrated / held across is the same number in both)."""
from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from synthetic_ahrs_accuracy import events_of  # noqa: E402

from estimators import core  # noqa: E402
from estimators import synthetic_ahrs as ref  # noqa: E402
from estimators.geomag import earth_field_ned_gauss  # noqa: E402
from estimators.synthetic_ahrs import ImuEvent, SyntheticAhrsParams  # noqa: E402
from service.heading_arbitration import ArbitrationState, SourceReading, arbitrate  # noqa: E402
from service.heading_sources import (B_PROPAGATION_WINDOW_S, B_REFERENCE_MAX_AGE_S,  # noqa: E402
                                     SyntheticAhrsHealth, synthetic_ahrs_source)
from sim.offline import simulate  # noqa: E402

STEPS = [ref.synthetic_ahrs_step] + ([core.synthetic_ahrs_step] if core.B_AVAILABLE else [])
SLOW_FROM_S, SLOW_TO_S, SLOW_DT_S = 10.0, 25.0, 0.37
CYCLE_S = 0.02


@pytest.fixture(scope="module")
def run():
    return simulate("multicopter_takeoff", seed=1, imu_rate_hz=100.0, duration_s=36.0)


def _params(run) -> SyntheticAhrsParams:
    s = run.site
    return SyntheticAhrsParams(variant="b2", C_body_from_sensor=s["C_body_from_sensor"],
                               field_nav_gauss=tuple(earth_field_ned_gauss(s["lat_deg"], s["lon_deg"], s["alt_m"],
                                                                           s["decimal_year"])))


def _readings(run, step, keep) -> list[tuple[float, object, object]]:
    """B stepped on the run's events with the IMU samples ``keep(t)`` lets through; its source
    reading every output cycle: [(t, reading, output)]."""
    params = _params(run)
    st, out, health = ref.synthetic_ahrs_init(params), None, SyntheticAhrsHealth()
    rows, next_cycle = [], 0.0
    for ev in events_of(run, signalled=False):
        if isinstance(ev, ImuEvent) and not keep(ev.time_s):
            continue
        while ev.time_s >= next_cycle:
            if out is not None:
                rows.append((next_cycle, synthetic_ahrs_source(out, health, next_cycle, False, True), out))
            next_cycle += CYCLE_S
        st, o = step(st, ev, params, output=True)
        out = o if o is not None else out
    return rows


def _slow(t: float) -> bool:
    """100 Hz, but one sample per SLOW_DT_S between SLOW_FROM_S and SLOW_TO_S."""
    if not SLOW_FROM_S <= t < SLOW_TO_S:
        return True
    k = round((t - SLOW_FROM_S) / SLOW_DT_S)
    return abs(t - SLOW_FROM_S - k * SLOW_DT_S) < 0.005


@pytest.mark.parametrize("step", STEPS, ids=lambda s: s.__module__)
def test_given_imu_inputs_too_slow_to_integrate_then_b_is_no_candidate_and_says_why_until_they_return(run, step):
    rows = _readings(run, step, _slow)
    before = [r for t, r, o in rows if 6.0 <= t < SLOW_FROM_S and o.valid]
    during = [(t, r) for t, r, o in rows if SLOW_FROM_S + B_PROPAGATION_WINDOW_S + 0.5 <= t < SLOW_TO_S]
    after = [(t, r) for t, r, o in rows if SLOW_TO_S + 1.0 <= t]
    assert before and during and after
    assert all(isinstance(r, SourceReading) and r.valid and r.why_code == "" for r in before)
    for t, r in during:   # THEN not a candidate, with the code and the words
        assert isinstance(r, SourceReading) and not r.valid and r.why_code == "no_propagation", (t, r)
        assert r.why_not.startswith("cannot propagate: ") and "too long to integrate" in r.why_not, r.why_not
    for t, r in after:    # ... and a candidate again once its inputs are back
        assert isinstance(r, SourceReading) and r.valid and r.why_code != "no_propagation", (t, r)
    # the outputs say how much was held across: the slow stretch's intervals, nearly all of it
    o = rows[-1][2]
    assert SLOW_TO_S - SLOW_FROM_S - 0.5 <= o.imu_not_integrated_s <= SLOW_TO_S - SLOW_FROM_S + 0.5
    # the aiding record through the arbitration: no candidate, the code and the detail
    t, r = during[-1]
    _, outp = arbitrate(ArbitrationState(), [r], t)
    rec = outp.records["synthetic_ahrs"]
    assert (rec.candidate, rec.fused, rec.why_not) == (False, False, "no_propagation")
    assert rec.detail == f"not valid: {r.why_not}"


@pytest.mark.parametrize("gap_s", [1.0, 10.0])
@pytest.mark.parametrize("step", STEPS, ids=lambda s: s.__module__)
def test_given_one_gap_at_the_full_rate_then_b_stays_a_candidate(run, step, gap_s):
    rows = _readings(run, step, lambda t: not 18.0 <= t < 18.0 + gap_s)
    assert not any(isinstance(r, SourceReading) and r.why_code == "no_propagation" for _, r, _ in rows)
    assert rows[-1][2].imu_not_integrated_s == pytest.approx(gap_s, abs=0.02)


def _b(t, air_fused, trusted=False, integrated_s=None):
    """A method-B output as SyntheticAhrsHealth reads it (its counters and flags)."""
    return SimpleNamespace(time_s=t, air_fused=air_fused, mag_fused=0, mag_gated=0, reference_trusted=trusted,
                           imu_integrated_s=t if integrated_s is None else integrated_s, imu_not_integrated_s=0.0)


def test_given_no_trusted_fc_then_b_is_a_candidate_while_it_fuses_air_data_and_not_after_its_allowance():
    h = SyntheticAhrsHealth()
    n_air, verdicts = 0, []
    for k in range(0, 12001):      # 0..120 s at 100 Hz; air data fused every 0.1 s before 40 s and after 100 s
        t = k * 0.01
        if (k < 4000 or k >= 10000) and k % 10 == 0:
            n_air += 1
        verdicts.append((t, h.check(_b(t, n_air), t)))
    last_air_s = 39.9
    for t, (has_ref, consistent, why, code) in verdicts:
        if t < last_air_s + B_REFERENCE_MAX_AGE_S - 0.005 or t >= 100.0:
            assert (has_ref, consistent, why, code) == (True, True, "", ""), t
        elif t > last_air_s + B_REFERENCE_MAX_AGE_S + 0.005:
            assert (has_ref, code) == (False, "no_reference"), t
            assert why == "lost its reference (no trusted FC attitude, no air data)"
    # the FC trusted again: a reference at once, air data or not
    assert h.check(_b(120.01, n_air, trusted=True), 120.01)[:2] == (True, True)


def test_given_a_restarted_b_clock_then_its_old_imu_time_is_not_counted():
    h = SyntheticAhrsHealth()
    h.check(SimpleNamespace(**{**vars(_b(100.0, 0, True)), "imu_not_integrated_s": 50.0}), 100.0)
    # the FC clock restarted: B's time and counters are from the new start
    assert h.check(_b(0.5, 0, True, integrated_s=0.5), 100.5)[:2] == (True, True)
    assert math.isfinite(h.imu_hist[0][0]) and len(h.imu_hist) == 1


def test_the_held_count_is_the_windows_own_count():
    # GIVEN a seeded walk of B's outputs: intervals integrated or held across (a slow input, a gap), the
    # same time again, a restarted clock, THEN after every check the held count SyntheticAhrsHealth
    # keeps equals the count over its window, and the verdict is the one that count gives
    import random
    from service.heading_sources import B_MAX_NOT_INTEGRATED_SHARE, B_MIN_HELD_INTERVALS
    rng = random.Random(5)
    h = SyntheticAhrsHealth()
    t = integ = held = 0.0
    seen = set()
    for k in range(4000):
        r = rng.random()
        if r < 0.01:
            t, integ, held = 0.0, 0.0, 0.0                         # a new B (a restarted clock)
        elif r < 0.05:
            pass                                                  # the same B time again
        elif r < 0.45:
            t += 0.37
            held += 0.37                                          # too long to integrate: held across
        else:
            t += 0.02
            integ += 0.02
        b = SimpleNamespace(time_s=t, air_fused=k, mag_fused=0, mag_gated=0, reference_trusted=True,
                            imu_integrated_s=integ, imu_not_integrated_s=held)
        has_ref, _, _, code = h.check(b, 1000.0 + 0.02 * k)
        n = sum(x[1] for x in h.imu_hist)
        assert h.n_held == n, k
        slow = n >= B_MIN_HELD_INTERVALS and n > B_MAX_NOT_INTEGRATED_SHARE * len(h.imu_hist)
        assert (code == "no_propagation") == slow and has_ref == (not slow), k
        seen.add(code)
    assert seen == {"", "no_propagation"}, seen
