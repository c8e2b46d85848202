"""Method D's deviation RLS in the compiled core equals its Python reference (issue 19 item 2):
estimators/mag_deviation.py (deviation_step, corrected_mag, residual_sigma_gauss, deviation_coverage,
as the Pipeline calls them) against core/mag_deviation.hpp through estimators/core.py (HeldDeviation).

GIVEN observation triplets of a calibration manoeuvre (every heading, rolls and pitches within and
beyond the limits, a non-finite one) in a hard- and soft-iron distorted field, for the seed's model
and the extended one, with and without forgetting,
WHEN the reference and the core step the same observations,
THEN after every step the coefficients, P (per element against sqrt(P_ii P_jj)), the counts, the
residual sums, the diagnostics (updated, reason, a-priori residual), the corrected field, the residual
sigma and the coverage are equal to 1e-9 relative (tests/parity_compare.py), and the held state reads
like the reference's (to_dict round trip, the reference's functions accept it);
AND a simulated flight through the daemon's Pipeline with D calibrating and applied (a covered state
given at the start) gives the same D state, the same events and the same solutions with the core
backend as with the Python reference.
"""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from estimators import core
from estimators import mag_deviation as dv
from estimators.rotations import dcm_from_euler
from tests.parity_compare import differences

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

pytestmark = pytest.mark.skipif(not core.DEVIATION_AVAILABLE,
                                reason=f"compiled core without method D's RLS: {core.IMPORT_ERROR or 'old build'}")

FIELD = np.array([0.21, 0.01, 0.43])
SOFT = np.array([[1.05, 0.03, -0.02], [0.03, 0.96, 0.04], [-0.02, 0.04, 1.02]])
HARD = np.array([0.06, -0.04, 0.03])


def _observations(n=900, seed=2):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        psi = 0.013 * k * 7.0 % (2 * math.pi) - (0.5 if k % 5 == 0 else 0.0)   # some negative headings
        roll = 0.6 * math.sin(0.037 * k)      # beyond the 30 deg limit at the peaks
        pitch = 0.4 * math.sin(0.023 * k + 1.0)
        m = SOFT @ (dcm_from_euler(roll, pitch, psi).T @ FIELD) + HARD + rng.normal(0, 0.002, 3)
        if k == 17:
            m = np.array([math.nan, 0.0, 0.0])
        out.append((m, psi, roll, pitch))
    return out


def _state(s):
    return s.to_state() if isinstance(s, core.HeldDeviation) else s


@pytest.mark.parametrize("params", [dv.DeviationParams(), dv.DeviationParams(extended=True),
                                    dv.DeviationParams(forgetting_factor=0.98, heading_bins=8)])
def test_steps_equal(params):
    a = dv.deviation_init(params)
    b = a
    n_updated = n_refused = 0
    for m, psi, roll, pitch in _observations():
        a, da = dv.deviation_step(a, m, FIELD, psi, roll, pitch, params)
        b_prev = b
        b, db = core.deviation_step(b, m, FIELD, psi, roll, pitch, params)
        assert (da.updated, da.reason) == (db.updated, db.reason)
        if not db.updated:
            assert b is b_prev    # a refused observation leaves the state as it was (the reference's too)
        n_updated += da.updated
        n_refused += not da.updated
        bad = differences(a, _state(b), "state") + differences(da, db, "diag")
        assert bad == [], bad[:5]
        assert differences(dv.corrected_mag(a, m, psi, roll, pitch), core.corrected_mag(b, m, psi, roll, pitch)) == []
        assert differences(dv.residual_sigma_gauss(a), core.residual_sigma_gauss(b)) == []
        assert dv.deviation_coverage(a, params) == core.deviation_coverage(b, params)
    assert n_updated > 300 and n_refused > 50
    assert dv.deviation_coverage(a, params).overall == 1.0
    sig = dv.residual_sigma_gauss(a)
    assert np.all(sig > 0.0) and np.all(sig < 0.05)


def test_held_state_reads_like_the_reference():
    p = dv.DeviationParams()
    a = dv.deviation_init(p)
    for m, psi, roll, pitch in _observations(200):
        a, _ = dv.deviation_step(a, m, FIELD, psi, roll, pitch, p)
    held = core.HeldDeviation(a)
    assert differences(a, held.to_state()) == []
    assert dv.DeviationState.from_dict(held.to_dict()).to_dict() == a.to_dict()
    # the reference's functions read the held state (the Pipeline's aiding record and residual use them)
    assert dv.deviation_coverage(held, p) == dv.deviation_coverage(a, p)
    assert np.array_equal(dv.residual_sigma_gauss(held), dv.residual_sigma_gauss(a))
    # a step does not change the state it was given (the reference returns a new one too)
    m, psi, roll, pitch = _observations(1)[0]
    before = held.to_dict()
    new, d = core.deviation_step(held, m, FIELD, psi, roll, pitch, p)
    assert d.updated and new is not held and held.to_dict() == before and new.n == held.n + 1
    with pytest.raises(ValueError, match="shape"):
        core.deviation_step(held, np.zeros(2), FIELD, 0.0, 0.0, 0.0, p)
    with pytest.raises(ValueError, match="coverage bins"):
        core.deviation_step(held, m, FIELD, 0.0, 0.0, 0.0, dv.DeviationParams(heading_bins=6))


def test_pipeline_flight_core_equals_reference(monkeypatch):
    from tests.test_pipeline_deviation_hard_iron import _covered_deviation
    from service.config import validate
    from service.pipeline import Pipeline
    from sim.offline import simulate
    from sitl import feed_pipeline, pipeline_inputs, scenario_site
    run = simulate("inclined_rail", seed=4, imu_rate_hz=100.0, duration_s=100.0,
                   overrides={"mag": {"hard_iron_gauss": HARD.tolist(), "soft_iron": SOFT.tolist()}})
    cfg = validate({**scenario_site("inclined_rail"), "deviation": {"calibrate": True}})
    items = pipeline_inputs(run)
    out = {}
    for backend in ("python", "core"):
        monkeypatch.setenv("AZIMUTHD_CORE", backend)
        p = Pipeline(cfg)
        p.deviation = _covered_deviation(p)
        events: list = []
        sols = list(feed_pipeline(p, items, events))
        out[backend] = p, sols, events
    (pp, sp, ep), (pc, sc, ec) = out["python"], out["core"]
    assert pp.core.name == "python" and pc.core.name == "core"
    assert isinstance(pc.deviation, core.HeldDeviation) and not isinstance(pp.deviation, core.HeldDeviation)
    assert pc._deviation_in_use is True and pp._deviation_in_use is True     # D's correction was applied
    assert pc.deviation.n == pp.deviation.n > 48 * 7 * 5                      # and it learnt in flight
    assert differences(pp.deviation, pc.deviation.to_state()) == []
    assert ec == ep
    assert len(sc) == len(sp) > 1000
    bad = []
    for a, b in zip(sp, sc):
        bad += differences(dataclasses.asdict(a), dataclasses.asdict(b), f"t={a.time_fc_s}")
        if len(bad) > 5:
            break
    assert bad == [], bad[:5]
