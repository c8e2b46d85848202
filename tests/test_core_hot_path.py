"""The Pipeline's per-sample hot path (service/hot_path.py, core/hot_path.hpp) behind on_imu_batch
gives what on_imu gives sample by sample.

GIVEN a simulated launcher flight (inclined rail, 8 s at rest, 100 Hz) with method A solving in
flight, a non-finite sample, a repeated time, an out-of-range sample mid-batch and, late, an IMU gap
that disables A (the rest of the flight with A off), fed as the daemon's batch path feeds it (the
IMU samples between two other items in batches of 1-40 rows), THEN with the compiled core and its
hot path every NavSolution, event, counter, aiding record, A output and the propagated solution at
each batch's end equal the Python reference's (AZIMUTHD_CORE=python, on_imu per sample) to 1e-9
relative (tests/parity_compare), most samples never reach Python, and A's state (its stored
samples, G, C) is the reference's. A hot path with a deliberate fault (the x rate it integrates
off by 1e-6 rad/s, or the accumulated rate off by 1e-7 rad/s) fails the same comparison. The real logs: see
tests/test_replay_batches.py."""
from __future__ import annotations

import dataclasses
import random
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))
from sitl import pipeline_inputs, scenario_site  # noqa: E402
from parity_compare import differences  # noqa: E402

from estimators import core as ec  # noqa: E402
from mavlink_io.samples import FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, ImuSample, PressureSample  # noqa: E402
from service import core_backend  # noqa: E402
from service.config import validate  # noqa: E402
from service.hot_path import batch_of  # noqa: E402
import service.pipeline as sp  # noqa: E402
from sim.offline import simulate  # noqa: E402

pytestmark = pytest.mark.skipif(not ec.HOT_PATH_AVAILABLE, reason="compiled core without the hot path")
RATE_HZ = 100.0


def _faulted(items: list) -> list:
    """The flight with bad samples mid-flight: NaN gyro at 17 s, the same time twice at 18 s, a
    1000 m/s^2 sample at 19 s, and 0.7 s of samples missing from 95 s (a gap: A is disabled)."""
    out, done = [], set()
    for it in items:
        if type(it) is ImuSample:
            t = it.time_fc_s
            if t >= 17.0 and "nan" not in done:
                done.add("nan")
                out.append(dataclasses.replace(it, gyro_rad_s=np.array([np.nan, 0.0, 0.0])))
                continue
            if t >= 18.0 and "dup" not in done:
                done.add("dup")
                out += [it, dataclasses.replace(it, gyro_rad_s=it.gyro_rad_s * 1.01)]
                continue
            if t >= 19.0 and "range" not in done:
                done.add("range")
                out.append(dataclasses.replace(it, accel_m_s2=np.array([1000.0, 0.0, -9.8])))
                continue
            if 95.0 <= t < 95.7:
                continue
        out.append(it)
    assert done == {"nan", "dup", "range"}
    return out


def faulted_flight(duration_s: float, rate_hz: float = RATE_HZ) -> tuple[list, dict]:
    """The inclined-rail flight with the input faults of ``_faulted``, and its config."""
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=rate_hz,
                   duration_s=duration_s, overrides={"launcher": {"rest_s": 8.0}})
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    return _faulted(pipeline_inputs(run)), validate({**site, "mavlink": {"imu_rate_hz": rate_hz}})


@pytest.fixture(scope="module")
def flight():
    return faulted_flight(100.0)


def in_batches(p, items, rng: random.Random, max_batch: int, on_batch) -> None:
    """``items`` as the daemon's batch path hands them: consecutive IMU samples to ``on_batch(list)``
    in batches of 1..max_batch rows (cut at every other item), the others to their handlers."""
    others = {PressureSample: p.on_pressure, FcAttitude: p.on_fc_attitude, FcHeartbeat: p.on_fc_heartbeat,
              FcFlightState: p.on_fc_flight_state, FcEkfStatus: p.on_fc_ekf_status}
    run: list = []
    size = rng.randint(1, max_batch)
    for it in items:
        if type(it) is ImuSample:
            run.append(it)
            if len(run) >= size:
                on_batch(run)
                run = []
                size = rng.randint(1, max_batch)
        else:
            if run:
                on_batch(run)
                run = []
            others[type(it)](it)
    if run:
        on_batch(run)


def feed_batches(p, items, seed: int = 7, max_batch: int = 40) -> dict:
    """``items`` through ``in_batches``; after each batch what the daemon reads: the propagated
    solution, A's output, the aiding records, the counters."""
    got = {"solutions": [], "events": [], "after_batch": []}
    handled = [0]
    on_imu = p.on_imu

    def counted(s, *a):
        handled[0] += 1
        return on_imu(s, *a)
    p.on_imu = counted

    def on_batch(run):
        got["solutions"] += p.on_imu_batch(batch_of(run))
        got["events"] += p.drain_events()
        got["after_batch"].append((p.propagated_solution(), p.azimuth_out, dict(p.aiding), p.counters.imu_samples,
                                   p.counters.imu_rejected, p.last_time_fc_s, p.azimuth_status()))
    in_batches(p, items, random.Random(seed), max_batch, on_batch)
    got["python_handled"] = handled[0]
    got["pipeline"] = p
    return got


_RUNS: dict = {}


def _run(name: str, backend, items, cfg) -> dict:
    if name not in _RUNS:
        mp = pytest.MonkeyPatch()
        try:
            mp.setattr(sp, "select_core", lambda: backend)
            _RUNS[name] = feed_batches(sp.Pipeline(cfg), items)
        finally:
            mp.undo()
    return _RUNS[name]


INNOVATIONS = ("innovation_rad", "test_ratio", "source_innovation_rad", "source_test_ratio")
"""Aiding-record fields that are differences of near-equal headings (observation minus fused): the
core's method B and the reference agree on each heading to 1e-9 relative, not on their difference,
with or without the hot path (test_hot_path_equals_on_imu_exactly holds them to the bit there)."""


def _records(after_batch, innovations: bool):
    if innovations:
        return after_batch
    return [(*x[:2], {k: r._replace(**{f: 0.0 for f in INNOVATIONS}) for k, r in x[2].items()}, *x[3:])
            for x in after_batch]


def _compare(a: dict, b: dict, rtol: float = 1e-9, innovations: bool = False) -> list:
    bad = differences(a["solutions"], b["solutions"], "solutions", rtol)
    bad += differences(_records(a["after_batch"], innovations), _records(b["after_batch"], innovations),
                       "after_batch", rtol)
    if a["events"] != b["events"]:
        bad.append(("events", f"{len(a['events'])} vs {len(b['events'])}"))
    return bad


def _backends():
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    return core_backend.select({"AZIMUTHD_CORE": "python"}), core, dataclasses.replace(core, hot_run=None)


def test_hot_path_equals_python_reference(flight):
    items, cfg = flight
    python, core, _ = _backends()
    ref = _run("python", python, items, cfg)
    hot = _run("core", core, items, cfg)
    pr, ph = ref["pipeline"], hot["pipeline"]
    assert pr.core.hot_run is None and ph.core.hot_run is not None
    n_imu = sum(type(it) is ImuSample for it in items)
    assert ref["python_handled"] == n_imu
    # the flight did what the test is about: A solved, the bad samples were rejected, the gap disabled A
    ev = ref["events"]
    assert ("azimuth", "solved") in ev, ev
    assert pr.counters.imu_rejected == 3 and pr.input_checks.counts["gap"] == 1
    assert pr.azimuth_status().startswith("disabled: IMU gap in flight")
    # the samples that reached Python: the filter steps (50 Hz of 100 Hz), the ground, A's solver
    # schedule and the faults; the others never did
    assert hot["python_handled"] < 0.6 * n_imu, (hot["python_handled"], n_imu)
    assert len(ref["solutions"]) > 4000
    bad = _compare(ref, hot)
    assert not bad, bad[:5]
    assert ev == hot["events"]
    assert pr.input_checks.counts == ph.input_checks.counts
    assert len(pr.azimuth.samples) == len(ph.azimuth.samples) > 200
    assert not differences(pr.azimuth, ph.azimuth, "azimuth")


def test_hot_path_equals_on_imu_exactly(flight):
    """The core with its hot path against the core's on_imu for every sample: bit for bit (measured;
    the real logs are compared to 1e-12: tests/test_replay_batches.py NOT_REPRODUCIBLE)."""
    items, cfg = flight
    _, core, no_hot = _backends()
    hot = _run("core", core, items, cfg)
    each = _run("core_on_imu", no_hot, items, cfg)
    assert each["python_handled"] == sum(type(it) is ImuSample for it in items) > hot["python_handled"]
    bad = _compare(each, hot, rtol=0.0, innovations=True)
    assert not bad, bad[:5]
    assert not differences(each["pipeline"].azimuth, hot["pipeline"].azimuth, "azimuth", 0.0)


def _mutant(run, fault: str):
    def wrong(state, checks, strapdown, azimuth, rows, start, *a):
        if fault == "gyro":
            rows = rows.copy()
            rows[:, 2] += 1e-6
        out = run(state, checks, strapdown, azimuth, rows, start, *a)
        if fault == "rate" and out[3]:
            state.acc_gyro = state.acc_gyro + 1e-7 * out[3]
        return out
    return wrong


@pytest.mark.parametrize("fault", ["gyro", "rate"])
def test_a_wrong_hot_path_fails_the_comparison(flight, fault):
    items, cfg = flight
    python, core, _ = _backends()
    ref = _run("python", python, items, cfg)
    wrong = _run("mutant_" + fault, dataclasses.replace(core, hot_run=_mutant(core.hot_run, fault)), items, cfg)
    assert _compare(ref, wrong)
