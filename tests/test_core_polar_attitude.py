"""Method C's attitude filter in the compiled core equals its Python reference (issue 19 items 1-2):
estimators/polar_attitude.py (polar_attitude_init, _init_at, _step, _estimate, _unseen, and the
zero-rate update at rest of estimators/zero_rate.py that the Pipeline applies to it) against
core/polar_attitude.hpp through estimators/core.py.

GIVEN the calls a Pipeline made into C (recorded at the Pipeline, C in the reference) on
- simulated flights (sim.offline): any_motion_aerobatic (rest, then loops and rolls through
  upside down at up to ~400 deg/s), any_motion_handheld, inclined_rail (rest, the rail launch whose
  seconds of acceleration are gated out, the re-entry after them, flight), and a hand launch;
- the real logs in ../shared/data, read by service.logreaders and replayed through the Pipeline:
  the ArduCopter RTL DataFlash (started mid-flight: polar_attitude_init_at) and the ArduCopter
  telemetry log (RAW_IMU at ~2.7 Hz: every interval a hole bridged, gaps not integrated);
- edge inputs driven directly: NaN samples, dt 0 and time going back, a gap beyond max_dt_s and the
  restart after it, an unseen interval, a tilt error beyond the gate re-levelled at rest, the
  re-entry test waiting and the covariance matching, bad shapes and bad arguments,
WHEN the reference and the core (the state held in C++) take the same calls,
THEN after every call the diagnostics (reason strings, flags identical; innovation, test ratios,
raised variance, re-level angle to 1e-9 relative), the whole state (to_state(): quaternion, x_hat,
the 25 x 25 covariance against 1e-9 sqrt(P_ii P_jj), accumulators, counters identical) and the
estimate (roll, pitch, their covariance, gyro bias) agree (tests/parity_compare.py), and a Pipeline
on the core backend holds C in the core and gives the same solutions and events as with C's
reference. A test here fails when any value differs beyond 1e-9 relative.
"""
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
sys.path.insert(0, str(ROOT / "tests"))
from pipeline_recording import fly, run_with_backend, select_core_backend  # noqa: E402
from parity_compare import differences  # noqa: E402
from sitl import pipeline_inputs, scenario_site  # noqa: E402

from estimators import core  # noqa: E402
from estimators import polar_attitude as ref  # noqa: E402
from estimators import zero_rate as zr  # noqa: E402
from estimators.polar_attitude import PolarAttitudeParams  # noqa: E402
from service.config import validate  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")

pytestmark = pytest.mark.skipif(not core.POLAR_AVAILABLE,
                                reason=f"compiled core without C's attitude filter: {core.IMPORT_ERROR or 'old build'}")

C_CALLS = ("polar_attitude_init", "polar_attitude_init_at", "polar_attitude_step", "polar_attitude_estimate",
           "polar_attitude_unseen", "attitude_zero_rate_update")


# --- the calls a Pipeline makes into C ------------------------------------------------------------

def _reference_c(backend):
    """``backend`` with C in the reference (what the Pipeline's calls are recorded on)."""
    from service import core_backend
    py = core_backend.select({"AZIMUTHD_CORE": "python"})
    return dataclasses.replace(backend, **{k: getattr(py, k) for k in C_CALLS})


def _recording(backend, calls: list):
    """``backend`` with C in the reference, every call into C appended to ``calls`` as
    (name, args, kwargs) (estimate calls are not recorded: the replay checks the estimate after
    every call)."""
    b = _reference_c(backend)

    def rec(name, fn):
        def call(*a, **k):
            calls.append((name, a, k))
            return fn(*a, **k)
        return call
    return dataclasses.replace(b, **{k: rec(k, getattr(b, k)) for k in C_CALLS if k != "polar_attitude_estimate"})


def _sim(scenario: str, duration_s: float, rate_hz: float, seed: int = 0, overrides=None, cfg=None):
    """(config, the Pipeline's inputs) of a simulated flight; ``cfg``: the config without the site
    (None: the operator's config for the scenario, bench/sitl.scenario_site)."""
    from sim.offline import simulate
    run = simulate(scenario, seed=seed, imu_grade="consumer", imu_rate_hz=rate_hz, duration_s=duration_s,
                   overrides=overrides)
    s = run.site
    site = {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"], "decimal_year": s["decimal_year"]}
    cfg = dict(scenario_site(scenario) if cfg is None else cfg)
    cfg["site"] = {**cfg.get("site", {}), **site}
    return validate({**cfg, "mavlink": {"imu_rate_hz": rate_hz}}), pipeline_inputs(run)


# a hand-held rig as bench/any_motion.py flies it (aligned case, the FC's yaw not used), 50 Hz
ANY_MOTION = {"launch": {"case": "aligned", "vehicle": "hand"}, "heading": {"use_fc_yaw": False}}
SIMS = {
    "aerobatic": lambda: _sim("any_motion_aerobatic", 60.0, 50.0, cfg=ANY_MOTION),
    "handheld": lambda: _sim("any_motion_handheld", 60.0, 50.0, cfg=ANY_MOTION),
    "inclined_rail": lambda: _sim("inclined_rail", 30.0, 100.0, seed=3, overrides={"launcher": {"rest_s": 8.0}}),
}
LOGS = ("arducopter-rtl-midflight.bin", "arducopter-flight.tlog")
_INPUTS: dict = {}


def _fly(name: str):
    """The flight through the Pipeline (tests/pipeline_recording.fly)."""
    return fly(name, SIMS, _INPUTS, DATA, ())


def _run(name: str, backend):
    """(what ``_fly`` returns, the Pipeline it ran) with ``backend`` as the Pipeline's core backend."""
    return run_with_backend(_fly, name, backend)


_CACHE: dict = {}


@pytest.fixture(scope="module", params=[*SIMS, *LOGS])
def recorded(request):
    """The flight with C in the reference: the calls into C, what the flight gave, its Pipeline."""
    from service import core_backend
    name = request.param
    if name not in _CACHE:
        calls: list = []
        out, pipe = _run(name, _recording(core_backend.select(), calls))
        _CACHE[name] = {"calls": calls, "out": out, "pipeline": pipe}
    return name, _CACHE[name]


# --- replay ------------------------------------------------------------------------------------------

class Replay:
    """The reference and the core side by side: each call to both, then everything compared."""

    def __init__(self, label: str):
        self.label = label
        self.ref = self.core = None
        self.k = 0
        self.kinds: dict[str, int] = {}

    def _check(self, what: str, dr=None, dc=None) -> None:
        where = f"{self.label} call {self.k} ({what})"
        bad = differences(dr, dc, f"{where} diag")
        sc = self.core.to_state() if isinstance(self.core, core.HeldPolarAttitude) else self.core
        bad += differences(self.ref, sc, f"{where} state")
        bad += differences(ref.polar_attitude_estimate(self.ref), core.polar_attitude_estimate(self.core),
                           f"{where} estimate")
        assert not bad, bad[:4]
        self.k += 1

    def init(self, *a, **k):
        self.ref, self.core = ref.polar_attitude_init(*a, **k), core.polar_attitude_init(*a, **k)
        self._check("init")

    def init_at(self, *a, **k):
        self.ref, self.core = ref.polar_attitude_init_at(*a, **k), core.polar_attitude_init_at(*a, **k)
        self._check("init_at")

    def step(self, t, w, f, params):
        self.ref, dr = ref.polar_attitude_step(self.ref, t, w, f, params)
        self.core, dc = core.polar_attitude_step(self.core, t, w, f, params)
        kind = ("relevelled" if dr.relevelled else "raised" if dr.accel_var_raised_m2_s4 > 0.0
                else dr.reason.split(" (")[0].split(":")[0] or ("fused" if dr.fused else "sample"))
        self.kinds[kind] = self.kinds.get(kind, 0) + 1
        self._check(f"step t={t}", dr, dc)
        return dr

    def unseen(self, s, params):
        self.ref = ref.polar_attitude_unseen(self.ref, s, params)
        self.core = core.polar_attitude_unseen(self.core, s, params)
        self.kinds["unseen"] = self.kinds.get("unseen", 0) + 1
        self._check("unseen")

    def zero_rate(self, rate, params):
        self.ref, dr = zr.attitude_zero_rate_update(self.ref, rate, params)
        self.core, dc = core.attitude_zero_rate_update(self.core, rate, params)
        self.kinds["zero_rate"] = self.kinds.get("zero_rate", 0) + 1
        self._check("zero_rate", dr, dc)

    def run(self, calls) -> "Replay":
        for name, a, k in calls:
            {"polar_attitude_init": self.init, "polar_attitude_init_at": self.init_at,
             "polar_attitude_step": lambda st, *r, **kw: self.step(*r, **kw),
             "polar_attitude_unseen": lambda st, *r, **kw: self.unseen(*r, **kw),
             "attitude_zero_rate_update": lambda st, *r, **kw: self.zero_rate(*r, **kw)}[name](*a, **k)
        return self


# what each flight must have exercised (not a run that stayed in one branch)
EXERCISED = {
    "aerobatic": {"fused", "zero_rate"},
    "handheld": {"fused", "zero_rate"},
    "inclined_rail": {"fused", "specific-force residual gated out", "zero_rate"},
    "arducopter-rtl-midflight.bin": {"fused", "increments restarted"},
    "arducopter-flight.tlog": {"fused", "gap of"},
}


def test_c_core_equals_reference_on_what_the_pipeline_feeds(recorded):
    name, rec = recorded
    calls = rec["calls"]
    assert sum(1 for c in calls if c[0] == "polar_attitude_step") > 200
    r = Replay(name).run(calls)
    need = EXERCISED[name]
    assert all(any(k.startswith(n) for k in r.kinds) for n in need), (need, r.kinds)


def test_pipeline_runs_c_in_the_core(recorded, monkeypatch):
    # GIVEN the flight recorded above (C in the reference, everything else as selected), WHEN it runs
    # on the default core backend, THEN C is held in the core, and the solutions (or the replay's rows),
    # the events and C's final state and estimate are the same
    from service import core_backend
    name, rec = recorded
    if name not in ("inclined_rail", "arducopter-rtl-midflight.bin"):
        pytest.skip("two flights are enough for the wiring (a launch; a start in flight)")
    backend = select_core_backend(monkeypatch)
    assert backend.polar_attitude_step is core.polar_attitude_step
    out, p = _run(name, backend)
    q = rec["pipeline"]
    assert isinstance(p.polar_att, core.HeldPolarAttitude) and not isinstance(q.polar_att, core.HeldPolarAttitude)
    assert (out.get("events"), len(out.get("solutions", out.get("time_s")))) == \
        (rec["out"].get("events"), len(rec["out"].get("solutions", rec["out"].get("time_s"))))
    bad = differences(rec["out"], out, name)
    bad += differences(q.polar_att, p.polar_att.to_state(), "C state")
    bad += differences(ref.polar_attitude_estimate(q.polar_att), core.polar_attitude_estimate(p.polar_att), "C est")
    assert not bad, bad[:5]


def test_a_deep_copy_goes_on_as_the_unbroken_run(recorded):
    name, rec = recorded
    if name != "aerobatic":
        pytest.skip("one flight is enough")
    calls = rec["calls"]
    whole = Replay(name).run(calls)
    split = int(len(calls) * 0.6)
    first = Replay(name).run(calls[:split])
    second = Replay(name)
    second.ref, second.core = first.ref, copy.deepcopy(first.core)
    assert isinstance(second.core, core.HeldPolarAttitude) and second.core is not first.core
    second.run(calls[split:])
    assert not differences(whole.core.to_state(), second.core.to_state(), "split")
    # the copy holds its own core state: stepping it did not move the original
    assert first.core.n_updates < second.core.n_updates


# --- edge inputs, driven directly ---------------------------------------------------------------------

def _still(t, w=(0.001, -0.002, 0.0005), f=(0.0, 0.0, -9.80665)):
    return t, np.array(w), np.array(f)


def test_bad_samples_time_and_gaps():
    # GIVEN a filter levelled at rest, WHEN it gets a NaN gyro, an infinite force, a NaN time, the
    # same time again, an earlier time, a hole (samples lost), a gap beyond max_dt_s and the samples
    # after it, THEN the core and the reference say and do the same at each
    p = PolarAttitudeParams()
    r = Replay("edge")
    r.init(p)
    t = 0.0
    for _ in range(40):
        r.step(*_still(t), p)
        t += 0.02
    assert r.ref.initialised
    r.step(t, np.array([math.nan, 0.0, 0.0]), np.array([0.0, 0.0, -9.8]), p)
    r.step(t, np.zeros(3), np.array([0.0, math.inf, -9.8]), p)
    r.step(math.nan, np.zeros(3), np.array([0.0, 0.0, -9.8]), p)
    r.step(*_still(t - 0.02), p)             # dt = 0 (the last sample's time)
    r.step(*_still(t - 0.5), p)              # time going back
    for _ in range(10):
        r.step(*_still(t, w=(0.3, -0.2, 0.5)), p)
        t += 0.02
    t += 0.2                                 # a hole of lost samples: bridged
    for _ in range(10):
        r.step(*_still(t, w=(-0.4, 0.1, 0.2)), p)
        t += 0.02
    t += 2.0                                 # a gap: not integrated, sigma widened
    for _ in range(30):
        r.step(*_still(t), p)
        t += 0.02
    assert {"time not increasing", "non-finite sample", "gap of 2.020 s not integrated; attitude sigma widened",
            "fused"} <= set(r.kinds), r.kinds
    # shapes the reference refuses with a reason (not an exception)
    dr = ref.polar_attitude_step(r.ref, t, np.zeros(2), np.zeros(3), p)[1]
    dc = core.polar_attitude_step(r.core, t, np.zeros(2), np.zeros(3), p)[1]
    assert dr == dc and dr.reason == "gyro and accel must have shape (3,)"


def test_unseen_restart_and_init_at():
    # GIVEN a filter started at a given roll/pitch (with a gyro-bias prior), WHEN an interval is not
    # seen (before and after it levelled), the clock restarts lower, and params change, THEN equal
    p = PolarAttitudeParams(max_dt_s=0.3)
    r = Replay("init_at")
    r.init(p, gyro_bias_rad_s=np.array([0.01, -0.02, 0.003]), gyro_bias_sigma_rad_s=0.002)
    r.unseen(1.5, p)                         # not levelled yet: nothing to widen
    r.init_at(100.0, math.radians(20.0), math.radians(-35.0), math.radians(3.0), p,
              np.array([0.001, 0.002, -0.003]), 0.004)
    t = 100.0
    for k in range(60):
        r.step(t, np.array([0.2, -0.1, 0.05]), np.array([3.0, -2.5, -8.9]), p)
        t += 0.02
    r.unseen(4.0, p)                         # an FC clock restart: 4 s not seen
    t = 3.0                                  # the new clock starts lower
    p2 = dataclasses.replace(p, manoeuvre_speed_m_s=10.0, relevel_allowed=False)
    for k in range(60):
        r.step(t, np.array([0.0, 0.3, -0.2]), np.array([0.5, 1.0, -9.7]), p2)
        t += 0.02
    # the increments restart at the first sample after init_at (which here has its time: dt 0) and
    # after the unseen interval
    assert r.kinds.get("increments restarted") == 2 and r.kinds["unseen"] == 2, r.kinds


def test_relevel_reentry_and_matching():
    # GIVEN a filter levelled at rest, WHEN it is turned upside down by a rotation its state does not
    # know (as after a tumble beyond the gyro range), THEN the residuals are gated out and after
    # relevel_rest_s at rest it re-levels from the accelerometer; then a sustained acceleration
    # (gated out), a transient settling (the re-entry test waits) and the re-entry update with
    # its covariance matching. Also the re-entry test switched off. All equal.
    for p in (PolarAttitudeParams(), PolarAttitudeParams(reentry_max_wait_updates=0, reentry_match_gain=0.0)):
        r = Replay("relevel")
        r.init(p)
        t = 0.0
        for _ in range(60):
            r.step(*_still(t), p)
            t += 0.02
        for _ in range(100):                 # upside down, the filter not told
            r.step(*_still(t, f=(0.3, 0.2, 9.80)), p)
            t += 0.02
        assert r.kinds.get("relevelled") == 1, r.kinds
        for _ in range(50):
            r.step(*_still(t, f=(0.3, 0.2, 9.80)), p)
            t += 0.02
        for k in range(60):                  # 2.5 m/s^2 forward for 1.2 s, then decaying
            r.step(*_still(t, f=(2.8, 0.2, 9.80)), p)
            t += 0.02
        for k in range(80):
            a = 2.5 * math.exp(-k / 6.0) * (1.0 + 0.5 * math.sin(k))
            r.step(*_still(t, f=(0.3 + a, 0.2, 9.80)), p)
            t += 0.02
        assert "specific-force residual gated out" in r.kinds, r.kinds
        if p.reentry_max_wait_updates:
            assert {"raised", "specific-force residual not settled after a gated-out run"} <= set(r.kinds), r.kinds


def test_arguments_refused_alike():
    # bad arguments: the core refuses them with the reference's message
    p = PolarAttitudeParams()
    for call in (lambda m: m.polar_attitude_init(p, gyro_bias_rad_s=[0.0, math.nan, 0.0]),
                 lambda m: m.polar_attitude_init(p, gyro_bias_rad_s=[0.0, 0.0]),
                 lambda m: m.polar_attitude_init(p, gyro_bias_sigma_rad_s=-1.0),
                 lambda m: m.polar_attitude_init_at(math.inf, 0.0, 0.0, 0.1, p),
                 lambda m: m.polar_attitude_init_at(0.0, math.nan, 0.0, 0.1, p),
                 lambda m: m.polar_attitude_init_at(0.0, 0.0, 0.0, 0.0, p),
                 lambda m: m.polar_attitude_unseen(m.polar_attitude_init(p), -1.0, p),
                 lambda m: m.polar_attitude_unseen(m.polar_attitude_init(p), math.nan, p)):
        with pytest.raises(ValueError) as e_ref:
            call(ref)
        with pytest.raises(ValueError) as e_core:
            call(core)
        assert str(e_core.value) == str(e_ref.value)


def test_the_backend_selects_c(monkeypatch, caplog):
    # GIVEN the core (the default), AZIMUTHD_CORE=python, and an extension built before C was ported
    # WHEN the service selects THEN C runs in the core, in the reference, in the reference with one
    # warning line saying so
    import logging

    from service import core_backend
    monkeypatch.setattr(core_backend, "_said", set())
    b = core_backend.select({})
    assert b.name == "core" and all(getattr(b, k) is getattr(core, k) for k in C_CALLS)
    py = core_backend.select({"AZIMUTHD_CORE": "python"})
    assert py.polar_attitude_step is ref.polar_attitude_step and py.attitude_zero_rate_update is zr.attitude_zero_rate_update
    monkeypatch.setattr(core, "POLAR_AVAILABLE", False)
    with caplog.at_level(logging.WARNING, logger="azimuthd.core"):
        old = core_backend.select({})
        core_backend.select({})
    assert old.name == "core" and old.strapdown_step is core.strapdown_step_held
    assert old.polar_attitude_step is ref.polar_attitude_step and old.polar_attitude_init is ref.polar_attitude_init
    assert [r.getMessage() for r in caplog.records] == [
        "compiled core without method C's attitude filter (an older build): it runs the Python reference"]


def test_the_shared_compare_flags_what_it_must():
    # tests/parity_compare.differences (the core's parity tests share it): a covariance element off
    # by 2e-9 sqrt(P_ii P_jj) is flagged and 0.5e-9 is not, also where the element itself is ~0; a
    # vector in its max norm; NaN equals NaN; a reason string, a flag or a None that differs is flagged
    P = np.array([[4.0, 1e-20], [1e-20, 1.0]])
    for off, flagged in ((2e-9, True), (0.5e-9, False)):
        Q = P.copy()
        Q[0, 1] = Q[1, 0] = 1e-20 + off * 2.0
        assert bool(differences({"P": P}, {"P": Q})) is flagged
        assert bool(differences(np.array([1.0, 1e-12]), np.array([1.0, 1e-12 + off]))) is flagged
    d = ref.PolarAttitudeDiag(updated=True, innovation_m_s2=np.array([0.1, math.nan, 0.0]), reason="x")
    assert not differences(d, dataclasses.replace(d, innovation_m_s2=np.array([0.1, math.nan, 0.0])))
    assert [p for p, _ in differences(d, dataclasses.replace(d, reason="y", fused=np.bool_(True)))] == \
        [".fused", ".reason"]
    assert differences((1.0, None), (1.0, 0.0)) and not differences((np.bool_(True), 2), (True, 2))
    # an angle (``_rad``) near 0 against 1 rad: 3e-7 rad off by 7e-16 (rounding of the quaternion it is
    # read from) is not flagged, off by 2e-9 rad is; a float that is no angle stays relative
    e = ref.AttitudeEstimate(3e-7, 0.2, np.eye(2), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    assert not differences(e, dataclasses.replace(e, roll_rad=3e-7 + 7e-16))
    assert [p for p, _ in differences(e, dataclasses.replace(e, roll_rad=3e-7 + 2e-9))] == [".roll_rad"]
    assert differences({"x_m": 3e-7}, {"x_m": 3e-7 + 7e-16})
