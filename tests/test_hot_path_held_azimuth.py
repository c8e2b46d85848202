"""Method A's state stays in the core across batches until Python reads it (service/hot_path.py,
``Pipeline._azimuth_held``; issue 19: no per-batch conversion of A's state on the daemon's batches
of one sample).

GIVEN a simulated launcher flight at 400 Hz (inclined rail, 8 s at rest; A fitting in flight) with
the bad samples of tests/test_core_hot_path.py (a non-finite sample, a repeated time, an
out-of-range sample), fed in batches of 1-4 rows (the daemon's batch path at 400 Hz: one or a few
RAW_IMU per wake-up) with the compiled core and its hot path, reading after each batch
only what the daemon reads every time (the solutions, the propagated solution, the aiding records,
the counters; not A's state),
THEN A's run is held across many consecutive batches, and every solution, event, propagated solution,
aiding record and counter, and at the end A's state and output, equal the core's on_imu sample by
sample bit for bit; a held run that drops the magnetometer samples it stored fails the comparison.
"""
from __future__ import annotations

import dataclasses
import random

import pytest

from mavlink_io.samples import FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, ImuSample, PressureSample
from parity_compare import differences
from service import core_backend
from service.hot_path import batch_of
import service.pipeline as sp
from test_core_hot_path import faulted_flight, in_batches
from estimators import core as ec

pytestmark = pytest.mark.skipif(not ec.HOT_PATH_AVAILABLE, reason="compiled core without the hot path")


@pytest.fixture(scope="module")
def flight():
    return faulted_flight(45.0, rate_hz=400.0)   # the daemon's rate: one RAW_IMU per wake-up


def _feed(p, items, seed: int = 11, max_batch: int = 4) -> dict:
    got = {"solutions": [], "events": [], "after_batch": [], "held_on": 0}

    def on_batch(run):
        held = p._azimuth_held
        got["solutions"] += p.on_imu_batch(batch_of(run))
        got["events"] += p.drain_events()
        got["held_on"] += held is not None and p._azimuth_held is held   # the same run went on
        got["after_batch"].append((p.propagated_solution(), dict(p.aiding), p.counters.imu_samples,
                                   p.counters.imu_rejected, p.last_time_fc_s))
    in_batches(p, items, random.Random(seed), max_batch, on_batch)
    got["azimuth"], got["azimuth_out"], got["status"] = p.azimuth, p.azimuth_out, p.azimuth_status()
    return got


def _run(backend, items, cfg) -> dict:
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(sp, "select_core", lambda: backend)
        return _feed(sp.Pipeline(cfg), items)
    finally:
        mp.undo()


def _compare(a: dict, b: dict) -> list:
    bad = differences(a["solutions"], b["solutions"], "solutions", 0.0)
    bad += differences(a["after_batch"], b["after_batch"], "after_batch", 0.0)
    bad += differences(a["azimuth"], b["azimuth"], "azimuth", 0.0)
    bad += differences(a["azimuth_out"], b["azimuth_out"], "azimuth_out", 0.0)
    if a["events"] != b["events"]:
        bad.append(("events", f"{len(a['events'])} vs {len(b['events'])}"))
    if a["status"] != b["status"]:
        bad.append(("status", f"{a['status']} vs {b['status']}"))
    return bad


def test_held_azimuth_run_equals_on_imu_bit_for_bit(flight):
    items, cfg = flight
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    each = _run(dataclasses.replace(core, hot_run=None), items, cfg)
    hot = _run(core, items, cfg)
    # A stepped and stored samples in flight, and its solver ran on them (its fits withheld the
    # azimuth this early: too little orientation diversity)
    assert any(k == "azimuth" and d.startswith("withheld") for k, d in each["events"]), each["events"]
    assert hot["held_on"] > 1000, hot["held_on"]   # A stayed in the core across batches
    assert len(each["azimuth"].samples) > 200
    bad = _compare(each, hot)
    assert not bad, bad[:5]


def test_a_held_run_that_loses_stored_samples_fails(flight, monkeypatch):
    items, cfg = flight
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    each = _run(dataclasses.replace(core, hot_run=None), items, cfg)
    import service.hot_path as hp
    real = hp._azimuth_run
    seen = {"n": 0}

    def leaky(p):
        arun, steps = real(p)
        if arun is not None and arun is p._azimuth_held:
            seen["n"] += 1
            if seen["n"] % 50 == 0:   # now and then a held run's stored samples are dropped
                arun.result()
        return arun, steps
    monkeypatch.setattr(hp, "_azimuth_run", leaky)
    wrong = _run(core, items, cfg)
    assert seen["n"] > 100
    assert _compare(each, wrong)


def _feed_one_by_one(p, items, step) -> dict:
    others = {PressureSample: p.on_pressure, FcAttitude: p.on_fc_attitude, FcHeartbeat: p.on_fc_heartbeat,
              FcFlightState: p.on_fc_flight_state, FcEkfStatus: p.on_fc_ekf_status}
    got = {"solutions": [], "events": [], "after_batch": []}
    for it in items:
        if type(it) is ImuSample:
            got["solutions"].append(step(p, it))
            got["events"] += p.drain_events()
            got["after_batch"].append((p.propagated_snapshot() is not None, dict(p.aiding), p.counters.imu_samples,
                                       p.counters.imu_rejected, p.last_time_fc_s))
        else:
            others[type(it)](it)
    got["solutions"].append(p.propagated_solution())
    got["azimuth"], got["azimuth_out"], got["status"] = p.azimuth, p.azimuth_out, p.azimuth_status()
    return got


def test_step_imu_equals_on_imu_bit_for_bit(flight):
    """The daemon's message path (Pipeline.step_imu: a quiet sample through the hot path as a batch
    of one row) gives on_imu's solutions, events, counters and A's state, bit for bit, sample by
    sample; the samples were taken by the core (on_imu not called for most in flight)."""
    items, cfg = flight
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(sp, "select_core", lambda: core)
        each = _feed_one_by_one(sp.Pipeline(cfg), items, lambda p, s: p.on_imu(s))
        p = sp.Pipeline(cfg)
        n_on_imu = [0]
        on_imu = p.on_imu

        def counted(s, *a):
            n_on_imu[0] += 1
            return on_imu(s, *a)
        p.on_imu = counted
        stepped = _feed_one_by_one(p, items, lambda p, s: p.step_imu(s))
    finally:
        mp.undo()
    n_imu = sum(type(it) is ImuSample for it in items)
    assert n_on_imu[0] < 0.5 * n_imu, (n_on_imu[0], n_imu)
    bad = _compare(each, stepped)
    assert not bad, bad[:5]
