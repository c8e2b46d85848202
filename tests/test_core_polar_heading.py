"""Method C's heading filter in the compiled core equals its Python reference (issue 19 items 1-2):
estimators/polar_heading.py (polar_heading_init, _step, _unseen, _estimate, _attitude, and the
zero-rate update at rest of estimators/zero_rate.py that the Pipeline applies to it) against
core/polar_heading.hpp through estimators/core.py.

GIVEN the calls a Pipeline made into C's heading filter (recorded at the Pipeline, the heading filter
in the reference) on
- simulated flights (sim.offline): any_motion aerobatic (loops and rolls through upside down: the
  platform formulation), handheld, hover_spin, magnet_nearby (a stationary extra field for 20 s:
  innovations gated out, the magnetometer withheld) and magnet_attached (a new hard iron: rejections,
  the hard iron re-learnt), inclined_rail (rest, rail launch, flight);
- the real logs in ../shared/data replayed as ``azimuthd replay`` runs them: the ArduCopter RTL
  DataFlash (started mid-flight), the ArduCopter telemetry log (RAW_IMU at ~2.7 Hz: every step a gap
  beyond max_dt_s, the heading widened as unseen) and the PX4 logs that reach C's heading;
- edge inputs driven directly: NaN samples, dt 0 and time going back, a gap, an unseen interval and
  the restart after it, params changed, the Euler formulation (pitch beyond max_abs_pitch_rad), a
  field too weak, continuous rejection and the reset after it, a withheld magnetometer, levelling
  with a given roll/pitch, bad shapes (answered by the reference on the held record) and refused
  arguments with the reference's messages,
WHEN the reference and the core (the state held in C++) take the same calls,
THEN after every call the diagnostics (reason strings and flags identical; heading measurement,
innovation, its variance, test ratio, reset jump to 1e-9 relative), the whole state (to_state(): x,
the covariance against 1e-9 sqrt(P_ii P_jj), the filter's own attitude, counters and times
identical), the published estimate and the composed attitude agree (tests/parity_compare.py), and a
Pipeline on the core backend gives the same solutions and events as with the heading filter in the
reference. A test here fails when any value differs beyond 1e-9 relative (the last test shows it).
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
from parity_compare import RTOL, differences  # noqa: E402
from sitl import pipeline_inputs, scenario_site  # noqa: E402

from estimators import core  # noqa: E402
from estimators import polar_heading as ref  # noqa: E402
from estimators import zero_rate as zr  # noqa: E402
from estimators.polar_heading import HeadingInputs, PolarHeadingParams  # noqa: E402
from service.config import validate  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")

pytestmark = pytest.mark.skipif(not core.POLAR_HEADING_AVAILABLE,
                                reason=f"compiled core without C's heading filter: {core.IMPORT_ERROR or 'old build'}")

H_CALLS = ("polar_heading_init", "polar_heading_step", "polar_heading_estimate", "polar_heading_attitude",
           "polar_heading_unseen", "heading_zero_rate_update")
RECORDED = ("polar_heading_init", "polar_heading_step", "polar_heading_unseen", "heading_zero_rate_update")


# --- the calls a Pipeline makes into C's heading filter -----------------------------------------------

def _reference_h(backend):
    """``backend`` with C's heading filter in the reference (what the Pipeline's calls are recorded on)."""
    from service import core_backend
    py = core_backend.select({"AZIMUTHD_CORE": "python"})
    return dataclasses.replace(backend, **{k: getattr(py, k) for k in H_CALLS})


def _recording(backend, calls: list):
    """``backend`` with the heading filter in the reference, every call that changes its state appended
    to ``calls`` as (name, args, kwargs) (the replay checks the estimate and attitude after each)."""
    b = _reference_h(backend)

    def rec(name, fn):
        def call(*a, **k):
            calls.append((name, a, k))
            return fn(*a, **k)
        return call
    return dataclasses.replace(b, **{k: rec(k, getattr(b, k)) for k in RECORDED})


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
    "hover_spin": lambda: _sim("any_motion_hover_spin", 45.0, 50.0, cfg=ANY_MOTION),
    "magnet_nearby": lambda: _sim("any_motion_magnet_nearby", 70.0, 50.0, cfg=ANY_MOTION),
    "magnet_attached": lambda: _sim("any_motion_magnet_attached", 90.0, 50.0, cfg=ANY_MOTION),
    "inclined_rail": lambda: _sim("inclined_rail", 30.0, 100.0, seed=3, overrides={"launcher": {"rest_s": 8.0}}),
}
LOGS = ("arducopter-rtl-midflight.bin", "arducopter-flight.tlog", "px4-quad-no-gnss.ulg",
        "px4-vtol-airspeed-small.ulg", "px4-bench-sample.ulg")
NO_SITE = ("px4-quad-no-gnss.ulg", "px4-bench-sample.ulg")
_INPUTS: dict = {}


def _fly(name: str):
    """The flight through the Pipeline (tests/pipeline_recording.fly)."""
    return fly(name, SIMS, _INPUTS, DATA, NO_SITE)


def _run(name: str, backend):
    """(what ``_fly`` returns, the Pipeline it ran) with ``backend`` as the Pipeline's core backend."""
    return run_with_backend(_fly, name, backend)


_CACHE: dict = {}


@pytest.fixture(scope="module", params=[*SIMS, *LOGS])
def recorded(request):
    """The flight with C's heading filter in the reference: its calls, what the flight gave, its Pipeline."""
    from service import core_backend
    name = request.param
    if name not in _CACHE:
        calls: list = []
        out, pipe = _run(name, _recording(core_backend.select(), calls))
        _CACHE[name] = {"calls": calls, "out": out, "pipeline": pipe}
    return name, _CACHE[name]


# --- replay ------------------------------------------------------------------------------------------

RESIDUALS = ("innovation_rad", "reset_jump_rad", "test_ratio")


def _angle_differences(a: float, b: float, where: str) -> list:
    """A heading in [0, 2pi) compared on the circle to 1e-9 rad (1e-9 relative to one radian). Its own
    relative error means nothing near 0 = 2pi: the heading there is a sum of angles of ~1 rad wrapped
    (x[0] + the yaw of C_HB), so two roundings 1e-15 rad apart read as 1e-9 relative at a heading of
    1.6e-6 rad (magnet_attached, t = 59.54 s), and the wrap may put one at 2pi - e and the other at +e."""
    a, b = float(a), float(b)
    if a == b or (math.isnan(a) and math.isnan(b)):
        return []
    d = abs(math.remainder(a - b, 2.0 * math.pi)) if math.isfinite(a) and math.isfinite(b) else math.inf
    return [] if d <= RTOL else [(where, f"{a!r} vs {b!r} ({d:.3g} rad apart on the circle)")]


def _state_differences(sr, sc, where: str) -> list:
    """tests/parity_compare.differences of two PolarHeadingStates, but x per element: the heading x[0]
    on the circle (``_angle_differences``), the rates and biases x[i] to 1e-9 max(|x_i|, sqrt(P_ii)),
    as the covariance is compared. x holds an angle of ~1 rad beside rates of 1e-5..1e-3 rad/s: a
    max norm over the vector would let a bias be 1e-9 rad/s off (a thousand times its 1e-9 relative),
    and a relative measure of a value far below its own sigma (a bias estimated 1e-19 rad/s from an
    exact 0 in one, 1e-23 in the other) compares rounding noise."""
    xr, xc = np.array(sr.x, float), np.array(sc.x, float)
    if xr.shape != xc.shape:
        return [(f"{where}.x", f"shape {xr.shape} vs {xc.shape}")]
    bad = _angle_differences(xr[0], xc[0], f"{where}.x[0]")
    sig = np.sqrt(np.abs(np.diag(np.asarray(sr.P, float)))) if np.shape(sr.P) == (len(xr), len(xr)) else 0.0
    tol = RTOL * np.maximum(np.maximum(np.abs(xr), np.abs(xc)), sig)
    for i in range(1, len(xr)):
        if not (xr[i] == xc[i] or (math.isnan(xr[i]) and math.isnan(xc[i])) or abs(xr[i] - xc[i]) <= tol[i]):
            bad.append((f"{where}.x[{i}]", f"{xr[i]!r} vs {xc[i]!r} (tolerance {tol[i]:.3g})"))
    xr[:] = xc[:] = 0.0
    return bad + differences(dataclasses.replace(sr, x=xr), dataclasses.replace(sc, x=xc), where)


def _solutions_differences(a: dict, b: dict, where: str) -> list:
    """A flight's outputs (``_fly``) compared: the solutions' headings on the circle, the rest as
    tests/parity_compare.differences compares it."""
    if "solutions" not in a:
        return differences(a, b, where)
    bad: list = []
    sa, sb = list(a["solutions"]), list(b["solutions"])
    if len(sa) != len(sb):
        return [(f"{where}.solutions", f"{len(sa)} vs {len(sb)} solutions")]
    for i, (x, y) in enumerate(zip(sa, sb)):
        for k in ("heading_rad", "azimuth_rad"):
            u, v = getattr(x, k), getattr(y, k)
            if u is not None and v is not None:
                bad += _angle_differences(u, v, f"{where}.solutions[{i}].{k}")
                x, y = dataclasses.replace(x, **{k: 0.0}), dataclasses.replace(y, **{k: 0.0})
        bad += differences(x, y, f"{where}.solutions[{i}]")
    return bad + differences({k: v for k, v in a.items() if k != "solutions"},
                             {k: v for k, v in b.items() if k != "solutions"}, where)


def _diag_differences(dr, dc, where: str) -> list:
    """tests/parity_compare.differences, but for the innovation (and the reset jump, the same number),
    compared in its own sigma as a covariance element is: |d nu| <= 1e-9 sqrt(S), and the test ratio
    (nu^2 / (P + R) / chi2, compared with 1 by the gate) to 1e-9 max(1, ratio). The innovation is
    z - psi, two angles of ~1 rad: when they agree (a noise-free rig that turns as its attitude says)
    it is rounding, ~1e-16, and the reference's and the core's roundings need not be the same number
    (here 8.9e-16 vs 0.0 after a state that agreed to 1 ulp); any relative measure of it is then noise."""
    if not isinstance(dr, ref.HeadingDiag) or not isinstance(dc, ref.HeadingDiag):
        return differences(dr, dc, where)
    blank = {**{k: 0.0 for k in RESIDUALS}, "heading_meas_rad": 0.0}
    bad = differences(dataclasses.replace(dr, **blank), dataclasses.replace(dc, **blank), where)
    bad += _angle_differences(dr.heading_meas_rad, dc.heading_meas_rad, f"{where}.heading_meas_rad")
    scale = math.sqrt(abs(dr.innovation_var_rad2)) if math.isfinite(dr.innovation_var_rad2) else 1.0
    for k in RESIDUALS:
        a, b = float(getattr(dr, k)), float(getattr(dc, k))
        tol = RTOL * (max(1.0, abs(a)) if k == "test_ratio" else scale)
        if not (a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol):
            bad.append((f"{where}.{k}", f"{a!r} vs {b!r} (tolerance {tol:.3g})"))
    return bad


class Replay:
    """The reference and the core side by side: each call to both, then everything compared."""

    def __init__(self, label: str, core_params=None):
        self.label = label
        self.ref = self.core = None
        self.k = 0
        self.kinds: dict[str, int] = {}
        self.core_params = core_params  # the mutation check: other params for the core only

    def _check(self, what: str, dr=None, dc=None) -> None:
        where = f"{self.label} call {self.k} ({what})"
        bad = _diag_differences(dr, dc, f"{where} diag")
        sc = self.core.to_state() if isinstance(self.core, core.HeldPolarHeading) else self.core
        bad += _state_differences(self.ref, sc, f"{where} state")
        er, ec = ref.polar_heading_estimate(self.ref), core.polar_heading_estimate(self.core)
        bad += _angle_differences(er.heading_rad, ec.heading_rad, f"{where} estimate.heading_rad")
        bad += differences(dataclasses.replace(er, heading_rad=0.0), dataclasses.replace(ec, heading_rad=0.0),
                           f"{where} estimate")
        bad += differences(ref.polar_heading_attitude(self.ref), core.polar_heading_attitude(self.core),
                           f"{where} attitude")
        if er.initialised:   # the attitude at another heading (the arbitration's)
            bad += differences(ref.polar_heading_attitude(self.ref, er.heading_rad + 0.3),
                               core.polar_heading_attitude(self.core, er.heading_rad + 0.3), f"{where} attitude(h)")
        assert not bad, bad[:4]
        self.k += 1

    def _cp(self, params):
        return params if self.core_params is None else self.core_params

    def init(self, *a, **k):
        self.ref, self.core = ref.polar_heading_init(*a, **k), core.polar_heading_init(*a, **k)
        self._check("init")

    def step(self, u, params=PolarHeadingParams()):
        st = self.ref
        if st.initialised and st.time_s is not None and u.time_s - st.time_s > params.max_dt_s:
            self.kinds["gap"] = self.kinds.get("gap", 0) + 1     # widened as unseen inside the step
        self.ref, dr = ref.polar_heading_step(self.ref, u, params)
        self.core, dc = core.polar_heading_step(self.core, u, self._cp(params))
        kind = ("reset" if dr.reset else dr.reason.split(" (")[0].split(" 0.")[0]
                or ("fused" if dr.fused else "measured" if dr.measured else "sample"))
        self.kinds[kind] = self.kinds.get(kind, 0) + 1
        if dr.measured:
            self.kinds["platform" if self.ref.platform else "euler"] = 1
        self._check(f"step t={u.time_s}", dr, dc)
        return dr

    def unseen(self, s, params=PolarHeadingParams()):
        self.ref = ref.polar_heading_unseen(self.ref, s, params)
        self.core = core.polar_heading_unseen(self.core, s, self._cp(params))
        self.kinds["unseen"] = self.kinds.get("unseen", 0) + 1
        self._check("unseen")

    def zero_rate(self, rate, params):
        self.ref, dr = zr.heading_zero_rate_update(self.ref, rate, params)
        self.core, dc = core.heading_zero_rate_update(self.core, rate, params)
        self.kinds["zero_rate"] = self.kinds.get("zero_rate", 0) + 1
        self._check("zero_rate", dr, dc)

    def run(self, calls) -> "Replay":
        for name, a, k in calls:
            {"polar_heading_init": self.init,
             "polar_heading_step": lambda st, *r, **kw: self.step(*r, **kw),
             "polar_heading_unseen": lambda st, *r, **kw: self.unseen(*r, **kw),
             "heading_zero_rate_update": lambda st, *r, **kw: self.zero_rate(*r, **kw)}[name](*a, **k)
        return self


# what each flight must have exercised (not a run that stayed in one branch); a PX4 log that never
# reaches C's heading is skipped, saying so
EXERCISED = {
    "aerobatic": {"fused", "platform", "zero_rate"},
    "handheld": {"fused", "platform", "zero_rate"},
    "hover_spin": {"fused", "platform"},
    "magnet_nearby": {"fused", "innovation gated out"},
    "magnet_attached": {"fused", "innovation gated out"},
    "inclined_rail": {"fused", "initialised from source"},
    "arducopter-rtl-midflight.bin": {"fused", "initialised from source"},
    "arducopter-flight.tlog": {"fused", "gap"},
    # 6.5 s on the ground, the magnetometer not usable meanwhile: the heading filter predicts only
    "px4-vtol-airspeed-small.ulg": {"sample"},
}


def test_heading_core_equals_reference_on_what_the_pipeline_feeds(recorded):
    name, rec = recorded
    calls = rec["calls"]
    steps = sum(1 for c in calls if c[0] == "polar_heading_step")
    if name.endswith(".ulg") and steps == 0:
        pytest.skip(f"{name}: the replay never steps C's heading filter (no magnetometer/attitude for it)")
    assert steps > 100, steps
    r = Replay(name).run(calls)
    need = EXERCISED.get(name, {"fused"})
    assert need <= set(r.kinds), (need, r.kinds)


def test_pipeline_runs_c_heading_in_the_core(recorded, monkeypatch):
    # GIVEN the flight recorded above (C's heading in the reference, everything else as selected), WHEN it
    # runs on the default core backend, THEN the heading filter is held in the core, and the solutions (or
    # the replay's rows), the events and its final state and estimate are the same
    from service import core_backend
    name, rec = recorded
    if name not in ("inclined_rail", "arducopter-rtl-midflight.bin", "magnet_attached"):
        pytest.skip("three flights are enough for the wiring (a launch; a start in flight; a relearn)")
    backend = select_core_backend(monkeypatch)
    assert backend.polar_heading_step is core.polar_heading_step
    out, p = _run(name, backend)
    q = rec["pipeline"]
    assert isinstance(p.polar_hdg, core.HeldPolarHeading) and not isinstance(q.polar_hdg, core.HeldPolarHeading)
    assert (out.get("events"), len(out.get("solutions", out.get("time_s")))) == \
        (rec["out"].get("events"), len(rec["out"].get("solutions", rec["out"].get("time_s"))))
    bad = _solutions_differences(rec["out"], out, name)
    bad += _state_differences(q.polar_hdg, p.polar_hdg.to_state(), "C heading state")
    er, ec = ref.polar_heading_estimate(q.polar_hdg), core.polar_heading_estimate(p.polar_hdg)
    bad += _angle_differences(er.heading_rad, ec.heading_rad, "C heading estimate")
    bad += differences(dataclasses.replace(er, heading_rad=0.0), dataclasses.replace(ec, heading_rad=0.0), "C est")
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
    assert isinstance(second.core, core.HeldPolarHeading) and second.core is not first.core
    second.run(calls[split:])
    assert not _state_differences(whole.core.to_state(), second.core.to_state(), "split")
    assert first.core.n_fused < second.core.n_fused   # the copy holds its own core state


# --- edge inputs, driven directly ---------------------------------------------------------------------

FIELD = np.array([0.19, 0.02, 0.45])            # body-frame field (gauss), level, heading ~ -6 deg
Q_LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _u(t, mag=FIELD, q=Q_LEVEL, w=(0.001, -0.002, 0.01), roll=0.0, pitch=0.0, decl=0.1, **kw):
    """One HeadingInputs in the platform formulation (``q`` None: the Euler formulation)."""
    base = dict(cov_roll_pitch_rad2=np.eye(2) * 1e-5, mag_body_gauss=None if mag is None else np.asarray(mag, float),
                declination_rad=decl, declination_sigma_rad=0.01, mag_residual_sigma_gauss=None,
                q_P_from_body=None if q is None else np.asarray(q, float),
                cov_att_body_rad2=None if q is None else np.eye(3) * 2e-5, gyro_bias_rad_s=None,
                level_with_roll_pitch=False)
    base.update(kw)
    return HeadingInputs(t, np.asarray(w, float), roll, pitch, **base)


def _turning(t, rate=0.2):
    """The body turned about the vertical by ``rate`` * t: the field and attitude as a rig sees them."""
    c, s = math.cos(rate * t), math.sin(rate * t)
    q = np.array([math.cos(0.5 * rate * t), 0.0, 0.0, math.sin(0.5 * rate * t)])
    m = np.array([c * FIELD[0] + s * FIELD[1], -s * FIELD[0] + c * FIELD[1], FIELD[2]])
    return q, m


def test_bad_samples_time_gaps_and_unseen():
    # GIVEN a platform filter fusing at 50 Hz, WHEN it gets a NaN gyro, a NaN quaternion, a NaN time, a
    # NaN magnetometer, the same time again, an earlier time, a gap beyond max_dt_s, an unseen interval
    # and a clock restarting lower, and params changed, THEN the core and the reference agree at each
    p = PolarHeadingParams()
    r = Replay("edge")
    r.init(params=p)
    t = 0.0
    for _ in range(60):
        q, m = _turning(t)
        r.step(_u(t, m, q, w=(0.0, 0.0, 0.2)), p)
        t += 0.02
    r.step(_u(t, w=(math.nan, 0.0, 0.0)), p)
    r.step(_u(t, q=(math.nan, 0.0, 0.0, 1.0)), p)
    r.step(_u(math.nan), p)
    r.step(_u(t, mag=(0.1, math.inf, 0.4)), p)
    r.step(_u(t - 0.02), p)                      # dt = 0
    r.step(_u(t - 0.5), p)                       # time going back
    t += 0.5                                     # a gap: not integrated, widened as unseen
    for _ in range(30):
        q, m = _turning(t)
        r.step(_u(t, m, q, w=(0.0, 0.0, 0.2)), p)
        t += 0.02
    r.unseen(3.0, p)                             # an FC clock restart
    t = 2.0
    p2 = dataclasses.replace(p, mag_error_turn_rad=0.0, consider_floor_fraction=0.5, mag_noise_gauss=0.004)
    for _ in range(40):
        q, m = _turning(t)
        r.step(_u(t, m, q, w=(0.0, 0.0, 0.2), mag_residual_sigma_gauss=0.006), p2)
        t += 0.02
    assert {"non-finite input", "non-finite magnetometer", "time not increasing", "fused", "gap", "unseen"} <= \
        set(r.kinds), r.kinds


def test_euler_formulation_pitch_field_and_reset():
    # GIVEN the Euler formulation (no q_P_from_body) seeded with a heading and a bias prior, WHEN the
    # pitch goes beyond max_abs_pitch_rad, the horizontal field is too weak, and the magnetometer is
    # turned 60 deg for longer than reset_after_s (rejections, then the reset), THEN equal
    p = PolarHeadingParams(reset_after_s=2.0)
    r = Replay("euler")
    r.init(0.2, math.radians(5.0), p, (0.001, -0.002))
    t = 0.0
    for k in range(40):
        r.step(_u(t, q=None, roll=0.1, pitch=0.05, w=(0.01, 0.02, 0.03)), p)
        t += 0.02
    for k in range(10):
        r.step(_u(t, q=None, pitch=math.radians(87.0)), p)
        t += 0.02
    for k in range(10):
        r.step(_u(t, mag=(0.001, 0.002, 0.5), q=None), p)
        t += 0.02
    c, s = math.cos(1.0), math.sin(1.0)
    turned = np.array([c * FIELD[0] - s * FIELD[1], s * FIELD[0] + c * FIELD[1], FIELD[2]])
    for k in range(200):
        r.step(_u(t, mag=turned, q=None), p)
        t += 0.02
    r.step(_u(t, q=None, roll=math.nan), p)
    assert {"pitch beyond max_abs_pitch_rad", "horizontal field", "innovation gated out", "reset", "euler"} <= \
        set(r.kinds), r.kinds


def test_platform_switch_withheld_and_levelled_with_roll_pitch():
    # GIVEN an Euler-formulation filter with a heading, WHEN the attitude filter's attitude comes (the
    # switch to the platform formulation keeps the heading), the magnetometer is disturbed (rejections),
    # withheld for 2 s (its rejections start over), levels with a given roll/pitch (and a NaN one),
    # THEN equal
    p = PolarHeadingParams()
    r = Replay("switch")
    r.init(params=p)
    t = 0.0
    for _ in range(20):
        r.step(_u(t, q=None, roll=0.02, pitch=-0.03), p)
        t += 0.02
    q_tilt = np.array([0.999, 0.03, -0.02, 0.1])
    for _ in range(20):
        r.step(_u(t, q=q_tilt), p)
        t += 0.02
    for _ in range(30):
        r.step(_u(t, mag=FIELD + np.array([0.25, -0.2, 0.0]), q=q_tilt), p)
        t += 0.02
    for _ in range(100):
        r.step(_u(t, mag=None, q=q_tilt), p)
        t += 0.02
    for _ in range(20):
        r.step(_u(t, q=q_tilt, roll=0.05, pitch=-0.04, level_with_roll_pitch=True), p)
        t += 0.02
    r.step(_u(t, q=q_tilt, roll=math.nan, level_with_roll_pitch=True), p)
    assert {"innovation gated out", "fused", "non-finite input", "platform", "euler"} <= set(r.kinds), r.kinds


def test_field_mismatch_alike_in_both_formulations():
    # GIVEN the model's field given with the magnetometer (C's field-mismatch consider term: a running
    # mean over the measurements that enter the heading), WHEN a platform filter turns with a field
    # 0.03 G off the model, goes through a gap, an FC clock restart, steps without the model (the mean
    # forgotten) and with it again, and an Euler filter is reset on a turned field, THEN equal at each
    model = FIELD + np.array([0.03, -0.01, -0.03])
    p = PolarHeadingParams(reset_after_s=2.0)
    r = Replay("mismatch")
    r.init(params=p)
    t = 0.0
    for k in range(80):
        q, m = _turning(t)
        r.step(_u(t, m, q, w=(0.0, 0.0, 0.2), field_model_ned_gauss=model), p)
        t += 0.02
    t += 0.5                                     # a gap: widened as unseen, the mean's clock restarts
    for k in range(20):
        q, m = _turning(t)
        r.step(_u(t, m, q, w=(0.0, 0.0, 0.2), field_model_ned_gauss=model), p)
        t += 0.02
    r.unseen(2.0, p)
    t = 1.0
    for k in range(20):
        q, m = _turning(t)
        r.step(_u(t, m, q, w=(0.0, 0.0, 0.2), field_model_ned_gauss=model if k >= 10 else None), p)
        t += 0.02
    assert r.ref.field_mismatch_gauss2 is not None and r.ref.field_mismatch_gauss2 > 1e-4
    e = Replay("mismatch-euler")
    e.init(0.2, math.radians(5.0), p)
    c, s_ = math.cos(1.0), math.sin(1.0)
    turned = np.array([c * FIELD[0] - s_ * FIELD[1], s_ * FIELD[0] + c * FIELD[1], FIELD[2]])
    t = 0.0
    for k in range(200):
        e.step(_u(t, mag=FIELD if k < 50 else turned, q=None, roll=0.1, pitch=-0.05, field_model_ned_gauss=model), p)
        t += 0.02
    assert {"fused", "gap", "unseen", "platform"} <= set(r.kinds) and {"fused", "reset", "euler"} <= set(e.kinds), \
        (r.kinds, e.kinds)
    # a state saved before these fields existed loads (None: no mean yet) into the core as into the reference
    d = {k: v for k, v in dataclasses.asdict(r.ref).items() if k not in ("field_mismatch_gauss2", "field_mismatch_time_s")}
    old = ref.PolarHeadingState(**d)
    held = core.HeldPolarHeading(core._core.PolarHeading(d))
    assert held.field_mismatch_gauss2 is None and held.field_mismatch_time_s is None
    assert not _state_differences(old, held.to_state(), "old")


def test_declination_and_residual_refused_alike():
    # a magnetometer sample with a NaN declination, a negative or NaN residual sigma: the core raises the
    # reference's ValueError and its held state is the one before the call
    p = PolarHeadingParams()
    for bad in (dict(decl=math.nan), dict(mag_residual_sigma_gauss=-1.0), dict(mag_residual_sigma_gauss=math.nan),
                dict(mag_residual_sigma_gauss=np.float64(-0.5)), dict(q=None, decl=math.inf),
                dict(q=None, mag_residual_sigma_gauss=-2.0), dict(field_model_ned_gauss=(0.2, math.nan, 0.4)),
                dict(q=None, field_model_ned_gauss=np.array([math.inf, 0.0, 0.4])),
                dict(field_model_ned_gauss=np.zeros(3))):
        r = Replay("refused")
        r.init(params=p)
        for k in range(10):
            r.step(_u(0.02 * k, q=None if "q" in bad else Q_LEVEL), p)
        before = r.core.to_state()
        u = _u(0.2 + 0.1, **bad)
        with pytest.raises(ValueError) as e_ref:
            ref.polar_heading_step(r.ref, u, p)
        with pytest.raises(ValueError) as e_core:
            core.polar_heading_step(r.core, u, p)
        assert str(e_core.value) == str(e_ref.value)
        assert not _state_differences(before, r.core.to_state(), "before")


def test_bad_shapes_answered_by_the_reference():
    # inputs of shapes the filter does not take: the reference answers them on the held record (a
    # reason, or its exception), the core's state after it is the reference's
    p = PolarHeadingParams()
    r = Replay("shapes")
    r.init(params=p)
    t = 0.0
    for _ in range(20):
        r.step(_u(t), p)
        t += 0.02
    for kw in (dict(w=(0.0, 0.0)), dict(q=(1.0, 0.0, 0.0)), dict(mag=(0.2, 0.0)), dict(q=(0.0, 0.0, 0.0, 0.0)),
               dict(cov_att_body_rad2=np.eye(2)), dict(q=None, cov_roll_pitch_rad2=np.eye(3) * 1e-5),
               dict(decl="east"), dict(mag_residual_sigma_gauss="small"), dict(q=None, roll=None),
               dict(field_model_ned_gauss=(0.2, 0.4)), dict(q=None, field_model_ned_gauss="wmm")):
        u = _u(t, **kw)
        try:
            with np.errstate(all="ignore"):
                want = ref.polar_heading_step(r.ref, u, p)
        except Exception as e_ref:  # noqa: BLE001 - the reference's own answer, whatever its type
            with pytest.raises(type(e_ref)) as e_core, np.errstate(all="ignore"):
                core.polar_heading_step(r.core, u, p)
            assert str(e_core.value) == str(e_ref)
            continue
        with np.errstate(all="ignore"):
            r.step(u, p)
        assert r.ref is want[0] or not _state_differences(want[0], r.ref, "again")
        t += 0.02


def test_arguments_refused_alike():
    p = PolarHeadingParams()
    for call in (lambda m: m.polar_heading_init(params=p, gyro_bias_yz_rad_s=(0.0, math.nan)),
                 lambda m: m.polar_heading_init(params=p, gyro_bias_yz_rad_s=(0.0, 0.0, 0.0)),
                 lambda m: m.polar_heading_init(1.0, None, p),
                 lambda m: m.polar_heading_init(math.inf, 0.1, p),
                 lambda m: m.polar_heading_init(1.0, -0.1, p),
                 lambda m: m.polar_heading_unseen(m.polar_heading_init(params=p), -1.0, p),
                 lambda m: m.polar_heading_unseen(m.polar_heading_init(params=p), math.nan, p)):
        with pytest.raises(ValueError) as e_ref:
            call(ref)
        with pytest.raises(ValueError) as e_core:
            call(core)
        assert str(e_core.value) == str(e_ref.value)
    # an attitude asked at a heading that is not a number: the reference's answer
    r = Replay("att")
    r.init(params=p)
    for k in range(5):
        r.step(_u(0.02 * k), p)
    with pytest.raises(ValueError) as e_ref:
        ref.polar_heading_attitude(r.ref, math.nan)
    with pytest.raises(ValueError) as e_core:
        core.polar_heading_attitude(r.core, math.nan)
    assert str(e_core.value) == str(e_ref.value)


def test_the_backend_selects_c_heading(monkeypatch, caplog):
    # GIVEN the core (the default), AZIMUTHD_CORE=python, and an extension built before C's heading was
    # ported WHEN the service selects THEN the heading filter runs in the core, in the reference, in the
    # reference with one warning line saying so (C's attitude filter still in the core)
    import logging

    from service import core_backend
    monkeypatch.setattr(core_backend, "_said", set())
    b = core_backend.select({})
    assert b.name == "core" and all(getattr(b, k) is getattr(core, k) for k in H_CALLS)
    py = core_backend.select({"AZIMUTHD_CORE": "python"})
    assert py.polar_heading_step is ref.polar_heading_step and py.heading_zero_rate_update is zr.heading_zero_rate_update
    monkeypatch.setattr(core, "POLAR_HEADING_AVAILABLE", False)
    with caplog.at_level(logging.WARNING, logger="azimuthd.core"):
        old = core_backend.select({})
        core_backend.select({})
    assert old.name == "core" and old.polar_attitude_step is core.polar_attitude_step
    assert old.polar_heading_step is ref.polar_heading_step and old.polar_heading_init is ref.polar_heading_init
    assert [r.getMessage() for r in caplog.records] == [
        "compiled core without method C's heading filter (an older build): it runs the Python reference"]


def test_the_replay_fails_on_a_small_difference():
    # the mutation check: the core given params 1e-6 relative off in one field (the magnetometer noise)
    # is caught within the first measurements; with the same params the same run passes
    p = PolarHeadingParams()
    calls = []
    t = 0.0
    for _ in range(40):
        q, m = _turning(t)
        calls.append(("polar_heading_step", (None, _u(t, m, q, w=(0.0, 0.0, 0.2)), p), {}))
        t += 0.02
    ok = Replay("same")
    ok.init(params=p)
    ok.run(calls)
    off = Replay("mutated", core_params=dataclasses.replace(p, mag_noise_gauss=p.mag_noise_gauss * (1.0 + 1e-6)))
    off.init(params=p)
    with pytest.raises(AssertionError):
        off.run(calls)
