"""Method C's rest detection held in the core (core/zero_rate.hpp: HeldZeroRate, rest_step) and the
zero-rate updates of its attitude and heading filters in the core equal estimators/zero_rate.py.

GIVEN rests, motion, a slow turn, a time step back, a repeated time and a non-finite sample, THEN the held
rest detector gives the reference's measurements (1e-9 relative: tests/parity_compare.py) and state at
every step, and a deep copy is its own state. GIVEN the filters as a hand-held flight left them, THEN the
core's updates fuse and gate out as the reference's, with its states and test ratios; before levelling or
outside the platform formulation they give the reference's reasons."""
from __future__ import annotations

import copy
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

from estimators import core  # noqa: E402
from estimators import zero_rate as zr  # noqa: E402
from parity_compare import differences  # noqa: E402
from sitl import feed_pipeline  # noqa: E402
from test_core_polar_heading import SIMS, _state_differences  # noqa: E402

pytestmark = pytest.mark.skipif(not core.ZERO_RATE_AVAILABLE, reason=f"compiled core without the rest detector "
                                                                      f"({core.IMPORT_ERROR or 'an older build'})")


# --- the rest detector, driven directly -------------------------------------------------------------

def _rest_sequence(seed: int = 1):
    """(t, gyro, accel) of rests, motion, a slow turn, a time step back, a repeat and non-finite samples."""
    rng = np.random.default_rng(seed)
    bias = np.array([0.004, -0.002, 0.003])
    out, t = [], 0.0
    for k in range(1200):
        t += 0.02
        w = bias + rng.normal(0, 0.002, 3)
        f = np.array([0.1, -0.2, -9.8]) + rng.normal(0, 0.02, 3)
        if 300 <= k < 360:      # motion
            w = w + np.array([0.5, -0.3, 0.8]) * math.sin(k / 5.0)
            f = f + rng.normal(0, 2.0, 3)
        if 600 <= k < 700:      # a slow turn: beyond max_rate
            w = w + np.array([0.0, 0.0, 0.05])
        if k == 800:
            t -= 0.5            # time back: the detector restarts
        if k == 900:
            w = np.array([math.nan, 0.0, 0.0])
        if k == 950:
            t = t - 0.02        # the same time again
        out.append((t, w, f))
    return out


def test_rest_step_core_equals_reference():
    ref_s, core_s = zr.ZeroRateState(), zr.ZeroRateState()
    params = zr.ZeroRateParams()
    reported = 0
    for i, (t, w, f) in enumerate(_rest_sequence()):
        ref_s, rr = zr.rest_step(ref_s, t, w, f, params)
        core_s, rc = core.rest_step(core_s, t, w, f, params)
        assert (rr is None) == (rc is None), i
        bad = differences(ref_s, core_s.to_state(), f"state[{i}]")
        if rr is not None:
            reported += 1
            bad += differences(rr, rc, f"rate[{i}]")
        assert not bad, bad[:3]
    assert reported >= 20, reported
    # a deep copy is its own state, through the reference's record
    c2 = copy.deepcopy(core_s)
    assert isinstance(c2, core.HeldZeroRate) and c2._c is not core_s._c
    assert not differences(c2.to_state(), core_s.to_state())


def test_zero_rate_updates_core_equal_reference(monkeypatch):
    # the filters as the hand-held flight left them (levelled; the heading in the platform formulation)
    from service.pipeline import Pipeline
    monkeypatch.setenv("AZIMUTHD_CORE", "python")
    cfg, items = SIMS["handheld"]()
    pipe = Pipeline(cfg)
    for _ in feed_pipeline(pipe, items):
        pass
    att, hdg = pipe.polar_att, pipe.polar_hdg
    assert att.initialised and hdg.platform
    bias = np.asarray(att.x_hat[0:3], float)
    cases = [zr.RestRate(bias + np.array([1e-4, -2e-4, 5e-5]), np.full(3, 1e-8), 25, 2.0),   # fused
             zr.RestRate(bias + np.array([0.05, 0.0, 0.0]), np.full(3, 1e-10), 25, 2.0)]    # gated out
    fused = set()
    for k, rate in enumerate(cases):
        sr, dr = zr.attitude_zero_rate_update(att, rate)
        sc, dc = core.attitude_zero_rate_update_core(core.HeldPolarAttitude(att), rate)
        bad = differences(dr, dc, f"att diag[{k}]") + differences(sr, sc.to_state(), f"att state[{k}]")
        hr, er = zr.heading_zero_rate_update(hdg, rate)
        hc, ec = core.heading_zero_rate_update_core(core.HeldPolarHeading(hdg), rate)
        bad += differences(er, ec, f"hdg diag[{k}]") + _state_differences(hr, hc.to_state(), f"hdg state[{k}]")
        assert not bad, bad[:3]
        fused |= {("att", dr.fused), ("hdg", er.fused)}
    assert fused == {("att", True), ("att", False), ("hdg", True), ("hdg", False)}
    # not levelled / not in the platform formulation: the reference's reasons
    from estimators.polar_attitude import polar_attitude_init
    from estimators.polar_heading import polar_heading_init
    _, d = core.attitude_zero_rate_update_core(core.polar_attitude_init(), cases[0])
    assert not d.fused and not differences(d, zr.attitude_zero_rate_update(polar_attitude_init(), cases[0])[1])
    _, d = core.heading_zero_rate_update_core(core.polar_heading_init(), cases[0])
    assert not d.fused and not differences(d, zr.heading_zero_rate_update(polar_heading_init(), cases[0])[1])
