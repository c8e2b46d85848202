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


def python_with_core_fit(core):
    """The Python reference backend with method A's fit kernels taken from ``core``: these tests
    are about the hot path (who sees which sample), not the fit. A's fit has its own parity test
    (tests/test_core_azimuth_fit.py): equal to 1e-9 on every solve the gate can accept; on an
    ill-conditioned one the gate rejects (this flight's gap-disabled A solves at condition 6.5e5)
    the reference does not reproduce itself to 1e-9 (samples reversed: 1e-6 at 8e4), so there it is
    held to 10x that, and a whole-Pipeline compare at 1e-9 would be comparing two LAPACKs."""
    python = core_backend.select({"AZIMUTHD_CORE": "python"})
    return dataclasses.replace(python, azimuth_fit_psi=core.azimuth_fit_psi,
                               azimuth_orientation_diversity=core.azimuth_orientation_diversity)


def _backends():
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    return python_with_core_fit(core), core, dataclasses.replace(core, hot_run=None)


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


# --- the message path's bound hot path (service/hot_path.sample_step, _core.HotPath) ----------------

def _feed_step(p, items, step) -> dict:
    """Every IMU sample through ``step(p, s)`` (the daemon's message path), the others to their
    handlers; after each sample what the daemon reads."""
    others = {PressureSample: p.on_pressure, FcAttitude: p.on_fc_attitude, FcHeartbeat: p.on_fc_heartbeat,
              FcFlightState: p.on_fc_flight_state, FcEkfStatus: p.on_fc_ekf_status}
    got = {"solutions": [], "events": [], "after_batch": []}
    for it in items:
        if type(it) is ImuSample:
            sol = step(p, it)
            if sol is not None:
                got["solutions"].append(sol)
            got["events"] += p.drain_events()
            got["after_batch"].append((p.propagated_solution(), p.azimuth_out, dict(p.aiding), p.counters.imu_samples,
                                       p.counters.imu_rejected, p.last_time_fc_s, p.azimuth_status()))
        else:
            others[type(it)](it)
    got["pipeline"] = p
    return got


_STEPPED: dict = {}


def _stepped(backend, items, cfg, on_imu_only: bool = False, count: list | None = None, key: str | None = None) -> dict:
    """A Pipeline on ``backend`` fed sample by sample (step_imu, or on_imu only); ``key``: cached
    under it for the module (a whole flight each)."""
    if key is not None and key in _STEPPED:
        return _STEPPED[key]
    got = _stepped_run(backend, items, cfg, on_imu_only, count)
    if key is not None:
        _STEPPED[key] = got
    return got


def _stepped_run(backend, items, cfg, on_imu_only: bool, count: list | None) -> dict:
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(sp, "select_core", lambda: backend)
        p = sp.Pipeline(cfg)
        if count is not None:
            on_imu = p.on_imu

            def counted(s, *a):
                count[0] += 1
                return on_imu(s, *a)
            p.on_imu = counted
        return _feed_step(p, items, (lambda p, s: p.on_imu(s)) if on_imu_only else (lambda p, s: p.step_imu(s)))
    finally:
        mp.undo()


@pytest.mark.skipif(not hasattr(ec, "HotPath"), reason="compiled core without the bound hot path")
def test_step_imu_bound_hot_path_equals_on_imu_exactly(flight):
    """step_imu (each quiet sample through the Pipeline's bound _core.HotPath, read from the ImuSample
    in C++) against the core's on_imu for every sample, on the faulted flight: bit for bit; most
    samples never reach on_imu; and the reference to 1e-9."""
    items, cfg = flight
    python, core, _ = _backends()
    count = [0]
    stepped = _stepped(core, items, cfg, count=count)
    each = _stepped(core, items, cfg, on_imu_only=True, key="core_on_imu")
    p = stepped["pipeline"]
    assert type(p._hot_bound.hot) is ec.HotPath   # the bound object took them, not a batch of one row
    n_imu = sum(type(it) is ImuSample for it in items)
    assert count[0] < 0.6 * n_imu, (count[0], n_imu)
    bad = _compare(each, stepped, rtol=0.0, innovations=True)
    assert not bad, bad[:5]
    assert not differences(each["pipeline"].azimuth, p.azimuth, "azimuth", 0.0)
    ref = _stepped(python, items, cfg, on_imu_only=True)
    assert ref["events"] == stepped["events"]
    bad = _compare(ref, stepped)
    assert not bad, bad[:5]


class _MutantHotPath:
    """A bound hot path whose flight step sees the x rate 1e-6 rad/s off (what the comparison must catch)."""

    def __init__(self, *a):
        self._h = ec.HotPath(*a)
        self.run, self.run_ground, self.ground = self._h.run, self._h.run_ground, self._h.ground

    def flight(self, s, *a):
        return self._h.flight(dataclasses.replace(s, gyro_rad_s=s.gyro_rad_s + np.array([1e-6, 0.0, 0.0])), *a)


@pytest.mark.skipif(not hasattr(ec, "HotPath"), reason="compiled core without the bound hot path")
def test_a_wrong_bound_hot_path_fails_the_comparison(flight, monkeypatch):
    import service.hot_path as hp
    items, cfg = flight
    _, core, _ = _backends()
    each = _stepped(core, items, cfg, on_imu_only=True, key="core_on_imu")
    monkeypatch.setattr(hp, "_HOT_PATH", _MutantHotPath)
    wrong = _stepped(core, items, cfg)
    assert type(wrong["pipeline"]._hot_bound.hot) is _MutantHotPath
    assert _compare(each, wrong)


def _odd_forms(items: list) -> list:
    """The flight with samples in forms the link never makes but on_imu takes, mid-flight and on the
    ground: a list magnetometer field, float32 arrays, a numpy float time, no magnetometer field, a
    NaN in it, another source."""
    forms = [lambda s: dataclasses.replace(s, mag_gauss=s.mag_gauss.tolist() if s.mag_gauss is not None else None),
             lambda s: dataclasses.replace(s, accel_m_s2=s.accel_m_s2.astype(np.float32)),
             lambda s: dataclasses.replace(s, gyro_rad_s=s.gyro_rad_s.astype(np.float32)),
             lambda s: dataclasses.replace(s, mag_gauss=None),
             lambda s: dataclasses.replace(s, mag_gauss=np.array([np.nan, 0.1, 0.2])),
             lambda s: dataclasses.replace(s, time_fc_s=np.float64(s.time_fc_s)),
             lambda s: dataclasses.replace(s, source="SCALED_IMU")]
    out, k = [], 0
    for it in items:
        if type(it) is ImuSample and (3.0 <= it.time_fc_s < 3.2 or 30.0 <= it.time_fc_s < 30.2):
            it = forms[k % len(forms)](it)
            k += 1
        out.append(it)
    assert k > 20
    return out


@pytest.mark.skipif(not hasattr(ec, "HotPath"), reason="compiled core without the bound hot path")
def test_step_imu_takes_odd_sample_forms_as_on_imu_does(flight):
    """Samples not in the link's form (the bound path leaves them unread: their row is built in
    Python, numpy converting them) and odd but readable ones give on_imu's results and events, in
    flight and on the ground, bit for bit."""
    items, cfg = flight
    items = _odd_forms(items[: len(items) // 3])
    _, core, _ = _backends()
    stepped = _stepped(core, items, cfg)
    each = _stepped(core, items, cfg, on_imu_only=True)
    bad = _compare(each, stepped, rtol=0.0, innovations=True)
    assert not bad, bad[:5]
    assert each["pipeline"].input_checks.counts == stepped["pipeline"].input_checks.counts


@pytest.mark.skipif(not hasattr(ec, "HotPath"), reason="compiled core without the bound hot path")
def test_a_deep_copied_pipeline_binds_its_own_hot_path(flight):
    """A Pipeline copied mid-flight (copy.deepcopy) after its bound hot path took samples goes on
    through its own binding (its own per-sample state), exactly as the original would; the original
    does not move."""
    import copy
    items, cfg = flight
    _, core, _ = _backends()
    whole = _stepped(core, items, cfg, key="core_step_imu")
    split = next(i for i, it in enumerate(items) if type(it) is ImuSample and it.time_fc_s >= 40.0)
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(sp, "select_core", lambda: core)
        first = sp.Pipeline(cfg)
        head = _feed_step(first, items[:split], lambda p, s: p.step_imu(s))
        assert type(first._hot_bound.hot) is ec.HotPath
        last_t = first.last_time_fc_s
        first.azimuth   # A's run held in the core is taken back first (a _core.AzimuthRun does not copy)
        second = copy.deepcopy(first)
        tail = _feed_step(second, items[split:], lambda p, s: p.step_imu(s))
    finally:
        mp.undo()
    assert second._hot_bound.hot is not first._hot_bound.hot
    assert first.last_time_fc_s == last_t
    joined = {k: head[k] + tail[k] for k in ("solutions", "events", "after_batch")}
    bad = _compare(whole, joined, rtol=0.0, innovations=True)
    assert not bad, bad[:5]


@pytest.mark.skipif(not hasattr(ec, "HotPath"), reason="compiled core without the bound hot path")
def test_bound_hot_path_refuses_bad_inputs_with_clear_errors():
    st, checks = ec.SampleState(), core_backend.select({"AZIMUTHD_CORE": "core"}).input_checks(
        sp.InputCheckParams())._c
    with pytest.raises(ValueError, match="C_body_from_sensor"):
        ec.HotPath(st, checks, np.eye(2), 0.1, 0.1, 0.02)
    with pytest.raises(ValueError, match="filter period"):
        ec.HotPath(st, checks, np.eye(3), 0.1, 0.1, 0.0)
    with pytest.raises(ValueError, match="SampleState"):
        ec.HotPath(None, checks, np.eye(3), 0.1, 0.1, 0.02)
    with pytest.raises(ValueError, match="InputChecks"):
        ec.HotPath(st, None, np.eye(3), 0.1, 0.1, 0.02)
    hot = ec.HotPath(st, checks, np.eye(3), 0.1, 0.1, 0.02)
    with pytest.raises(ValueError, match="rows"):
        hot.run(np.zeros((2, 5)), 0, None, ec.AzimuthRun(), np.zeros(3), False)
    with pytest.raises(ValueError, match="start"):
        hot.run(np.zeros((2, 11)), 3, None, ec.AzimuthRun(), np.zeros(3), False)
    with pytest.raises(ValueError, match="phases"):
        hot.run_ground(np.zeros((2, 11)), 0, None, None, None, (0,) * 8, np.zeros(3), False)
    # not a sample: unread (its row is built in Python), the state untouched
    assert hot.flight(object(), None, ec.AzimuthRun(), np.zeros(3)) == ec.HOT_UNREAD
    assert st.acc_n == 0 and st.last_time_fc_s is None


# --- the 50 Hz magnetometer checks' core twins -----------------------------------------------------

@pytest.mark.skipif(not ec.MAG_HARD_IRON_RESIDUAL_AVAILABLE, reason="compiled core without the twin")
def test_mag_hard_iron_residual_core_twin_equals_the_reference():
    """Pipeline._mag_hard_iron_residual on a state held in the core (the core's twin) against the
    reference (the Python formula, on the reference's state) on random attitudes, fields and hard-iron
    covariances, to 1e-12 relative; both None without a P or a horizontal field."""
    from types import SimpleNamespace
    from estimators.mag_disturbance import MagDisturbanceState
    from estimators.polar_heading import PolarHeadingParams
    from estimators.rotations import quat_from_euler
    rng = np.random.default_rng(5)
    ph = PolarHeadingParams()
    n = 0
    for k in range(300):
        A = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-4, -1)
        P = A @ A.T + (np.eye(3) * 1e-9 if k % 3 else 0.0)
        st = MagDisturbanceState(P_hard_iron=P, hard_iron_gauss=rng.normal(size=3) * 0.05)
        q = quat_from_euler(*rng.uniform(-1.5, 1.5, 2), rng.uniform(-np.pi, np.pi))
        att = SimpleNamespace(q_P_from_body=q if k % 2 else tuple(q.tolist()))
        m = rng.normal(size=3) * 0.3
        ref = sp.Pipeline._mag_hard_iron_residual(SimpleNamespace(mag_dist=st, polar_hdg_params=ph), m, att)
        core = sp.Pipeline._mag_hard_iron_residual(
            SimpleNamespace(mag_dist=ec.HeldMagDisturbance(st), polar_hdg_params=ph), m, att)
        assert ref is not None and core is not None
        assert abs(core - ref) <= 1e-12 * abs(ref), (k, core, ref)
        n += 1
    assert n == 300
    ident = SimpleNamespace(q_P_from_body=np.array([1.0, 0.0, 0.0, 0.0]))
    for st in (MagDisturbanceState(), MagDisturbanceState(P_hard_iron=np.eye(3) * 1e-4)):
        for m in (np.array([0.0, 0.0, 0.5]), np.array([0.2, 0.0, 0.4])):
            ref = sp.Pipeline._mag_hard_iron_residual(SimpleNamespace(mag_dist=st, polar_hdg_params=ph), m, ident)
            core = sp.Pipeline._mag_hard_iron_residual(
                SimpleNamespace(mag_dist=ec.HeldMagDisturbance(st), polar_hdg_params=ph), m, ident)
            assert (ref is None) == (core is None), (st.P_hard_iron, m, ref, core)
            assert ref is None or abs(core - ref) <= 1e-12 * ref
    assert sp.Pipeline._mag_hard_iron_residual(SimpleNamespace(mag_dist=ec.HeldMagDisturbance(
        MagDisturbanceState(P_hard_iron=np.eye(3))), polar_hdg_params=ph), None, ident) is None
