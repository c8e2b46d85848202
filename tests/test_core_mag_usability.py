"""The magnetometer usability in the compiled core equals its Python reference (issue 19 item 2).

GIVEN the calls a Pipeline made into estimators/mag_usability (recorded at the Pipeline on a
simulated flight, sim.offline inclined_rail at 50 Hz, and on the replay of the real
/work/shared/data/arducopter-rtl-midflight.bin; arducopter-flight.tlog, whose magnetometer the dip
test rejects, was checked once, equal, and left out for its 100 s replay), and a synthetic
sequence that walks through every test of the module (a good sensor, a field norm 0.87 G against
0.5 G, a wrong axis mapping seen by the dip, a frozen sensor and a stuck axis while the body turns,
a full-scale reading, a sensor too slow, held repeats, no samples at all, a learnt hard iron, no
tilt, no gyro),
WHEN the reference (estimators.mag_usability) and the core (estimators.core, the state held in
C++) take the same calls,
THEN every verdict agrees (reason strings and flags identical, the window medians and the rate to
1e-9 relative), and so does the state after every call (times and flags identical, the running
sums to 1e-9 relative). A deep copy of a held state goes on as the unbroken run.
"""
from __future__ import annotations

import copy
import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from estimators import core  # noqa: E402
from parity_compare import differences  # noqa: E402
from estimators import mag_usability as ref  # noqa: E402
from estimators.mag_usability import MagUsabilityState, mag_usability_params_for_field  # noqa: E402
from test_mag_usability import FIELD_NED_GAUSS, body_field  # noqa: E402  (the model field and its body-axes helper)

DATA = Path("/work/shared/data")
P = mag_usability_params_for_field(FIELD_NED_GAUSS)
pytestmark = pytest.mark.skipif(not core.MAG_USABILITY_AVAILABLE,
                                reason=f"compiled core without mag_usability: {core.IMPORT_ERROR or 'old build'}")


def _same_verdict(a, b) -> bool:
    """Equal verdicts: flags and reason identical, the numbers to 1e-9 relative (tests/parity_compare.py)."""
    return not differences(a, b)


def _same_state(a: MagUsabilityState, b: MagUsabilityState) -> bool:
    return not differences(a, b)


def _replay(calls, params=P):
    """Each call through the reference and the core; every verdict and state compared."""
    sr, sc = MagUsabilityState(), MagUsabilityState()
    n_changed = 0
    reasons = set()
    for kind, args in calls:
        if kind == "step":
            sr, vr = ref.mag_usability_step(sr, *args[:1], *args[1:4], params, *args[4:])
            sc, vc = core.mag_usability_step(sc, *args[:1], *args[1:4], params, *args[4:])
        else:
            sr, vr = ref.mag_usability_stale(sr, args[0], params, args[1])
            sc, vc = core.mag_usability_stale(sc, args[0], params, args[1])
        assert _same_verdict(vr, vc), (kind, args, vr, vc)
        assert _same_state(sr, sc.to_state()), (kind, args)
        assert sc.usable == sr.usable and sc.reason == sr.reason
        if vr is not None:
            n_changed += vr.changed
            reasons.add(vr.reason.split(" ")[0].rstrip(":"))  # the test's first word
    return n_changed, reasons




def _synthetic_calls() -> list:
    """(kind, args) through every test: args = (t, m, roll, pitch, gyro, hard_iron) / (t, gyro)."""
    rng = np.random.default_rng(7)
    calls, t, dt = [], 0.0, 0.1
    w = np.array([0.0, 0.0, 0.3])

    def seg(duration_s, field, roll=0.1, pitch=-0.05, gyro=w, hi=None, repeat=1, rate_dt=dt):
        nonlocal t
        for _ in range(int(round(duration_s / rate_dt))):
            m = field(t) + rng.normal(0.0, 0.002, 3)
            for j in range(repeat):
                calls.append(("step", (t + j * rate_dt / repeat, m, roll, pitch, gyro, hi)))
            t += rate_dt

    good = lambda s: body_field(0.3 * s, 0.1, -0.05)  # noqa: E731
    seg(5.0, good)                                              # being checked, then usable
    seg(4.0, lambda s: good(s) * (0.87 / P.field_norm_gauss))   # field norm
    seg(4.0, good)
    seg(4.0, lambda s: good(s)[[1, 0, 2]] * np.array([1, 1, -1]))  # wrong axis mapping: dip
    seg(3.0, good)
    frozen = good(t)
    for _ in range(50):                                         # frozen while turning
        calls.append(("step", (t, frozen, 0.1, -0.05, w, None)))
        t += dt
    seg(3.0, good)
    for _ in range(50):                                         # one axis stuck, the others change
        m = good(t) + rng.normal(0.0, 0.002, 3)
        m[0] = 0.31
        calls.append(("step", (t, m, 0.1, -0.05, np.array([0.3, 0.0, 0.3]), None)))
        t += dt
    seg(3.0, good, hi=np.array([0.01, -0.02, 0.005]))           # a learnt hard iron taken off
    seg(3.0, good, roll=None, pitch=None)                       # no tilt: no dip test
    seg(3.0, good, roll=float("nan"))
    seg(3.0, good, gyro=None)                                   # motion unknown
    seg(3.0, good, gyro=np.zeros(2))                            # a malformed gyro: motion known, not summed
    seg(12.0, good, repeat=5, rate_dt=2.0)                      # 0.5 Hz with held repeats: too slow
    seg(3.0, good)
    for k in range(60):                                         # no samples at all
        calls.append(("stale", (t, w if k % 3 else None)))
        t += dt
    seg(4.0, good)
    return calls


def test_core_equals_reference_through_every_test():
    n_changed, reasons = _replay(_synthetic_calls())
    assert reasons == {"", "being", "field", "dip", "frozen", "saturated", "too", "no"}, reasons
    assert n_changed >= 8


def test_core_full_scale_equals_reference():
    p = mag_usability_params_for_field(FIELD_NED_GAUSS, full_scale_gauss=0.4)
    calls = [("step", (0.1 * k, np.array([0.41 if k > 30 else 0.2, 0.01 * k, 0.3]), 0.0, 0.0, None, None))
             for k in range(60)]
    _replay(calls, p)


def _recording(calls: list, params_seen: dict | None = None):
    """A backend whose mag_usability calls run the reference and are recorded, in order (their
    params in ``params_seen["usability"]``)."""
    from service import core_backend
    params_seen = {} if params_seen is None else params_seen
    step, stale = ref.mag_usability_step, ref.mag_usability_stale

    def rec_step(state, t, m, roll, pitch, params, gyro=None, hi=None):
        calls.append(("step", (t, np.array(m), roll, pitch, None if gyro is None else np.array(gyro),
                               None if hi is None else np.array(hi))))
        params_seen["usability"] = params
        return step(state, t, m, roll, pitch, params, gyro, hi)

    def rec_stale(state, t, params, gyro=None):
        calls.append(("stale", (t, None if gyro is None else np.array(gyro))))
        params_seen["usability"] = params
        return stale(state, t, params, gyro)

    return dataclasses.replace(core_backend.select(), mag_usability_step=rec_step, mag_usability_stale=rec_stale)


def _pipeline_calls(cfg, items, monkeypatch) -> tuple[list, object]:
    """Run a Pipeline (the reference usability) over ``items`` as the daemon feeds it (bench/sitl),
    recording its mag_usability calls."""
    from sitl import feed_pipeline
    from service.pipeline import Pipeline
    calls: list = []
    monkeypatch.setattr("service.pipeline.select_core", lambda: _recording(calls))
    p = Pipeline(cfg)
    for _ in feed_pipeline(p, items):
        pass
    return calls, p.mag_usability_params


def test_core_equals_reference_on_a_simulated_flight(monkeypatch):
    from sitl import pipeline_inputs, scenario_site
    from service.config import validate
    from sim.offline import simulate
    run = simulate(scenario="inclined_rail", seed=4, imu_grade="consumer", imu_rate_hz=50.0, duration_s=20.0,
                   overrides={"launcher": {"rest_s": 8.0}})
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    calls, params = _pipeline_calls(validate({**site, "mavlink": {"imu_rate_hz": 50.0}}), pipeline_inputs(run),
                                    monkeypatch)
    assert len(calls) > 900
    n_changed, reasons = _replay(calls, params)
    assert "" in reasons and n_changed >= 1


_RTL: dict = {}


def rtl_replay_calls(monkeypatch) -> dict:
    """The replay of arducopter-rtl-midflight.bin (service/replay.py, as ``azimuthd replay`` runs it),
    run once per session, recording the Pipeline's calls: "usability" -> (mag_usability calls, their
    params), "disturbance" -> (mag_disturbance_step calls (t, m, q), their params; for
    tests/test_core_mag_disturbance.py)."""
    if not _RTL:
        from types import SimpleNamespace

        from estimators import mag_disturbance as md
        from service.logreaders import open_log
        from service.replay import build_config, run_replay
        log = open_log(DATA / "arducopter-rtl-midflight.bin")
        cfg, _notes = build_config(SimpleNamespace(config=None, site=None, exclude_fc_yaw=False), log)
        usab, dist, params = [], [], {}
        step_d = md.mag_disturbance_step

        def rec_d(state, t, m, q, p):
            dist.append((t, np.array(m), np.array(q)))
            params["disturbance"] = p
            return step_d(state, t, m, q, p)

        monkeypatch.setattr("service.pipeline.select_core", lambda: dataclasses.replace(
            _recording(usab, params), mag_disturbance_step=rec_d))
        run_replay(log, cfg, None)
        _RTL.update(usability=(usab, params["usability"]), disturbance=(dist, params["disturbance"]))
    return _RTL


@pytest.mark.skipif(not (DATA / "arducopter-rtl-midflight.bin").is_file(), reason="real logs not present")
def test_core_equals_reference_on_a_real_log(monkeypatch):
    calls, params = rtl_replay_calls(monkeypatch)["usability"]
    assert len(calls) > 1000
    _replay(calls, params)


def test_a_deep_copy_goes_on_as_the_unbroken_run():
    calls = _synthetic_calls()
    cut = len(calls) // 2
    s = MagUsabilityState()
    out = []
    for i, (kind, args) in enumerate(calls):
        if i == cut:
            s = copy.deepcopy(s)
        if kind == "step":
            s, v = core.mag_usability_step(s, args[0], args[1], args[2], args[3], P, args[4], args[5])
        else:
            s, v = core.mag_usability_stale(s, args[0], P, args[1])
        out.append(v)
    s2, out2 = MagUsabilityState(), []
    for kind, args in calls:
        if kind == "step":
            s2, v = core.mag_usability_step(s2, args[0], args[1], args[2], args[3], P, args[4], args[5])
        else:
            s2, v = core.mag_usability_stale(s2, args[0], P, args[1])
        out2.append(v)
    assert all(_same_verdict(a, b) for a, b in zip(out, out2))
    assert _same_state(s.to_state(), s2.to_state())
