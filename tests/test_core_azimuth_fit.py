"""Method A's re-solve in the compiled core equals its Python reference (issue 19 item 2):
estimators/azimuth_fit.py fit_psi (profile scan, Gauss-Newton, sandwich covariance, consider
sensitivity, the joint MAP of the gyro errors and the levelling tilt) against core/azimuth_fit.hpp
through estimators/core.py fit_psi.

GIVEN the states method A held at each re-solve of two simulated launcher flights through the daemon's
Pipeline (bench/azimuth_accuracy.py's flights: one with a clean magnetometer, two with hard and soft
iron and a launch-site distortion) and of the real logs in /work/shared/data replayed with launch.case
aligned (of those, only px4-quad-no-gnss.ulg gives A a levelled take-off; skipped cleanly when absent),
WHEN the reference and the core solve the same state (estimators/azimuth.py azimuth_solve),
THEN what the solve produced (the FitResult: psi, theta, the covariances, S, c_hat, P_psi_c, the gate
sigma, the condition number, the iteration count; the gate's reason; the Solution) is equal to 1e-9
relative (tests/parity_compare.py; covariances per element against sqrt(P_ii P_jj)), strings identical,
wherever the reference reproduces itself to 1e-10 (every accepted solution); on the ill-conditioned
solves the gate rejects, to 10x the reference's own difference on the same samples reversed;
AND on the edge cases both must agree on: too few samples, a NaN sample (a named reason, not a
LinAlgError), a singular normal matrix (all samples at one attitude: the distortion unobservable,
the pseudo-inverse branch), an ill-conditioned one, a solve stopped before it converged (1 and 2
iterations) and a wrong P_prior shape (the same ValueError).
"""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from estimators import azimuth as az
from estimators import azimuth_fit as af
from estimators import core
from tests.parity_compare import differences

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

DATA = Path("/work/shared/data")
pytestmark = pytest.mark.skipif(not core.FIT_AVAILABLE,
                                reason=f"compiled core without method A's re-solve: {core.IMPORT_ERROR or 'old build'}")


def _both(data, C_isf_af, e, model, **kw):
    a = af.fit_psi(data, C_isf_af, e, model, **kw)
    b = core.fit_psi(data, C_isf_af, e, model, **kw)
    assert differences(a, b) == [], differences(a, b)
    return a, b


def _synthetic(N=300, seed=1, model_err=True, turn=True):
    """Samples of a turning sensor in a distorted field (hard + soft iron), with a K = 12 G."""
    from estimators.rotations import rot_x, rot_y, rot_z
    rng = np.random.default_rng(seed)
    k = np.arange(N)
    C = np.array([rot_z(0.02 * i * turn) @ rot_x(0.01 * i * turn) @ rot_y(0.3 * math.sin(0.03 * i) * turn) for i in k])
    e = np.array([0.21, 0.01, 0.43])
    Cia = af.C_isf_from_af(0.04, -0.03)
    A = np.eye(3) + (rng.normal(0, 0.05, (3, 3)) if model_err else 0.0)
    b = np.array([0.05, -0.02, 0.03]) if model_err else np.zeros(3)
    h = np.einsum("nij,j->ni", C @ Cia, af.r3(1.3) @ e) @ A.T + b + rng.normal(0, 0.003, (N, 3))
    var_white = 9e-6 + k * 1e-9
    w = 1.0 / (var_white + (k * 2e-4) ** 2 * 1e-3)
    G = rng.normal(0, 1, (N, 3, 12)) * k[:, None, None] * 0.01
    P = np.diag(np.r_[np.full(3, 1e-8), np.full(9, 1e-5), np.full(2, 1e-4)])
    return af.FitData(C, h, var_white, w, G), Cia, e, P


@pytest.mark.parametrize("model", af.MODELS)
@pytest.mark.parametrize("estimate", [False, True])
def test_synthetic_samples_equal(model, estimate):
    data, Cia, e, P = _synthetic()
    a, _ = _both(data, Cia, e, model, P_prior=P, estimate_errors=estimate)
    assert a.ok and a.iterations >= 1 and np.all(np.isfinite(a.P_psi_c))
    _both(data, Cia, e, model, P_prior=None, estimate_errors=estimate)       # no prior: consider only
    _both(af.FitData(data.C_sf_from_isf, data.h_sf_gauss, data.var_white_gauss2, data.weight), Cia, e, model,
          estimate_errors=estimate)                                         # K = 0


def _at_own_floor(data, Cia, e, model, **kw):
    """Reference and core on the same samples, compared at max(1e-9, 10 x the reference's own difference
    when given them reversed); (reference, core, that own difference)."""
    a = af.fit_psi(data, Cia, e, model, **kw)
    b = core.fit_psi(data, Cia, e, model, **kw)
    own = _floor(a, _reversed_reference(data, Cia, e, model, **kw))
    if math.isinf(own):   # not even 10x apart: unobservable; both must say so (the gate then rejects both)
        limit = af.GateParams().max_condition_number
        assert a.ok == b.ok and a.condition_number > limit and b.condition_number > limit, model
        return a, b, own
    rtol = max(1e-9, 10.0 * own)
    assert differences(a, b, rtol=rtol) == [], (model, own, differences(a, b, rtol=rtol)[:3])
    return a, b, own


def test_edge_cases_agree():
    data, Cia, e, P = _synthetic(N=60)
    few = af.FitData(*(x[:2] for x in (data.C_sf_from_isf, data.h_sf_gauss, data.var_white_gauss2, data.weight,
                                       data.G_gyro)))
    for model, n in (("none", 0), ("seed7", 2), ("full12", 2), ("full12", 4)):
        sub = af.FitData(*(x[:n] for x in (data.C_sf_from_isf, data.h_sf_gauss, data.var_white_gauss2, data.weight,
                                           data.G_gyro)))
        a, _ = _both(sub, Cia, e, model, P_prior=P, estimate_errors=True)
        assert not a.ok and "equations for" in a.reason
    assert not _both(few, Cia, e, "full12")[0].ok
    # a NaN sample: a named reason in both (the reference raised a LinAlgError from its SVD before)
    h = data.h_sf_gauss.copy()
    h[7, 1] = math.nan
    for model in af.MODELS:
        a, _ = _both(af.FitData(data.C_sf_from_isf, h, data.var_white_gauss2, data.weight, data.G_gyro), Cia, e,
                     model, P_prior=P, estimate_errors=True)
        assert not a.ok and a.reason == "1 of 60 samples not finite"
    # singular: one attitude throughout, so the distortion unknowns are not observable; ill-conditioned:
    # small sweeps. Compared at the reference's own reproducibility (see _floor below); the gate
    # (max_condition_number 1e4) rejects both wherever the problem is worse than that
    from estimators.rotations import rot_x, rot_z
    one, _, _, _ = _synthetic(N=120, turn=False)
    gate = af.GateParams()
    for sweep, model in [(0.0, "seed7"), (0.0, "full12"), (0.05, "full12"), (0.1, "full12"), (0.2, "full12"),
                         (0.02, "seed7")]:
        C = np.array([rot_z(sweep * math.sin(0.05 * i)) @ rot_x(0.3 * sweep * math.cos(0.07 * i)) for i in range(120)])
        d = af.FitData(C, one.h_sf_gauss, one.var_white_gauss2, one.weight, one.G_gyro)
        for est in (False, True):
            a, b, own = _at_own_floor(d, Cia, e, model, P_prior=P, estimate_errors=est)
            assert a.ok and b.ok
            if sweep == 0.0:
                assert a.condition_number > gate.max_condition_number < b.condition_number
            if model == "full12" and sweep <= 0.05:   # unobservable / badly conditioned: the gate rejects it
                assert a.condition_number > gate.max_condition_number and own >= 1e-8
    # stopped before convergence: the same iterate after 1 and 2 Gauss-Newton steps
    for it in (1, 2):
        a, b, _ = _at_own_floor(data, Cia, e, "full12", P_prior=P, max_iterations=it, estimate_errors=False)
        assert a.iterations == b.iterations == it
    with pytest.raises(ValueError, match="P_prior must be 14x14"):
        af.fit_psi(data, Cia, e, "seed7", P_prior=np.eye(3))
    with pytest.raises(ValueError, match="P_prior must be 14x14"):
        core.fit_psi(data, Cia, e, "seed7", P_prior=np.eye(3))
    with pytest.raises(ValueError):
        core.fit_psi(af.FitData(data.C_sf_from_isf[:5], data.h_sf_gauss, data.var_white_gauss2, data.weight), Cia,
                     e, "seed7")


# --- the states method A re-solved on in flights --------------------------------------------------
# A least-squares solve is only as reproducible as its conditioning allows: the reference itself, given
# the same samples in reverse order (the same problem), moves by ~eps cond(H) (0 to 1e-12 on the
# well-posed solves, up to the whole answer on the unobservable early ones, which the gate rejects).
# So each solve is compared at max(1e-9, 10 x the reference's own reversal difference): 1e-9 wherever
# the reference reproduces itself to 1e-10, and every accepted solution of these flights does.

def _reversed_reference(data, *args, **kw):
    r = np.arange(len(data.h_sf_gauss))[::-1]
    return af.fit_psi(af.FitData(data.C_sf_from_isf[r], data.h_sf_gauss[r], data.var_white_gauss2[r],
                                 data.weight[r], None if data.G_gyro is None else data.G_gyro[r]), *args, **kw)


_DECADES = [10.0 ** k for k in range(-12, 2)]


def _floor(a, b) -> float:
    """The smallest decade rtol at which ``a`` and ``b`` compare equal (inf: a string differs)."""
    return next((r for r in _DECADES if not differences(a, b, rtol=r)), math.inf)


def _masked(reason: str) -> str:
    import re
    return re.sub(r"[-+0-9.e]+", "#", reason)


def _recorded_states(fly, every: int = 2) -> list:
    """(state, time) of every ``every``-th re-solve with enough samples to fit that the Pipeline handed
    its solver in ``fly(solver class)``, and the last one."""
    from service.solver import InlineSolver
    seen = []

    class Recording(InlineSolver):
        def submit(self, state, time_s, *kernels):
            if len(state.samples) >= state.params.gate.min_samples:
                seen.append((state, time_s))
            return super().submit(state, time_s, *kernels)

    fly(Recording)
    return seen[::every] + seen[-1:] if seen else []


def _same_solves(states) -> tuple[int, int]:
    """Each state solved by the reference and by the core; (solves compared at 1e-9, accepted solves)."""
    at_rtol = accepted = 0
    for st, t in states:
        a = az.azimuth_solve_result(az.azimuth_solve(st, t))
        b = az.azimuth_solve_result(az.azimuth_solve(st, t, core.fit_psi, core.orientation_diversity_rad))
        own = _floor(a, az.azimuth_solve_result(az.azimuth_solve(st, t, _reversed_reference)))
        if math.isinf(own):   # unobservable: the reference's own verdict text moves with the sample order
            assert (a["last_fit"].ok, _masked(a["last_gate_reason"])) == (b["last_fit"].ok,
                                                                         _masked(b["last_gate_reason"])), t
            assert a["last_gate_reason"] != "" and b["last_gate_reason"] != ""
            continue
        rtol = max(1e-9, 10.0 * own)
        if rtol > 1e-9 and a["last_fit"] is not None and abs(a["last_fit"].iterations - b["last_fit"].iterations) == 1:
            # ill-conditioned: whether the last Gauss-Newton step falls under the 1e-12 rad stop is rounding
            b = {**b, "last_fit": dataclasses.replace(b["last_fit"], iterations=a["last_fit"].iterations)}
        assert differences(a, b, rtol=rtol) == [], (t, rtol, differences(a, b, rtol=rtol)[:3])
        at_rtol += rtol == 1e-9
        if a["last_gate_reason"] == "":
            accepted += 1
            assert rtol == 1e-9, (t, own)
    return at_rtol, accepted


def _accuracy_flight(case: str, seed: int, clean: bool):
    """One of bench/azimuth_accuracy.py's flights (climb, two banked turns, level; hard and soft iron and a
    launch-site distortion) through the daemon's Pipeline as its operator configures it; ``clean``: an
    undistorted magnetometer."""
    import azimuth_accuracy as aa
    from service.pipeline import Pipeline
    from sim.offline import simulate
    from sitl import feed_pipeline, pipeline_inputs
    rng = np.random.default_rng(10_000 * aa.CASES.index(case) + seed)
    scenario, ov = aa.flight_overrides(case, rng)
    if clean:
        ov["mag"] = {"hard_iron_gauss": [0.0, 0.0, 0.0], "soft_iron": np.eye(3).tolist(),
                     "site_distortion_ned_gauss": [0.0, 0.0, 0.0]}
    run = simulate(scenario, seed=seed, imu_grade="consumer", imu_rate_hz=100.0, duration_s=aa.REST_S + aa.WINDOW_S,
                   overrides=ov)
    cfg = aa.operator_config(case, ov, run.site, "full12", 100.0)

    def fly(solver_cls):
        for _ in feed_pipeline(Pipeline(cfg, solver=solver_cls()), pipeline_inputs(run)):
            pass
    return fly


@pytest.mark.parametrize("case,seed,clean", [("inclined", 1, True), ("inclined", 2, False), ("aligned", 3, False)])
def test_simulated_flight_solves_equal(case, seed, clean):
    states = _recorded_states(_accuracy_flight(case, seed, clean))
    assert len(states) > 10
    at_rtol, accepted = _same_solves(states)
    assert accepted >= 5, "the comparison must see accepted solutions, not only rejections"
    assert at_rtol >= len(states) // 2


@pytest.mark.parametrize("log", ["px4-vtol-airspeed-small.ulg", "arducopter-rtl-midflight.bin",
                                 "px4-quad-no-gnss.ulg", "arducopter-flight.tlog"])
def test_real_log_solves_equal(monkeypatch, log):
    path = DATA / log
    if not path.is_file():
        pytest.skip(f"{path} not present (the shared real logs)")
    from types import SimpleNamespace

    import service.solver as solver_mod
    from service.logreaders import open_log
    from service.replay import build_config, run_replay
    src = open_log(path)
    cfg, _ = build_config(SimpleNamespace(config=None, site="47.37,8.54", exclude_fc_yaw=False), src)
    cfg["launch"]["case"] = "aligned"   # multicopter take-offs: the case that lets A run on them

    def fly(solver_cls):
        monkeypatch.setattr(solver_mod, "InlineSolver", solver_cls)
        run_replay(src, cfg, None)
    states = _recorded_states(fly, every=3)
    if not states:
        pytest.skip(f"{log}: method A never had samples to re-solve on it (no launch it could use)")
    _same_solves(states)


def test_orientation_diversity_equal():
    """The diversity the gate reads: the core's O(N^2) loop against the reference's N x N product."""
    data, Cia, e, _ = _synthetic(N=400)
    C = data.C_sf_from_isf @ Cia
    for n in (1, 2, 30, 400):
        for psi in (0.0, 1.3, 5.9):
            a, b = af.orientation_diversity_rad(C[:n], psi, e), core.orientation_diversity_rad(C[:n], psi, e)
            assert differences(a, b, "diversity_rad") == [], (n, psi, a, b)
    assert af.orientation_diversity_rad(C, 1.3, e) > math.radians(60.0)
    # one attitude throughout: 0 up to acos's resolution at 1 (sqrt(2 eps) = 2.1e-8 rad) in both
    one, _, _, _ = _synthetic(N=50, turn=False)
    C1 = one.C_sf_from_isf @ Cia
    assert af.orientation_diversity_rad(C1, 1.3, e) < 3e-8 and core.orientation_diversity_rad(C1, 1.3, e) < 3e-8
    # a NaN attitude: the reference's min is NaN, which max(-1, .) turns into -1: pi in both
    Cn = C[:10].copy()
    Cn[3, 0, 0] = math.nan
    assert af.orientation_diversity_rad(Cn, 1.3, e) == core.orientation_diversity_rad(Cn, 1.3, e) == math.pi
    with pytest.raises(ValueError):
        core.orientation_diversity_rad(C[:0], 1.3, e)
    with pytest.raises(ValueError):
        af.orientation_diversity_rad(C[:0], 1.3, e)
