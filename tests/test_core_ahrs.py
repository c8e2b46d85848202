"""Method B (the synthetic AHRS, variant b2) in the compiled core equals its Python reference
(issue 19 item 2), on the events the daemon's Pipeline feeds B:

- a simulated GNSS-denied flight (sim.offline runway_gnss_denied, shortened: GNSS lost at 35 s, 65 s
  at 50 Hz): trusted FC alignment, KF1 learning, the loss (revert), air-data fusion after it;
- a real log from ../shared/data (ArduCopter RTL DataFlash, started mid-flight: pressure, the FC's
  attitude and flight state), read by the log reader and replayed through the Pipeline (also
  checked once, not in the suite for its time: px4-vtol-airspeed-small.ulg, equal).

GIVEN the events a Pipeline handed B (recorded at Pipeline._step_ahrs, with the FC-clock restarts
it reported and the take-off), WHEN the reference (estimators.synthetic_ahrs) and the core (estimators.core, the
state held in C++) step through them, THEN every output agrees (strings, flags and counters
identical; numbers to 1e-9 relative), and so does the whole state at the end, KF2's and KF1's
covariances included. Relative means: per scalar |a - b| <= 1e-9 max(|a|, |b|); per vector
(quaternions, biases, KF1's x) in the max norm of the vector; per covariance element against
sqrt(P_ii P_jj) (the core's matrix products round differently from numpy's BLAS: elements that are
0 in exact arithmetic differ by ~1e-21 there, which no relative measure of the element can take).
Also: a deep copy of a held state continues as the unbroken run, an event B refuses leaves the held
state unchanged (ValueError, as the reference), and the Pipeline runs B in the core."""
from __future__ import annotations

import copy
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import feed_pipeline, pipeline_inputs, scenario_site  # noqa: E402

from estimators import core  # noqa: E402
from parity_compare import differences  # noqa: E402
from estimators import synthetic_ahrs as ref  # noqa: E402
from estimators.synthetic_ahrs import FcAttitudeEvent, ImuEvent, SyntheticAhrsParams  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")

pytestmark = pytest.mark.skipif(not core.AVAILABLE, reason=f"compiled core not built: {core.IMPORT_ERROR}")


# --- what the Pipeline feeds B ------------------------------------------------------------------

def _record(cfg, items) -> dict:
    """Run a Pipeline (B in the reference, the rest as selected) over ``items``, recording every call
    it made into B, in order, with what the reference returned: ("step", event, params, output flag,
    output or "refused: <reason>") and ("unseen", seconds, params, False, None). Returns the calls,
    B's state before and after, and the Pipeline's solutions and events."""
    calls: list = []
    p = Pipeline(cfg)
    start = p.ahrs
    step, unseen = ref.synthetic_ahrs_step, ref.synthetic_ahrs_unseen

    def rec_step(state, event, params, output=True):
        try:
            state, out = step(state, event, params, output)
        except ValueError as exc:
            calls.append(("step", event, params, output, f"refused: {exc}"))
            raise
        calls.append(("step", event, params, output, out))
        return state, out

    def rec_unseen(state, unseen_s, params):
        calls.append(("unseen", unseen_s, params, False, None))
        return unseen(state, unseen_s, params)

    def rec_takeoff(state, params):
        calls.append(("takeoff", None, params, False, None))
        return ref.synthetic_ahrs_takeoff(state, params)

    p.core = dataclasses.replace(p.core, synthetic_ahrs_step=rec_step, synthetic_ahrs_unseen=rec_unseen,
                                 synthetic_ahrs_takeoff=rec_takeoff)
    events: list = []
    sols = list(feed_pipeline(p, items, events))
    return {"calls": calls, "start": start, "end": p.ahrs, "pipeline": p, "solutions": sols, "events": events,
            "cfg": cfg, "items": items}


def _sim_flight():
    from sim.offline import simulate
    run = simulate(scenario="runway_gnss_denied", seed=2, imu_grade="consumer", imu_rate_hz=50.0, duration_s=65.0,
                   overrides={"launcher": {"rest_s": 10.0}, "gnss": {"lost_at_s": 35.0}})
    site = scenario_site("runway_gnss_denied")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    # launch case "inclined" on a runway: method A stays off (its solver would cost ~60 s of this
    # test's CPU and feeds B nothing)
    site["launch"] = {**site.get("launch", {}), "case": "inclined"}
    return validate({**site, "mavlink": {"imu_rate_hz": 50.0}}), pipeline_inputs(run)


def _log_flight(name):
    from service.logreaders import open_log
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"{path} not present (the shared real logs)")
    log = open_log(path)
    items = list(log.items())
    cfg = validate({"site": {"lat_deg": 47.4, "lon_deg": 8.5, "alt_m": 500.0, "decimal_year": 2026.0}})
    return cfg, items


_CACHE: dict = {}


@pytest.fixture(scope="module", params=("sim", "arducopter-rtl-midflight.bin"))
def recorded(request):
    if request.param not in _CACHE:
        cfg, items = _sim_flight() if request.param == "sim" else _log_flight(request.param)
        _CACHE[request.param] = _record(cfg, items)
    return request.param, _CACHE[request.param]


# --- comparison -----------------------------------------------------------------------------------

def _differs(a, b, path: str, bad: list) -> None:
    """Append (path, why) for every leaf of a and b (records, tuples, arrays, numbers) that is not
    equal as the module docstring says (tests/parity_compare.py, shared by the core's parity tests;
    numpy scalars count as the Python ones: the reference holds some flags as numpy.bool_)."""
    bad.extend(differences(a, b, path))


def _run(calls, start, impl=core):
    """Step ``impl`` through the recorded calls: (final state, [outputs or "refused: <reason>"])."""
    st, outs = start, []
    for kind, arg, params, output, _ in calls:
        if kind == "unseen":
            st = impl.synthetic_ahrs_unseen(st, arg, params)
            continue
        if kind == "takeoff":
            st = impl.synthetic_ahrs_takeoff(st, params)
            continue
        try:
            st, out = impl.synthetic_ahrs_step(st, arg, params, output)
        except ValueError as exc:
            out = f"refused: {exc}"
        outs.append(out)
    return st, outs


def test_b_core_equals_reference_on_what_the_pipeline_feeds(recorded):
    name, rec = recorded
    calls = rec["calls"]
    out_ref = [c[4] for c in calls if c[0] == "step"]
    st_core, out_core = _run(calls, rec["start"])
    assert isinstance(st_core, core.HeldSyntheticAhrs)
    n_imu = sum(1 for c in calls if isinstance(c[1], ImuEvent))
    assert n_imu > 300 and sum(1 for c in calls if isinstance(c[1], FcAttitudeEvent)) > 300
    bad: list = []
    for k, (a, b) in enumerate(zip(out_ref, out_core)):
        _differs(a, b, f"{name} event {k}", bad)
    _differs(rec["end"], st_core.to_state(), f"{name} state", bad)
    assert len(out_ref) == len(out_core) and not bad, bad[:5]
    # the flight exercised what B does (not a run that stayed in one branch)
    last = next(o for o in reversed(out_ref) if o is not None and not isinstance(o, str))
    assert last.valid and last.ref_fused > 0 and last.mag_fused > 0
    if name == "sim":   # GNSS lost at 35 s: trust lost, the air data fused after it, KF1 learnt before
        assert sum(1 for c in calls if c[0] == "takeoff") == 1     # the launch at 10 s (synthetic_ahrs_takeoff)
        assert not last.reference_trusted and last.air_fused > 0 and rec["end"].kf1_learn.n_updates > 10


def test_b_deep_copy_of_held_state_continues_as_the_unbroken_run(recorded):
    name, rec = recorded
    calls = rec["calls"]
    split = int(len(calls) * 0.6)
    whole, _ = _run(calls, rec["start"])
    first, _ = _run(calls[:split], rec["start"])
    second, _ = _run(calls[split:], copy.deepcopy(first))
    bad: list = []
    _differs(whole.to_state(), second.to_state(), f"{name} split", bad)
    assert not bad, bad[:5]


def test_b_refused_event_leaves_the_held_state_unchanged():
    # GIVEN a trusted FC, one IMU sample and the FC's first attitude at pitch 90 deg (a vertical
    # launcher: KF2 starts there and reports it; test_ahrs_gimbal_lock),
    # WHEN the FC's next attitude is fused while B is still at 90 deg (the update's Jacobian T is
    # singular: the reference refuses the event with a ValueError and keeps its state), THEN the
    # core refuses it with the same message and holds the state from before the event; the next IMU
    # sample (the vehicle turns off 90 deg) and FC attitude are then taken in both alike
    params = SyntheticAhrsParams(field_nav_gauss=(0.2, 0.0, 0.4))
    st_ref = st_core = ref.synthetic_ahrs_init(params)
    bad: list = []
    for ev in (ref.FcStatusEvent(0.0, system_status=4, attitude_ok=True, horiz_pos_ok=True),
               ImuEvent(0.0, np.zeros(3), np.array([0.2, 0.0, 0.4])),
               FcAttitudeEvent(0.0, np.array([0.0, math.pi / 2, 0.0]))):
        st_ref, out_ref = ref.synthetic_ahrs_step(st_ref, ev, params)
        st_core, out_core = core.synthetic_ahrs_step(st_core, ev, params)
    assert out_ref.valid and math.isfinite(out_ref.heading_sigma_rad) and out_ref.pitch_sigma_rad < 1.0
    _differs(out_ref, out_core, "output at 90 deg", bad)
    imu = ImuEvent(0.1, np.zeros(3), np.array([0.2, 0.0, 0.4]))   # still at rest: B stays at 90 deg
    st_ref, _ = ref.synthetic_ahrs_step(st_ref, imu, params)
    st_core, _ = core.synthetic_ahrs_step(st_core, imu, params)
    before = st_core.to_state()
    bad_event = FcAttitudeEvent(0.1, np.array([0.0, math.pi / 2, 0.0]))   # due: ref_update_interval_s
    with pytest.raises(ValueError) as e_ref:
        ref.synthetic_ahrs_step(st_ref, bad_event, params)
    with pytest.raises(ValueError) as e_core:
        core.synthetic_ahrs_step(st_core, bad_event, params)
    assert str(e_core.value) == str(e_ref.value) and "singular" in str(e_ref.value)
    _differs(before, st_core.to_state(), "after refusal", bad)
    for ev in (ImuEvent(0.12, np.array([0.0, -0.5, 0.0]), np.array([0.2, 0.0, 0.4])),
               FcAttitudeEvent(0.12, np.array([0.0, math.pi / 2 - 0.01, 0.0]))):
        st_ref, out_ref = ref.synthetic_ahrs_step(st_ref, ev, params)
        st_core, out_core = core.synthetic_ahrs_step(st_core, ev, params)
    assert out_ref.valid
    _differs(out_ref, out_core, "next output", bad)
    _differs(st_ref, st_core.to_state(), "next state", bad)
    assert not bad, bad[:5]


def test_pipeline_runs_b_in_the_core(recorded, monkeypatch):
    # GIVEN the Pipeline that fed B's reference above, WHEN a Pipeline with the core backend (the
    # default) runs the same log, THEN B is held in the core and the Pipeline's solutions, events,
    # B's output and state, the air data and the KF1 estimate it hands on are the same
    name, rec = recorded
    if name != "arducopter-rtl-midflight.bin":
        pytest.skip("one flight is enough for the wiring")
    monkeypatch.delenv("AZIMUTHD_CORE", raising=False)
    p = Pipeline(rec["cfg"])
    events: list = []
    sols = list(feed_pipeline(p, rec["items"], events))
    q = rec["pipeline"]
    assert p.core.name == "core" and isinstance(p.ahrs, core.HeldSyntheticAhrs)
    assert events == rec["events"] and len(sols) == len(rec["solutions"]) > 100
    bad: list = []
    _differs(rec["solutions"], sols, "solutions", bad)
    _differs(q.ahrs_out, p.ahrs_out, "B output", bad)
    _differs(q.ahrs, p.ahrs.to_state(), "B state", bad)
    _differs(q.kf1_estimate(), p.kf1_estimate(), "KF1", bad)
    assert q.air_data() == p.air_data()
    assert not bad, bad[:5]


def test_b_core_equals_reference_with_heading_mode_and_a_calibration(recorded):
    # GIVEN the RTL log's events, WHEN B runs with what the daemon's default config does not use:
    # the heading-only magnetometer update (mag_mode "heading") and a KF1 calibration from an earlier
    # flight applied (this flight's learnt estimate), THEN the core equals the reference there too
    name, rec = recorded
    if name != "arducopter-rtl-midflight.bin":
        pytest.skip("one flight is enough for the variants")
    calls = rec["calls"]
    learnt = rec["end"].kf1_learn
    assert learnt.field_norm_gauss is not None and learnt.n_updates > 0
    params = dataclasses.replace(calls[0][2], mag_mode="heading")
    start = dataclasses.replace(rec["start"], kf1_applied=dataclasses.replace(learnt, flight_count=1))
    calls = [(kind, arg, params, output, None) for kind, arg, _, output, _ in calls]
    st_ref, out_ref = _run(calls, start, ref)
    st_core, out_core = _run(calls, start, core)
    bad: list = []
    for k, (a, b) in enumerate(zip(out_ref, out_core)):
        _differs(a, b, f"event {k}", bad)
    _differs(st_ref, st_core.to_state(), "state", bad)
    assert not bad, bad[:5]
    last = out_ref[-1]
    assert last.kf1_applied_flights == 1 and last.mag_fused > 0
