"""Method A's filter-step samples on its held run in the core, its output built there, and its re-solve
handed one packed array (issue 19 item 1: service/hot_path.py azimuth_held_step / azimuth_output_held /
SamplePack, core/azimuth_output.hpp, estimators/azimuth.py PackedSamples).

GIVEN simulated flights of the three launch cases (an inclined rail, a vertical tube, a runway take-off
(launch.case aligned); 100 Hz, the filters at 50 Hz so every other sample is a filter step)
fed as the daemon's batch path feeds them (batches of 1-40 rows),
WHEN the Pipeline runs with the compiled core and its hot path,
THEN every solution, event (identical), A output and aiding record after each batch equal the Python
reference's (AZIMUTHD_CORE=python, on_imu per sample, the core's fit kernels: the fit has its own
parity test) to 1e-9 relative, A reaches a gated solution on each flight (so the output's solution
branch: the error correction, the sigmas, the vertical case's tilt term, is compared), and A's state is
taken back from the core only where the reference needs it (a solver submit, a result to apply, a
status change): not at every filter step. A held step fed a gyro off by 1e-6 relative, or an output
whose ARW term is off by 1e-4, fails the comparison.
"""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))
from sitl import pipeline_inputs, scenario_site  # noqa: E402
from parity_compare import differences  # noqa: E402
from test_core_hot_path import _compare, feed_batches, python_with_core_fit  # noqa: E402

from estimators import core as ec  # noqa: E402
from estimators.azimuth import azimuth_init  # noqa: E402
from service import core_backend  # noqa: E402
from service import hot_path  # noqa: E402
from service.config import validate  # noqa: E402
import service.pipeline as sp  # noqa: E402
from sim.offline import simulate  # noqa: E402

pytestmark = pytest.mark.skipif(not getattr(ec, "AZIMUTH_OUTPUT_AVAILABLE", False),
                                reason="compiled core without method A's output")
RATE_HZ = 100.0
FLIGHTS = {"inclined_rail": 70.0, "vertical_launch": 70.0, "runway_takeoff": 70.0}


def _flight(scenario: str):
    run = simulate(scenario=scenario, seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ,
                   duration_s=FLIGHTS[scenario], overrides={"launcher": {"rest_s": 8.0}})
    site = scenario_site(scenario)
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    return pipeline_inputs(run), validate({**site, "mavlink": {"imu_rate_hz": RATE_HZ}})


_FLIGHTS: dict = {}


def flight(scenario: str):
    if scenario not in _FLIGHTS:
        _FLIGHTS[scenario] = _flight(scenario)
    return _FLIGHTS[scenario]


def _run(backend, items, cfg, mp: pytest.MonkeyPatch) -> dict:
    """feed_batches with ``backend``; counts A's take-backs and the solver's submits."""
    n = {"back": 0, "submit": 0}
    take_back = sp.azimuth_take_back

    def counted(p):
        n["back"] += 1
        return take_back(p)
    mp.setattr(sp, "azimuth_take_back", counted)
    mp.setattr(sp, "select_core", lambda: backend)
    p = sp.Pipeline(cfg)
    # psi alone and a lower diversity gate: these short flights sweep 10-20 deg, and the solution branch
    # is what is compared
    p.azimuth_params = dataclasses.replace(p.azimuth_params, distortion_model="none", gate=dataclasses.replace(
        p.azimuth_params.gate, min_diversity_rad=math.radians(5.0)))
    p.azimuth = azimuth_init(p.azimuth_params)
    submit = p.solver.submit

    def submits(*a):
        n["submit"] += 1
        return submit(*a)
    p.solver.submit = submits
    got = feed_batches(p, items)
    got.update(n)
    return got


_REF: dict = {}


def _reference(scenario: str) -> dict:
    if scenario not in _REF:
        core = core_backend.select({"AZIMUTHD_CORE": "core"})
        mp = pytest.MonkeyPatch()
        try:
            _REF[scenario] = _run(python_with_core_fit(core), *flight(scenario), mp)
        finally:
            mp.undo()
    return _REF[scenario]


@pytest.mark.parametrize("scenario", sorted(FLIGHTS))
def test_held_filter_steps_and_core_output_equal_the_reference(scenario, monkeypatch):
    items, cfg = flight(scenario)
    ref = _reference(scenario)
    got = _run(core_backend.select({"AZIMUTHD_CORE": "core"}), items, cfg, monkeypatch)
    assert _compare(got, ref) == []
    outs = [x[1] for x in got["after_batch"] if x[1] is not None]
    assert any(o.status == "solved" and o.valid for o in outs), {o.status for o in outs}
    assert got["python_handled"] < 0.6 * got["pipeline"].counters.imu_samples   # the quiet samples stayed in the core
    # A's state back in Python only where the reference needs it (at most one per submit, and a few
    # status changes), not at each of the flight's filter steps
    flight_s = FLIGHTS[scenario] - 8.0
    assert got["submit"] > 10 and got["back"] <= got["submit"] + 10, (got["back"], got["submit"])
    assert got["back"] < 0.2 * flight_s * 50.0


def test_a_wrong_held_step_fails_the_comparison(monkeypatch):
    items, cfg = flight("inclined_rail")
    ref = _reference("inclined_rail")
    step = hot_path.azimuth_held_step

    def off(p, gyro_rad_s, mag_gauss, time_s):
        return step(p, gyro_rad_s * (1.0 + 1e-6), mag_gauss, time_s)
    monkeypatch.setattr(sp, "azimuth_held_step", off)
    got = _run(core_backend.select({"AZIMUTHD_CORE": "core"}), items, cfg, monkeypatch)
    assert _compare(got, ref) != []


def test_a_wrong_core_output_fails_the_comparison(monkeypatch):
    items, cfg = flight("inclined_rail")
    ref = _reference("inclined_rail")
    cfg_of = ec.azimuth_output_cfg

    def off(st):
        c = cfg_of(st)
        return c if not c[0] else (*c[:7], c[7] * (1.0 + 1e-4), *c[8:])
    monkeypatch.setattr(ec, "azimuth_output_cfg", off)
    got = _run(core_backend.select({"AZIMUTHD_CORE": "core"}), items, cfg, monkeypatch)
    assert _compare(got, ref) != []


def test_backend_without_the_core_output_takes_the_reference_path(monkeypatch):
    """A core backend whose output numbers are the reference's (an older build, a test's backend): the
    held run is taken back at the filter steps and the reference's output built: the same results."""
    items, cfg = flight("inclined_rail")
    core = dataclasses.replace(core_backend.select({"AZIMUTHD_CORE": "core"}),
                               azimuth_output_numbers=core_backend.Backend.azimuth_output_numbers)
    got = _run(core, items, cfg, monkeypatch)
    assert _compare(got, _reference("inclined_rail")) == []
    assert got["back"] > 0.5 * (FLIGHTS["inclined_rail"] - 8.0) * 50.0   # every filter step took it back


def test_the_solver_gets_one_packed_array_and_solves_the_same(monkeypatch):
    """Item 2: what the Pipeline submits carries A's samples as one (N, 49) array (PackedSamples, rows
    equal to the records' bit for bit, the core's rows on the held path), it pickles with no MagRecord
    in it, and its solve equals the records' solve bit for bit."""
    import pickle

    from estimators import azimuth as az
    from service.solver import InlineSolver
    items, cfg = flight("vertical_launch")
    seen = []

    class Recording(InlineSolver):
        def submit(self, state, time_s, *kernels):
            seen.append((state, time_s, kernels))
            return super().submit(state, time_s, *kernels)
    monkeypatch.setattr(sp, "select_core", lambda: core_backend.select({"AZIMUTHD_CORE": "core"}))
    p = sp.Pipeline(cfg, solver=Recording())
    p.azimuth_params = dataclasses.replace(p.azimuth_params, distortion_model="none", gate=dataclasses.replace(
        p.azimuth_params.gate, min_diversity_rad=math.radians(5.0)))
    p.azimuth = azimuth_init(p.azimuth_params)
    feed_batches(p, items)
    records = p.azimuth.samples
    assert len(seen) > 10 and len(records) > 200
    solved = 0
    for st, t, kernels in seen[::5] + seen[-1:]:
        assert isinstance(st.samples, az.PackedSamples) and st.samples.rows.shape == (len(st.samples), 49)
        mine = records[:len(st.samples)]
        assert np.array_equal(st.samples.rows, az.pack_samples(mine))
        as_records = dataclasses.replace(st, samples=mine)
        sent = pickle.dumps(st)   # what a worker process gets: one array, no MagRecord
        assert b"MagRecord" not in sent and b"MagRecord" in pickle.dumps(as_records)
        assert len(pickle.loads(sent).samples) == len(mine)
        a = az.azimuth_solve_result(az.azimuth_solve(st, t, *kernels))
        b = az.azimuth_solve_result(az.azimuth_solve(as_records, t, *kernels))
        assert differences(a, b, "solve", 0.0) == []
        solved += a["last_gate_reason"] == ""
    assert solved > 0
