"""The filter step's solution numbers in one core call (core/solution.hpp, issue 19): C's roll/pitch and
their sigmas, the heading rate the arbitration blends with and method C's heading reading, read from the
held attitude and heading filters, give the Pipeline the same outputs as the reference's reads
(service/pipeline.py Pipeline._solution_attitude, AZIMUTHD_CORE=python runs them).

GIVEN simulated flights (a rail launch, a magnet nearby, a start in flight, variant B1) and real logs in
../shared/data (a multicopter started mid-flight, a VTOL), each run through the Pipeline on the core
backend twice, once with the solution numbers from the core call and once with the reference's reads,
THEN every filter step's solution (headings on the circle, the rest to 1e-9 relative:
tests/parity_compare.py, flags included), its aiding records, the magnetometer status and the events are
the same; the core call ran at every filter step with C levelled and never in the reference run. A
broken reading (C's heading variance, the heading rate) is caught. AZIMUTHD_CORE=python runs the
reference's reads."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

from estimators import core  # noqa: E402
from parity_compare import differences  # noqa: E402
from pipeline_recording import fly, run_with_backend, select_core_backend  # noqa: E402
from test_core_filter_chain import _aiding_differences  # noqa: E402
from test_core_polar_heading import DATA, NO_SITE, SIMS as C_SIMS, _solutions_differences  # noqa: E402

pytestmark = pytest.mark.skipif(not core.SOLUTION_AVAILABLE, reason=f"compiled core without the solution numbers "
                                                                    f"({core.IMPORT_ERROR or 'an older build'})")


def _started_in_flight():
    """The inclined-rail flight fed from 60 s after its launch (tests/test_pipeline_started_in_flight.py):
    no levelling, no launch, C re-initialised from the trusted FC attitude. -> (config, inputs)."""
    import test_pipeline_started_in_flight as sif
    captured = {}

    def capture(p, items, events):
        captured["items"] = items
        return []
    with pytest.MonkeyPatch.context() as mp:   # its Pipeline's config and inputs, not its run
        mp.setattr(sif, "Pipeline", lambda cfg: captured.setdefault("cfg", cfg))
        mp.setattr(sif, "feed_pipeline", capture)
        sif.feed_simulated("inclined_rail", 3, 100.0, 60.0, 100.0, overrides={"launcher": {"rest_s": 5.0}})
    return captured["cfg"], captured["items"]


def _b1():
    """The rail launch with method B's variant B1 (its heading fed from the other sources)."""
    from sim.offline import simulate
    from sitl import pipeline_inputs, scenario_site
    from service.config import validate
    run = simulate("inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=100.0, duration_s=40.0,
                   overrides={"launcher": {"rest_s": 8.0}})
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    return validate({**site, "mavlink": {"imu_rate_hz": 100.0}, "ahrs": {"variant": "b1"}}), pipeline_inputs(run)


SIMS = {"launch": C_SIMS["inclined_rail"], "magnet_nearby": C_SIMS["magnet_nearby"],
        "started_in_flight": _started_in_flight, "b1": _b1}
LOGS = ("arducopter-rtl-midflight.bin", "px4-vtol-airspeed-small.ulg")
_INPUTS: dict = {}
_CACHE: dict = {}


def _record_steps(sp, steps: list):
    """A Pipeline whose every filter step's solution is kept with its aiding records, magnetometer status
    and events so far (the real logs' replay keeps only its rows)."""
    base = sp.Pipeline

    class Recorded(base):
        def _solution(self, *a):
            sol = base._solution(self, *a)
            steps.append((sol, dict(self.aiding), self.mag_status, list(self.events)))
            return sol
    return Recorded


class _Counted:
    """core.solution_numbers with its calls counted; ``broken``: a wrapper given the real one (the
    mutation check)."""

    def __init__(self, real, broken=None):
        self.real, self.broken, self.n = real, broken, 0

    def __call__(self, *a):
        self.n += 1
        return self.real(*a) if self.broken is None else self.broken(self.real, *a)


def _both(name: str, monkeypatch, broken=None):
    """{"core": (steps, output, pipeline, core calls), "python": ...} of one flight on the core backend,
    the solution numbers from the core call ("core") or the reference's reads ("python"); ``broken``: a
    wrapper of core.solution_numbers (the mutation check)."""
    key = (name, broken)
    if key in _CACHE:
        return _CACHE[key]
    import service.pipeline as sp
    backend = select_core_backend(monkeypatch)
    runs = {}
    for mode in ("core", "python"):
        counted = _Counted(core.solution_numbers, broken)
        steps: list = []
        with monkeypatch.context() as mp:
            mp.setattr(core, "solution_numbers", counted)
            mp.setattr(core, "SOLUTION_AVAILABLE", mode == "core")
            mp.setattr(sp, "Pipeline", _record_steps(sp, steps))
            out, pipe = run_with_backend(lambda n: fly(n, SIMS, _INPUTS, DATA, NO_SITE), name, backend)
        runs[mode] = (steps, out, pipe, counted.n)
    _CACHE[key] = runs
    return runs


def _differences(runs: dict, name: str) -> list:
    (sc, oc, pc, _), (sp_, op, pp, _) = runs["core"], runs["python"]
    bad = _solutions_differences(op, oc, name)
    bad += _solutions_differences({"solutions": [s[0] for s in sp_]}, {"solutions": [s[0] for s in sc]},
                                  f"{name}.steps")
    bad += _aiding_differences([s[1] for s in sp_], [s[1] for s in sc], f"{name}.aiding")
    bad += differences([s[2:] for s in sp_], [s[2:] for s in sc], f"{name}.status_events")
    bad += differences((pp._yaw_P_prev, pp.mag_status, pp.arb), (pc._yaw_P_prev, pc.mag_status, pc.arb),
                       f"{name}.pipeline")
    return bad


@pytest.mark.parametrize("name", [*SIMS, *LOGS])
def test_core_solution_numbers_equal_the_reference(name, monkeypatch):
    runs = _both(name, monkeypatch)
    (sc, _, pc, nc), (sp_, _, pp, npy) = runs["core"], runs["python"]
    levelled = sum(1 for s in sp_ if s[0].roll_rad is not None)
    # the core call ran at the filter steps with C levelled there, never in the reference run
    assert npy == 0 and nc > 100 and nc <= len(sc), (nc, npy, len(sc))
    assert pc.solution_core and not pp.solution_core
    assert levelled > 100, levelled
    bad = _differences(runs, name)
    assert not bad, bad[:5]


EXERCISED = {  # what each simulated flight makes the solution do (so the parity above covers it): events,
    # sources fused in some step
    "launch": (("launch", "heading_source_change"), ("heading_filter",)),
    "magnet_nearby": (("magnetic_disturbance",), ("heading_filter",)),
    "started_in_flight": (("started in flight",), ("fc",)),
    "b1": (("launch",), ("heading_filter",)),
}


@pytest.mark.parametrize("name", list(SIMS))
def test_the_flights_exercise_the_solution(name, monkeypatch):
    steps, out, _, _ = _both(name, monkeypatch)["python"]
    text = " | ".join(f"{k}: {d}" for k, d in out["events"])
    events, fused = EXERCISED[name]
    for need in events:
        assert need in text, (need, text[:600])
    sources = {x for s in steps for x in s[0].heading_source.split("+")}
    assert set(fused) <= sources, sources
    # C's reading offered and not fused in some step, and not offered in another (its record's why)
    why = {s[1]["heading_filter"].why_not for s in steps if "heading_filter" in s[1]}
    assert len(why) >= 2, why


def _variance_off(real, *a):
    n = real(*a)
    if n is None or n[6] is None:
        return n
    c = n[6]
    return n[:6] + ((c[0], c[1] * 1.01) + c[2:],)


def _rate_off(real, *a):
    n = real(*a)
    return n if n is None or n[5] is None else n[:5] + (n[5] + 1e-4,) + n[6:]


@pytest.mark.parametrize("broken", [_variance_off, _rate_off])
def test_a_broken_reading_is_caught(broken, monkeypatch):
    # GIVEN C's heading variance 1 % off, or the heading rate 1e-4 rad/s off, in the core's numbers,
    # THEN the flight's comparison lists differences
    assert _differences(_both("started_in_flight", monkeypatch, broken), "started_in_flight")


def test_python_backend_runs_the_reference_reads(monkeypatch):
    # GIVEN AZIMUTHD_CORE=python, THEN the Pipeline reads the reference's numbers (no core call) and
    # gives headings (the start in flight)
    from service.pipeline import Pipeline
    from sitl import feed_pipeline
    monkeypatch.setenv("AZIMUTHD_CORE", "python")
    if "started_in_flight" not in _INPUTS:
        _INPUTS["started_in_flight"] = SIMS["started_in_flight"]()
    cfg, items = _INPUTS["started_in_flight"]
    counted = _Counted(core.solution_numbers)
    monkeypatch.setattr(core, "solution_numbers", counted)
    p = Pipeline(cfg)
    assert p.core.name == "python" and not p.solution_core
    sols = list(feed_pipeline(p, items, []))
    assert counted.n == 0 and sum(s.heading_valid for s in sols) > 100
