"""The message path's core takes the samples of a busy solver (service/hot_path.py _submit_blocked,
core/hot_path.hpp AzimuthRun.submit_blocked; issue 19 item 3).

While method A's solver works on a snapshot (the daemon's worker process), the reference's submit on
each sample with a solve due is refused and changes nothing (BackgroundSolver.submit returns False):
such a sample is quiet. Before, the core stopped at each of them and on_imu took every sample of a
solve's duration.

GIVEN a solver that solves as the inline one but holds each result for 1.5 s of FC time, busy (its
submit refused) until then, ready after (``DelayedSolver``: a worker slower than A's re-solve period,
0.5-1 s, as on a busy machine; its clock the FC time of the sample being fed, the one instant both
paths see), and a simulated launcher flight at 400 Hz (20 s) with the bad samples of
tests/test_core_hot_path.py, fed sample by sample through Pipeline.step_imu (the daemon's message
path) and through the core's on_imu,
THEN every solution, event, propagated solution, A output, aiding record and counter, and A's state
at the end, are equal bit for bit; on_imu takes under 0.2 of the samples the solver is busy on (the
filter steps are 1 in 8; before: all of them); a hot path that takes a submit-due sample while the
solver is free fails the comparison. A real log (px4-quad-no-gnss.ulg, A run in flight with
launch.case aligned) replayed through step_imu against on_imu with the same solver: the rows equal to
1e-9 (tests/parity_compare), the events identical, A's state bit for bit, and on_imu took under 0.35
of the samples the solver was busy on (the filter steps are ~0.23 of them there).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from parity_compare import differences  # noqa: E402
from pipeline_recording import NO_SITE_GIVEN, REPLAY_KEYS  # noqa: E402
from test_core_hot_path import _compare, _feed_step, faulted_flight  # noqa: E402

from estimators import core as ec  # noqa: E402
from mavlink_io.samples import ImuSample  # noqa: E402
from service import core_backend  # noqa: E402
import service.hot_path as hp  # noqa: E402
import service.pipeline as sp  # noqa: E402
from service.solver import InlineSolver  # noqa: E402

pytestmark = pytest.mark.skipif(not hasattr(ec, "HotPath"), reason="compiled core without the bound hot path")
DATA = ROOT.parent / "shared" / "data"
LOG = "px4-quad-no-gnss.ulg"
SOLVE_S = 1.5


class DelayedSolver(InlineSolver):
    """Solves at submit as InlineSolver does, and holds the result ``solve_s`` of FC time: ``busy`` (a
    submit refused, as BackgroundSolver's while its worker solves) until then, ``ready`` after. ``now``:
    the FC time of the sample being fed, set by the feeder before each."""
    background = True

    def __init__(self, solve_s: float = SOLVE_S):
        super().__init__()
        self.solve_s, self.now, self._due = solve_s, -math.inf, math.inf
        self.submits = self.refused = 0

    def busy(self) -> bool:
        return self._result is not None and self.now < self._due

    def submit(self, state, time_s: float, *kernels) -> bool:
        if self.busy():
            self.refused += 1
            return False
        self.submits += 1
        self._due = self.now + self.solve_s
        return super().submit(state, time_s, *kernels)

    def poll(self):
        return super().poll() if self.ready() else None

    def ready(self) -> bool:
        return self._result is not None and self.now >= self._due


def _pipeline(cfg, backend, solve_s: float):
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(sp, "select_core", lambda: backend)
        return sp.Pipeline(cfg, solver=DelayedSolver(solve_s))
    finally:
        mp.undo()


def _stepped(items, cfg, on_imu_only: bool, solve_s: float = SOLVE_S) -> dict:
    """The flight sample by sample (step_imu, or the core's on_imu), the solver's clock set before each
    sample; counts the samples the solver is busy on and the on_imu calls among them."""
    p = _pipeline(cfg, core_backend.select({"AZIMUTHD_CORE": "core"}), solve_s)
    sv = p.solver
    count = {"busy": 0, "busy_on_imu": 0}
    on_imu = p.on_imu

    def counted(s, *a):
        count["busy_on_imu"] += sv.busy()
        return on_imu(s, *a)
    p.on_imu = counted

    def step(p, s):
        sv.now = s.time_fc_s
        count["busy"] += sv.busy()
        return p.on_imu(s) if on_imu_only else p.step_imu(s)
    got = _feed_step(p, items, step)
    got.update(count, submits=sv.submits, refused=sv.refused)
    return got


@pytest.fixture(scope="module")
def flight():
    return faulted_flight(20.0, rate_hz=400.0)


@pytest.fixture(scope="module")
def each(flight):
    """The core's on_imu for every sample: with the slow solver, and with a fast one (0.3 s: free again
    when the next submit comes due)."""
    return {solve_s: _stepped(*flight, on_imu_only=True, solve_s=solve_s) for solve_s in (SOLVE_S, 0.3)}


def test_busy_solver_samples_taken_by_the_core_equal_on_imu(flight, each):
    items, cfg = flight
    ref = each[SOLVE_S]
    hot = _stepped(items, cfg, on_imu_only=False)
    # A re-solved in flight; its solver was busy on many samples and refused submits on them
    assert ref["submits"] > 5 and ref["refused"] > 1000 and ref["busy"] > 2000, (ref["submits"], ref["refused"])
    assert (hot["submits"], hot["busy"]) == (ref["submits"], ref["busy"])   # refused: the core asks no submit
    bad = _compare(ref, hot, rtol=0.0, innovations=True)
    assert not bad, bad[:5]
    assert not differences(ref["pipeline"].azimuth, hot["pipeline"].azimuth, "azimuth", 0.0)
    # the core took the busy samples between filter steps (before: on_imu took them all)
    assert hot["busy_on_imu"] < 0.2 * hot["busy"], (hot["busy_on_imu"], hot["busy"])
    assert ref["busy_on_imu"] == ref["busy"]


def test_a_submit_due_while_the_solver_is_free_stays_with_on_imu(flight, each):
    """The fast solver: the submits come due on quiet samples while it is free; the core leaves each to
    on_imu (equal), and a hot path that takes them as if the solver were busy fails the comparison."""
    ref = each[0.3]
    assert ref["submits"] > 10 and ref["busy"] > 1000, (ref["submits"], ref["busy"])
    hot = _stepped(*flight, on_imu_only=False, solve_s=0.3)
    assert hot["submits"] == ref["submits"]
    assert not _compare(ref, hot, rtol=0.0, innovations=True)
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(hp, "_submit_blocked", lambda p, run: setattr(run, "submit_blocked", True))
        wrong = _stepped(*flight, on_imu_only=False, solve_s=0.3)
    finally:
        mp.undo()
    assert wrong["submits"] < ref["submits"]
    assert _compare(ref, wrong, rtol=0.0, innovations=True)


class _Stepped(sp.Pipeline):
    """A Pipeline that takes a replay's IMU batches sample by sample through step_imu (``ON_IMU``: its
    on_imu), with a DelayedSolver whose clock is the sample's FC time."""
    ON_IMU = False
    made: list = []

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.solver = DelayedSolver()
        self.busy = self.busy_on_imu = 0   # samples the solver is busy on, on_imu calls among them
        _Stepped.made.append(self)

    def on_imu(self, s, verdict=None):
        self.busy_on_imu += self.solver.busy()
        return super().on_imu(s, verdict)

    def imu_batch_steps(self, batch, samples=None):
        step = self.on_imu if self.ON_IMU else self.step_imu
        for i, s in enumerate(samples if samples is not None else batch.samples()):
            self.solver.now = s.time_fc_s
            self.busy += self.solver.busy()
            yield i, step(s)


def _replay(path: Path, cfg_path: Path) -> dict:
    """The log replayed as ``azimuthd replay --config cfg_path --site 47.37,8.54`` runs it."""
    from types import SimpleNamespace

    from service.logreaders import open_log
    from service.replay import build_config, run_replay
    log = open_log(path)
    cfg, _ = build_config(SimpleNamespace(config=str(cfg_path), site=NO_SITE_GIVEN, exclude_fc_yaw=False), log)
    res = run_replay(log, cfg, None)
    return {k: getattr(res, k) for k in REPLAY_KEYS}


def test_real_log_through_step_imu_equals_on_imu_with_a_busy_solver(monkeypatch, tmp_path):
    """px4-quad-no-gnss.ulg (a quadcopter's 86 s in the air) with launch.case aligned, so that method A
    runs in flight and re-solves (the default, inclined, does not run on a multicopter)."""
    path = DATA / LOG
    if not path.is_file():
        pytest.skip(f"{path} not present (the shared real logs)")
    cfg_path = tmp_path / "aligned.toml"
    cfg_path.write_text('[launch]\ncase = "aligned"\n')
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    monkeypatch.setattr(sp, "select_core", lambda: core)
    got = {}
    for on_imu_only in (True, False):
        monkeypatch.setattr(sp, "Pipeline", type("Run", (_Stepped,), {"ON_IMU": on_imu_only}))
        got[on_imu_only] = _replay(path, cfg_path), _Stepped.made[-1]
    (each, p_each), (hot, p_hot) = got[True], got[False]
    assert hot["imu_samples"] == each["imu_samples"] > 10000
    assert hot["events"] == each["events"]
    assert any(e[1] == "azimuth" and "withheld" in e[2] for e in each["events"]), each["events"]
    bad = differences(each, hot, LOG, 1e-9)
    assert not bad, bad[:5]
    sv_each, sv_hot = p_each.solver, p_hot.solver
    assert sv_hot.submits == sv_each.submits > 20 and sv_each.refused > 1000, (sv_each.submits, sv_each.refused)
    assert not differences(p_each.azimuth, p_hot.azimuth, "azimuth", 0.0)
    # the core took the busy samples between filter steps (~219 Hz, filter steps 50 Hz; before: on_imu took all)
    assert p_hot.busy == p_each.busy_on_imu == p_each.busy > 5000, (p_hot.busy, p_each.busy)
    assert p_hot.busy_on_imu < 0.35 * p_hot.busy, (p_hot.busy_on_imu, p_hot.busy)
