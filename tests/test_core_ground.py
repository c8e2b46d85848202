"""The ground (pre-launch) path in the compiled core (core/ground.hpp, core/hot_path.hpp ground_run,
service/hot_path.py) gives what the Python reference gives.

GIVEN the ground state's own step (method A's delay line into its levelling, method E's rest data, a
still block's end that passed or not) fed 12 s of 400 Hz rest data with magnetometer dropouts and
non-finite magnetometer samples, THEN the core's GroundState holds bit for bit what
azimuth_prelaunch_step and rest_accumulate give, through a take-back / take-in and a deep copy.

GIVEN a simulated launcher flight with 20 s on the launcher at 200 Hz, the FC armed (HEARTBEAT,
its EKF status, pressure with a pitot), a knock on the launcher (a refused take-off), a magnetometer
dropout, a non-finite sample and a repeated time on the ground, and a reader of ``Pipeline.azimuth``
on the ground, fed in batches of 1-40 rows as the daemon's batch path feeds it (and sample by sample
through ``step_imu`` as its message path does); and a daemon started in flight (its first seconds are
on the ground path until the evidence holds), THEN with the compiled core and its ground run every
NavSolution, event, counter, aiding record and the propagated solution after each batch equal the
Python reference's (AZIMUTHD_CORE=python, on_imu per sample) to 1e-9 relative (tests/parity_compare),
and the state at the end of the ground phase (method A's delay line and levelling, the rest data,
the phases, method C's attitude filter with its covariance) too; against the core's on_imu per sample
bit for bit; most ground samples never reached Python. Two deliberately wrong ground runs (the
accelerometer off by 1e-6 m/s^2, method A's delay line not stepped) fail the same comparison.

GIVEN a real log with a ground phase (../shared/data, skipped when absent) replayed as ``azimuthd
replay`` runs it, THEN the core with its ground run gives the reference's rows and events (1e-9) and
took most of the ground samples between filter steps."""
from __future__ import annotations

import copy
import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))
from sitl import pipeline_inputs, scenario_site  # noqa: E402
from parity_compare import differences  # noqa: E402
from pipeline_recording import fly, run_with_backend  # noqa: E402
from test_core_hot_path import feed_batches, python_with_core_fit  # noqa: E402

from estimators import core as ec  # noqa: E402
from estimators.azimuth import azimuth_prelaunch_step  # noqa: E402
from estimators.declination import RestState, rest_accumulate  # noqa: E402
from mavlink_io.samples import FcEkfStatus, FcHeartbeat, ImuSample  # noqa: E402
from service import core_backend  # noqa: E402
from service.config import validate  # noqa: E402
import service.pipeline as sp  # noqa: E402
from sim.offline import simulate  # noqa: E402

pytestmark = pytest.mark.skipif(not ec.GROUND_AVAILABLE, reason="compiled core without the ground path")
RATE_HZ = 200.0
REST_S = 20.0
DATA = ROOT.parent / "shared" / "data"


def _backends():
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    assert core.ground_state is ec.GroundState
    return python_with_core_fit(core), core, dataclasses.replace(core, hot_run=None)


def _site_cfg(run, launch=None) -> dict:
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    return validate({**site, "mavlink": {"imu_rate_hz": RATE_HZ}, "launch": {**site.get("launch", {}), **(launch or {})}})


# --- the ground state's own step -------------------------------------------------------------------

def _reference_ground(st, rest, cand, g, a, m, t, block_ended, block_passed):
    """service/pipeline.py _step_azimuth's pre-launch branch, the reference."""
    st = azimuth_prelaunch_step(st, g, a, t)
    if m is not None:
        cand = rest_accumulate(cand, g, a, m)
    if block_ended:
        if block_passed:
            rest = cand
        else:
            cand = rest = RestState()
    return st, rest, cand


def _held_azimuth(gs, st):
    """(the AzimuthState with the core's delay line and levelling, the GroundState again holding them)."""
    rows, lev = gs.take_azimuth()
    assert not gs.a_held
    pending = tuple((t, r[1:4].copy(), r[4:7].copy()) for t, r in zip(rows[:, 0].tolist(), rows))
    out = dataclasses.replace(st, pending=pending, levelling=ec.levelling_unpack(lev))
    gs.set_azimuth(rows, lev, st.params.prelaunch_buffer_s)
    return out


def test_ground_state_equals_the_reference_bit_for_bit():
    run = simulate(scenario="inclined_rail", seed=5, imu_grade="consumer", imu_rate_hz=400.0, duration_s=12.0,
                   overrides={"launcher": {"rest_s": 30.0}})
    p = sp.Pipeline(_site_cfg(run))
    st = p.azimuth
    assert st.phase == "prelaunch" and st.params.prelaunch_buffer_s > 1.0
    rest, cand = RestState(), RestState()
    gs = ec.GroundState()
    gs.set_azimuth(np.zeros((0, 7)), ec.levelling_pack(st.levelling), st.params.prelaunch_buffer_s)
    rng = np.random.default_rng(1)
    checked = 0
    for k, (t, g, a, m) in enumerate(zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss)):
        m = None if 800 <= k < 1000 else (np.array([np.nan, 0.2, 0.4]) if k % 97 == 0 else m)  # dropout, bad mag
        ended = k % 800 == 799
        passed = ended and rng.random() < 0.6
        st, rest, cand = _reference_ground(st, rest, cand, g, a, m, t, ended, passed)
        gs.step(g, a, m, t, ended, passed)
        if k % 1111 == 0 or k == len(run.time_s) - 1:
            got = _held_azimuth(gs, st)
            assert len(got.pending) == len(st.pending) > 0
            assert not differences(st, got, "azimuth", 0.0)
            assert not differences((rest, cand), (gs.rest, gs.rest_candidate), "rest", 0.0)
            checked += 1
        if k == 3000:   # a deep copy goes on as the original
            gs = copy.deepcopy(gs)
            assert gs.a_held
    assert checked >= 5 and st.levelling.n > 3000 and rest.n > 0 and cand.n > 0


def test_ground_state_says_what_is_wrong():
    gs = ec.GroundState()
    with pytest.raises(ValueError, match="not held"):
        gs.step(np.zeros(3), np.zeros(3), None, 0.0, False, False)
    with pytest.raises(ValueError, match="k, 7"):
        gs.set_azimuth(np.zeros((2, 6)), np.zeros(38), 1.0)
    with pytest.raises(ValueError, match="38"):
        gs.set_azimuth(np.zeros((0, 7)), np.zeros(12), 1.0)
    with pytest.raises(ValueError, match="not held"):
        gs.take_azimuth()


# --- the Pipeline on the ground --------------------------------------------------------------------

GROUND_END_S = REST_S - 1.0
"""The ground-phase state is compared here (the launch is at REST_S)."""


def _faulted_ground(items: list) -> list:
    """On the launcher: a knock (16 samples of 40 m/s^2 backward at 12 s: a refused take-off), a
    magnetometer dropout (13-13.5 s), a non-finite gyro at 14 s and a repeated time at 15 s."""
    out, done = [], set()
    for it in items:
        if type(it) is ImuSample:
            t = it.time_fc_s
            if 12.0 <= t < 12.08:
                done.add("knock")
                out.append(dataclasses.replace(it, accel_m_s2=it.accel_m_s2 + np.array([-40.0, 0.0, 0.0])))
                continue
            if 13.0 <= t < 13.5:
                done.add("dropout")
                out.append(dataclasses.replace(it, mag_gauss=None))
                continue
            if t >= 14.0 and "nan" not in done:
                done.add("nan")
                out.append(dataclasses.replace(it, gyro_rad_s=np.array([0.0, np.nan, 0.0])))
                continue
            if t >= 15.0 and "dup" not in done:
                done.add("dup")
                out += [it, dataclasses.replace(it, gyro_rad_s=it.gyro_rad_s * 1.01)]
                continue
        out.append(it)
    assert done == {"knock", "dropout", "nan", "dup"}
    return out


def _with_fc(items: list, t0: float, t1: float, flying_from_s: float) -> list:
    """The FC's HEARTBEAT (armed; ArduPlane's STANDBY on the ground, ACTIVE from ``flying_from_s``) at
    1 Hz and its EKF status at 2 Hz, merged in time order (before an IMU sample of the same time)."""
    extra = [(t, FcHeartbeat(t, 1, 1, "ardupilot", 1, 129, 0, 4 if t >= flying_from_s else 3, True))
             for t in np.arange(t0, t1, 1.0).tolist()]
    extra += [(t, FcEkfStatus(t, True, True, 0, "EKF_STATUS_REPORT")) for t in np.arange(t0, t1, 0.5).tolist()]
    keyed = [(it.time_rx_s, 1, k, it) for k, it in enumerate(items)] + [(t, 0, 0, it) for t, it in extra]
    keyed.sort(key=lambda x: x[:3])
    return [x[3] for x in keyed]


def launcher_on_ground():
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ, duration_s=30.0,
                   overrides={"launcher": {"rest_s": REST_S}})
    items = _with_fc(_faulted_ground(pipeline_inputs(run)), 0.0, 30.0, REST_S + 2.0)
    return items, _site_cfg(run, {"vehicle": "launcher"})


def started_in_flight():
    """The feed begins 60 s after the launch (the daemon restarted in flight), the FC armed and flying."""
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ, duration_s=80.0,
                   overrides={"launcher": {"rest_s": 5.0}})
    items = [it for it in pipeline_inputs(run) if it.time_rx_s >= 65.0]
    return _with_fc(items, 65.0, 80.0, 0.0), _site_cfg(run, {"vehicle": "launcher"})


SCENARIOS = {"launcher_on_ground": launcher_on_ground, "started_in_flight": started_in_flight}
_INPUTS: dict = {}
_RUNS: dict = {}


def _inputs(name):
    if name not in _INPUTS:
        _INPUTS[name] = SCENARIOS[name]()
    return _INPUTS[name]


def _ground_state(p) -> dict:
    """What the ground path leaves: A's state (delay line and levelling), the rest data, the phases,
    C's attitude filter (covariance included), the counters."""
    st = p.polar_att
    return {"azimuth": p.azimuth, "rest": p.rest, "rest_candidate": p._rest_candidate,
            "phase": p.phase.to_state() if hasattr(p.phase, "to_state") else p.phase,
            "polar_att": st.to_state() if hasattr(st, "to_state") else st,
            "counters": (p.counters.imu_samples, p.counters.imu_rejected, dict(p.counters.reasons))}


def _run(scenario: str, kind: str, name: str, backend, until_s: float | None = None) -> dict:
    key = (scenario, kind, name, until_s)
    if key not in _RUNS:
        items, cfg = _inputs(scenario)
        if until_s is not None:
            items = [it for it in items if it.time_rx_s < until_s]
        mp = pytest.MonkeyPatch()
        try:
            mp.setattr(sp, "select_core", lambda: backend)
            p = sp.Pipeline(cfg)
            if kind == "step_imu":
                got = _feed_step_imu(p, items)
            else:
                got = feed_batches(p, _reading_azimuth(p, items))
        finally:
            mp.undo()
        got["ground"] = _ground_state(p) if until_s is not None else None
        _RUNS[key] = got
    return _RUNS[key]


def _reading_azimuth(p, items):
    """The items, with ``Pipeline.azimuth`` read (a reader such as a status query) at 9.3 s and 16.1 s:
    the core gives A's delay line back and takes it in again at the next ground sample. The read is
    an FcEkfStatus of source "reader", which ``_ekf_or_reader`` takes for one."""
    out = []
    marks = [9.3, 16.1]
    for it in items:
        if marks and type(it) is FcEkfStatus and it.time_rx_s >= marks[0]:
            marks.pop(0)
            out.append(FcEkfStatus(it.time_rx_s, True, True, 0, "reader"))
        out.append(it)
    return out


def _feed_step_imu(p, items) -> dict:
    """As the daemon's message path: each IMU sample through ``step_imu``, the propagated snapshot
    taken between filter steps."""
    got = {"solutions": [], "events": [], "after_batch": []}
    handled = [0]
    on_imu = p.on_imu

    def counted(s, *a):
        handled[0] += 1
        return on_imu(s, *a)
    p.on_imu = counted
    others = {"PressureSample": p.on_pressure, "FcAttitude": p.on_fc_attitude, "FcHeartbeat": p.on_fc_heartbeat,
              "FcEkfStatus": p.on_fc_ekf_status}
    for it in items:
        if type(it) is ImuSample:
            sol = p.step_imu(it)
            if sol is not None:
                got["solutions"].append(sol)
            got["events"] += p.drain_events()
            got["after_batch"].append((p.propagated_solution(), p.counters.imu_samples, p.last_time_fc_s))
        else:
            others[type(it).__name__](it)
    got["python_handled"] = handled[0]
    return got


_ORIG_EKF = sp.Pipeline.on_fc_ekf_status


def _ekf_or_reader(self, st):
    if st.source == "reader":
        self.azimuth   # noqa: B018 - the read is the point
        return
    _ORIG_EKF(self, st)


@pytest.fixture(autouse=True)
def _readers(monkeypatch):
    monkeypatch.setattr(sp.Pipeline, "on_fc_ekf_status", _ekf_or_reader)


def _compare(a: dict, b: dict, rtol: float = 1e-9) -> list:
    bad = differences(a["solutions"], b["solutions"], "solutions", rtol)
    bad += differences(_no_innovations(a["after_batch"]), _no_innovations(b["after_batch"]), "after_batch", rtol)
    if a["events"] != b["events"]:
        bad.append(("events", f"{len(a['events'])} vs {len(b['events'])}: "
                    f"{[e for e in a['events'] if e not in b['events']][:2]} / "
                    f"{[e for e in b['events'] if e not in a['events']][:2]}"))
    if a["ground"] is not None or b["ground"] is not None:
        bad += differences(a["ground"], b["ground"], "ground", rtol)
    return bad


def _no_innovations(after_batch):
    """The aiding records' innovation fields zeroed (differences of near-equal headings: see
    tests/test_core_hot_path.py INNOVATIONS); the ground has no A, B or C heading to differ anyway."""
    from test_core_hot_path import INNOVATIONS
    out = []
    for x in after_batch:
        if len(x) > 2 and isinstance(x[2], dict):
            x = (*x[:2], {k: r._replace(**{f: 0.0 for f in INNOVATIONS}) for k, r in x[2].items()}, *x[3:])
        out.append(x)
    return out


def _ground_samples(items, until_s) -> int:
    return sum(type(it) is ImuSample and it.time_fc_s < until_s for it in items)


@pytest.mark.parametrize("until_s", [GROUND_END_S, None], ids=["ground_state", "whole_flight"])
def test_ground_path_equals_python_reference(until_s):
    python, core, no_hot = _backends()
    ref = _run("launcher_on_ground", "batches", "python", python, until_s)
    hot = _run("launcher_on_ground", "batches", "core", core, until_s)
    each = _run("launcher_on_ground", "batches", "core_on_imu", no_hot, until_s)
    ev = ref["events"]
    # the ground did what the test is about: levelled, refused the knock, took off (the whole flight)
    assert any(k == "levelled" for k, _ in ev) and any(k == "takeoff_refused" for k, _ in ev), ev
    if until_s is None:
        assert ("phase", "launch") in ev
    else:
        g = ref["ground"]
        assert g["phase"].phase == "pre-launch" and len(g["azimuth"].pending) > 100 and g["rest"].n > 0
        assert g["azimuth"].levelling.n > 1000 and g["counters"][1] == 2
    bad = _compare(ref, hot)
    assert not bad, bad[:5]
    bad = _compare(each, hot, rtol=0.0)
    assert not bad, bad[:5]
    if until_s is not None:
        n_ground = _ground_samples(_inputs("launcher_on_ground")[0], until_s)
        assert each["python_handled"] == n_ground
        # Python: the 50 Hz filter steps (1 in 4 at 200 Hz), the events, the faults; the core the rest
        assert hot["python_handled"] < 0.3 * n_ground, (hot["python_handled"], n_ground)


def test_message_path_on_the_ground_equals_python_reference():
    python, core, _ = _backends()
    ref = _run("launcher_on_ground", "step_imu", "python", python, GROUND_END_S)
    hot = _run("launcher_on_ground", "step_imu", "core", core, GROUND_END_S)
    bad = _compare(ref, hot)
    assert not bad, bad[:5]
    n_ground = _ground_samples(_inputs("launcher_on_ground")[0], GROUND_END_S)
    assert hot["python_handled"] < 0.3 * n_ground, (hot["python_handled"], n_ground)


def test_started_in_flight_equals_python_reference():
    python, core, _ = _backends()
    ref = _run("started_in_flight", "batches", "python", python)
    hot = _run("started_in_flight", "batches", "core", core)
    kinds = [k for k, _ in ref["events"]]
    assert "started_in_flight" in kinds and "levelled" not in kinds, ref["events"]
    bad = _compare(ref, hot)
    assert not bad, bad[:5]


def _mutant(run, fault: str):
    def wrong(*a):
        a = list(a)
        if len(a) > 12 and a[12] is not None:   # a ground run
            if fault == "accel":
                a[4] = a[4].copy()
                a[4][:, 5] += 1e-6
            elif fault == "no_delay_line":
                a[14] = None
        return run(*a)
    return wrong


@pytest.mark.parametrize("fault", ["accel", "no_delay_line"])
def test_a_wrong_ground_run_fails_the_comparison(fault):
    python, core, _ = _backends()
    ref = _run("launcher_on_ground", "batches", "python", python, None)
    wrong = _run("launcher_on_ground", "batches", "mutant_" + fault,
                 dataclasses.replace(core, hot_run=_mutant(core.hot_run, fault)), None)
    assert _compare(ref, wrong)


# --- a real log ------------------------------------------------------------------------------------

REAL_LOG = "px4-bench-sample.ulg"


def test_real_log_ground_path_equals_the_reference():
    """The real log replayed with the core's ground run against the reference (rows, events, 1e-9)."""
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    took = {"ground": 0, "flight": 0}

    def counting(*a):
        out = core.hot_run(*a)
        took["ground" if len(a) > 12 and a[12] is not None else "flight"] += out[3]
        return out
    fly_one = lambda name: fly(name, {}, {}, DATA, no_site=(REAL_LOG,))   # noqa: E731
    hot, p_hot = run_with_backend(fly_one, REAL_LOG, dataclasses.replace(core, hot_run=counting))
    ref, _ = run_with_backend(fly_one, REAL_LOG, core_backend.select({"AZIMUTHD_CORE": "python"}))
    assert hot["imu_samples"] == ref["imu_samples"] > 1000
    assert hot["events"] == ref["events"]
    bad = differences(ref, hot, REAL_LOG, 1e-9)
    assert not bad, bad[:5]
    ground_rows = sum(ph == "pre-launch" for ph in hot["phase"])   # the filter steps on the ground
    print(f"{REAL_LOG}: the ground run took {took['ground']} samples, the flight run {took['flight']}, "
          f"of {hot['imu_samples']} ({ground_rows} filter steps on the ground)")
    assert ground_rows > 100 and took["ground"] > 2 * ground_rows, (took, ground_rows)
