"""Method C's filter step with its magnetometer chain as one core call (core/filter_chain.hpp, issue 19)
gives the Pipeline the same outputs as the Python chain it replaces (service/pipeline.py
Pipeline._filter_chain_python, each step a call of its own).

GIVEN simulated flights (hand-held, aerobatic, a magnet nearby, a magnet attached, an inclined rail) and
the real logs in ../shared/data, each run through the Pipeline on the core backend twice, once with the
chain in one core call and once with the Python chain, THEN the solutions (headings on the circle, the
rest to 1e-9 relative: tests/parity_compare.py), the aiding records, the magnetometer status, the events
(identical) and the final states of the attitude and heading filters, the rest detector, the hard iron
and the usability are the same; the core chain really ran (every filter step) and the flights exercised
what it does (rest updates, disturbance and relearn events, D's compensation applied). A backend with a
step replaced, or the reference, runs the Python chain. (The rest detector and the zero-rate updates
alone: tests/test_core_zero_rate.py.)"""
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

from estimators import core  # noqa: E402
from parity_compare import differences  # noqa: E402
from pipeline_recording import fly, run_with_backend, select_core_backend  # noqa: E402
from sitl import feed_pipeline  # noqa: E402
from test_core_polar_heading import (DATA, LOGS, NO_SITE, RTOL, SIMS, _angle_differences,  # noqa: E402
                                     _solutions_differences, _state_differences)

pytestmark = pytest.mark.skipif(not core.FILTER_CHAIN_AVAILABLE, reason=f"compiled core without the filter chain "
                                                                        f"({core.IMPORT_ERROR or 'an older build'})")

CHAIN_SIMS = ("handheld", "aerobatic", "magnet_nearby", "magnet_attached", "inclined_rail", "deviation")
_INPUTS: dict = {}


def _deviation_flight():
    """Method D calibrated in flight and applied once it covers enough attitudes (the calibration
    manoeuvre of tests/test_pipeline_deviation_hard_iron.py): the chain's deviation branch."""
    from sim.offline import simulate
    from sitl import pipeline_inputs, scenario_site
    from service.config import validate
    legs = [{"type": "climb", "alt_m": 150.0, "rate_m_s": 5.0}, {"type": "turn", "by_deg": 360.0, "bank_deg": 40.0},
            {"type": "figure8", "bank_deg": 30.0, "loops": 1}, {"type": "turn", "by_deg": -360.0, "bank_deg": 40.0}]
    run = simulate("inclined_rail", seed=3, imu_rate_hz=100.0, duration_s=None,
                   overrides={"legs": legs, "scenario": {"duration_s": 230.0},
                              "mag": {"hard_iron_gauss": [0.03, -0.02, -0.03], "soft_iron": np.eye(3).tolist(),
                                      "site_distortion_ned_gauss": [0.0, 0.0, 0.0]}})
    return validate({**scenario_site("inclined_rail"), "deviation": {"calibrate": True}}), pipeline_inputs(run)


SIMS = {**SIMS, "deviation": _deviation_flight}


def _fly(name: str) -> dict:
    """A simulated flight fed as the daemon feeds it, each solution with the aiding records and the
    magnetometer status after it; a real log replayed (tests/pipeline_recording.fly: its rows and events)."""
    import service.pipeline as sp
    if name not in SIMS:
        return fly(name, SIMS, _INPUTS, DATA, NO_SITE)
    if name not in _INPUTS:
        _INPUTS[name] = SIMS[name]()
    cfg, items = _INPUTS[name]
    p = sp.Pipeline(cfg)
    events: list = []
    sols, aiding, status = [], [], []
    for sol in feed_pipeline(p, items, events):
        sols.append(sol)
        aiding.append(dict(p.aiding))
        status.append(p.mag_status)
    return {"solutions": sols, "events": events, "aiding": aiding, "mag_status": status}


_CACHE: dict = {}


def _both(name: str, monkeypatch):
    """{"core": (out, pipeline, chain calls), "python": ...} of one flight on the core backend."""
    if name in _CACHE:
        return _CACHE[name]
    backend = select_core_backend(monkeypatch)
    runs = {}
    for mode in ("core", "python"):
        calls = [0]
        fused: list = []
        real, update = core.filter_chain_step, backend.attitude_zero_rate_update

        def counted(*a, **k):
            calls[0] += 1
            return real(*a, **k)

        def rest_update(*a, **k):   # the Python chain's zero-rate updates, fused or not
            st, d = update(*a, **k)
            fused.append(d.fused)
            return st, d
        with monkeypatch.context() as mp:
            mp.setattr(core, "filter_chain_step", counted)
            mp.setattr(core, "FILTER_CHAIN_AVAILABLE", mode == "core")
            out, pipe = run_with_backend(_fly, name, backend if mode == "core" else
                                         dataclasses.replace(backend, attitude_zero_rate_update=rest_update))
        runs[mode] = (out, pipe, calls[0], fused)
    _CACHE[name] = runs
    return runs


def _aiding_differences(a: list, b: list, where: str) -> list:
    """The aiding records of each step: the observation on the circle, an innovation in its own sigma
    (|d nu| <= 1e-9 sqrt(S): two headings of ~1 rad that agree leave a rounding-sized innovation, whose
    relative error is noise), a test ratio to 1e-9 max(1, ratio) (tests/test_core_polar_heading.py
    _diag_differences), the rest as tests/parity_compare.differences."""
    if len(a) != len(b):
        return [(where, f"{len(a)} vs {len(b)} steps")]
    bad: list = []
    for i, (ra, rb) in enumerate(zip(a, b)):
        if set(ra) != set(rb):
            bad.append((f"{where}[{i}]", f"{sorted(ra)} vs {sorted(rb)}"))
            continue
        for k in ra:
            x, y, w = ra[k], rb[k], f"{where}[{i}].{k}"
            blank = {}
            for nu, var, ratio in (("innovation_rad", "innovation_variance_rad2", "test_ratio"),
                                   ("source_innovation_rad", "source_innovation_variance_rad2", "source_test_ratio")):
                s_nu = math.sqrt(abs(getattr(x, var))) if math.isfinite(getattr(x, var)) else 1.0
                for f, tol in ((nu, RTOL * s_nu), (ratio, RTOL * max(1.0, abs(getattr(x, ratio)))
                                                   if math.isfinite(getattr(x, ratio)) else 0.0)):
                    u, v = getattr(x, f), getattr(y, f)
                    if not (u == v or (math.isnan(u) and math.isnan(v)) or abs(u - v) <= tol):
                        bad.append((f"{w}.{f}", f"{u!r} vs {v!r} (tolerance {tol:.3g})"))
                    blank[f] = 0.0
            bad += _angle_differences(x.observation_rad, y.observation_rad, f"{w}.observation_rad")
            blank["observation_rad"] = 0.0
            bad += differences(tuple(x._replace(**blank)), tuple(y._replace(**blank)), w)
    return bad


def _state(x):
    return x.to_state() if hasattr(x, "to_state") else x


@pytest.mark.parametrize("name", [*CHAIN_SIMS, *LOGS])
def test_core_chain_equals_the_python_chain(name, monkeypatch):
    runs = _both(name, monkeypatch)
    (oc, pc, nc, fc), (op, pp, npy, _) = runs["core"], runs["python"]
    n_steps = len(oc.get("solutions", oc.get("time_s")))
    if name.endswith(".ulg") and pc.polar_att.n_updates == 0:
        pytest.skip(f"{name}: the replay never steps C's attitude filter")
    # the chain ran in the core at every filter step there, never in the Python run
    assert npy == 0 and nc >= n_steps > 100 and not fc, (nc, npy, n_steps, len(fc))
    assert isinstance(pc.zero_rate, core.HeldZeroRate) and not isinstance(pp.zero_rate, core.HeldZeroRate)
    assert oc.get("events") == op.get("events")
    bad = _solutions_differences({k: v for k, v in op.items() if k != "aiding"},
                                 {k: v for k, v in oc.items() if k != "aiding"}, name)
    if "aiding" in op:
        bad += _aiding_differences(op["aiding"], oc["aiding"], f"{name}.aiding")
    bad += differences(_state(pp.polar_att), _state(pc.polar_att), "C attitude state")
    bad += _state_differences(_state(pp.polar_hdg), _state(pc.polar_hdg), "C heading state")
    bad += differences(_state(pp.zero_rate), _state(pc.zero_rate), "rest detector")
    bad += differences(_state(pp.mag_dist), _state(pc.mag_dist), "hard iron")
    bad += differences(_state(pp.mag_usability), _state(pc.mag_usability), "usability")
    bad += differences((pp.mag_status, pp._hdg_available, pp._deviation_in_use, pp._deviation_hard_iron_changed),
                       (pc.mag_status, pc._hdg_available, pc._deviation_in_use, pc._deviation_hard_iron_changed),
                       "pipeline flags")
    assert not bad, bad[:5]


EXERCISED = {  # what each simulated flight makes the chain do (so that the parity above covers it)
    "handheld": ("zero-rate update",),
    "inclined_rail": ("zero-rate update",),
    "magnet_nearby": ("magnetic_disturbance", "magnetometer"),
    "magnet_attached": ("magnetic_disturbance", "hard iron changed"),
    "aerobatic": ("heading_filter",),
    "deviation": ("deviation: compensation not applied: coverage", "deviation: compensation applied: coverage"),
}


@pytest.mark.parametrize("name", CHAIN_SIMS)
def test_the_flights_exercise_the_chain(name, monkeypatch):
    out, _, _, fused = _both(name, monkeypatch)["python"]
    text = " | ".join(f"{k}: {d}" for k, d in out["events"])
    for need in EXERCISED[name]:
        if need == "zero-rate update":   # rests measured and fused (the Python chain's calls)
            assert any(fused), fused
            continue
        assert need in text, (need, text[:400])


def test_pipeline_falls_back_to_the_python_chain(monkeypatch):
    # GIVEN AZIMUTHD_CORE=python, THEN the Pipeline runs the Python chain on the reference's states
    # (and gives the solutions of the core chain: the hand-held flight)
    from service.pipeline import Pipeline
    if "handheld" not in _INPUTS:
        _INPUTS["handheld"] = SIMS["handheld"]()
    cfg, items = _INPUTS["handheld"]
    monkeypatch.setenv("AZIMUTHD_CORE", "python")
    p = Pipeline(cfg)
    assert p.filter_chain_core is False
    # a backend with one of the chain's steps replaced (a test's recorder) runs the Python chain
    monkeypatch.delenv("AZIMUTHD_CORE")
    from service import core_backend
    b = core_backend.select()
    with monkeypatch.context() as mp:
        import service.pipeline as sp
        mp.setattr(sp, "select_core", lambda: dataclasses.replace(b, mag_usability_step=lambda *a: None))
        assert Pipeline(cfg).filter_chain_core is False
    monkeypatch.setenv("AZIMUTHD_CORE", "python")
    sols = list(feed_pipeline(p, items))
    assert dataclasses.is_dataclass(p.zero_rate) and dataclasses.is_dataclass(p.polar_att)
    monkeypatch.delenv("AZIMUTHD_CORE")
    q = Pipeline(cfg)
    assert q.filter_chain_core is True
    ref = list(feed_pipeline(q, items))
    assert isinstance(q.zero_rate, core.HeldZeroRate)
    assert len(sols) == len(ref) > 100
    assert sum(s.heading_rad is not None for s in sols) == sum(s.heading_rad is not None for s in ref) > 100
