"""The compiled core equals its Python reference (issue 19 item 2), on the same recorded flights:

- a simulated flight (sim.offline, any_motion_aerobatic at 400 Hz: rolls and loops, 94 deg/s);
- the real logs in ../shared/data read by the log readers (ArduCopter DataFlash, three PX4 ULogs;
  the 2.7 Hz ArduCopter tlog is left out: every sample of it is a gap, and its read costs 30 s).

Ported parts: the one gyro propagation (estimators/strapdown.py) and the rest accumulator
(estimators/levelling.py levelling_step), in both call forms (batch arrays and per sample), and a
run split in two through the state equals one unbroken run. Tolerance: 1e-9 relative per state
element (the build keeps the reference's IEEE operations, so they agree to the bit here)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from estimators import core
from estimators.levelling import LevellingState, levelling_step
from estimators.strapdown import StrapdownParams, StrapdownState, strapdown_init, strapdown_step

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")
REAL_LOGS = ("arducopter-rtl-midflight.bin", "px4-bench-sample.ulg", "px4-quad-no-gnss.ulg",
             "px4-vtol-airspeed-small.ulg")
RTOL = 1e-9
PARAMS = StrapdownParams(max_dt_s=0.1)


def close(a, b) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= RTOL * np.maximum(np.abs(a), np.abs(b))))


def _sim():
    from sim.offline import simulate
    run = simulate("any_motion_aerobatic", seed=1, imu_rate_hz=400.0, duration_s=30.0)
    return run.time_s, run.gyro_rad_s, run.accel_m_s2


def _log(name):
    from mavlink_io.samples import ImuSample
    from service.logreaders import open_log
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"{path} not present (the shared real logs)")
    t, g, a = [], [], []
    for it in open_log(path).items():
        if type(it) is ImuSample:
            t.append(it.time_fc_s)
            g.append(it.gyro_rad_s)
            a.append(it.accel_m_s2)
    return np.array(t), np.array(g, float), np.array(a, float)


_CACHE: dict = {}


@pytest.fixture(params=("sim",) + REAL_LOGS)
def flight(request):
    if request.param not in _CACHE:
        _CACHE[request.param] = _sim() if request.param == "sim" else _log(request.param)
    return request.param, *_CACHE[request.param]


def _bias(g):
    return np.mean(g[:200], axis=0)  # a bias-corrected rate, as the Pipeline propagates


def test_strapdown_core_equals_reference(flight):
    name, t, g, _ = flight
    w = g - _bias(g)
    start = strapdown_init(np.array([0.9, 0.1, -0.3, 0.2]))
    # GIVEN the reference sample by sample
    ref_q, ref_codes, st = np.empty((len(t), 4)), [], start
    for k in range(len(t)):
        st, d = strapdown_step(st, w[k], float(t[k]), PARAMS)
        ref_q[k] = st.q_ref_from_sensor
        ref_codes.append(d.reason)
    # WHEN the core runs the batch, the per-sample drop-in and the held state
    end, q, codes, _ = core.strapdown_propagate(start, w, t, PARAMS)
    per, held = start, start
    for k in range(len(t)):
        per, d1 = core.strapdown_step(per, w[k], float(t[k]), PARAMS)
        held, d2 = core.strapdown_step_held(held, w[k], float(t[k]), PARAMS)
        assert d1.reason == d2.reason == ref_codes[k], k
    # THEN every attitude, every verdict and the final state agree
    assert close(q, ref_q), f"{name}: max |dq| {np.abs(q - ref_q).max():.3e}"
    assert [core.strapdown_reason(c, 0.0) if c < core.TIME_NOT_INCREASING else "x" for c in codes] == \
        [r if not r.startswith(("time", "gap")) else "x" for r in ref_codes]
    for s in (end, per, held):
        assert close(s.q_ref_from_sensor, st.q_ref_from_sensor) and s.time_s == st.time_s
        assert close(s.gyro_prev_rad_s, st.gyro_prev_rad_s)
    n_int = int(np.sum(codes == core.INTEGRATED))
    assert n_int > 0.99 * len(t) - 2, f"{name}: only {n_int} of {len(t)} integrated"


def test_strapdown_split_run_equals_unbroken(flight):
    # GIVEN a run cut in two WHEN the second half starts from the first half's state THEN the
    # same attitudes as one unbroken run (the state carries everything: VQF's setState test)
    _, t, g, _ = flight
    start = strapdown_init(np.array([1.0, 0.0, 0.0, 0.0]))
    _, q_all, _, _ = core.strapdown_propagate(start, g, t, PARAMS)
    half = len(t) // 2
    mid, q1, _, _ = core.strapdown_propagate(start, g[:half], t[:half], PARAMS)
    resumed = StrapdownState(mid.q_ref_from_sensor.copy(), mid.time_s, mid.gyro_prev_rad_s.copy())
    _, q2, _, _ = core.strapdown_propagate(resumed, g[half:], t[half:], PARAMS)
    assert np.array_equal(np.vstack([q1, q2]), q_all)


def _lev_equal(x: LevellingState, y: LevellingState) -> bool:
    if (x.n, x.t_first_s, x.t_last_s, x.nb) != (y.n, y.t_first_s, y.t_last_s, y.nb):
        return False
    if len(x.batch) != len(y.batch) or len(x.batch_stats) != len(y.batch_stats):
        return False
    if x.batch and (x.batch[:2] != y.batch[:2] or not close(x.batch[2] + x.batch[3], y.batch[2] + y.batch[3])):
        return False
    if x.batch_stats and not close(np.ravel(x.batch_stats), np.ravel(y.batch_stats)):
        return False
    return all(close(getattr(x, f), getattr(y, f)) for f in
               ("accel_mean_m_s2", "accel_m2", "gyro_mean_rad_s", "gyro_m2"))


@pytest.mark.parametrize("timed", (True, False))
def test_levelling_core_equals_reference(flight, timed):
    name, t, g, a = flight
    times = t if timed else None
    # GIVEN the reference sample by sample over the whole flight (rest and motion alike)
    ref = LevellingState()
    for k in range(len(t)):
        ref = levelling_step(ref, g[k], a[k], float(t[k]) if timed else None)
    # WHEN the core accumulates the batch, in two halves, and per sample
    batch, used = core.levelling_accumulate(LevellingState(), g, a, times)
    half = len(t) // 2
    h1, _ = core.levelling_accumulate(LevellingState(), g[:half], a[:half], None if times is None else t[:half])
    h2, _ = core.levelling_accumulate(h1, g[half:], a[half:], None if times is None else t[half:])
    # THEN the same sums, means, batches and times
    assert used.all() and ref.n == len(t)
    for s in (batch, h2):
        assert _lev_equal(s, ref), name
    assert (ref.nb > 4) == timed


def test_levelling_skips_what_the_reference_skips():
    # GIVEN samples with NaN/inf in either sensor and a NaN time THEN the same skips and state
    rng = np.random.default_rng(7)
    g, a = rng.normal(0, 0.01, (50, 3)), np.array([0, 0, -9.8]) + rng.normal(0, 0.1, (50, 3))
    g[5, 1], a[9, 2], g[20, 0] = math.nan, math.inf, -math.inf
    t = np.arange(50) * 0.1
    t[30] = math.nan  # untimed sample in a timed run: counted, not batched
    ref = LevellingState()
    for k in range(50):
        ref = levelling_step(ref, g[k], a[k], float(t[k]))
    got, used = core.levelling_accumulate(LevellingState(), g, a, t)
    per = LevellingState()
    for k in range(50):  # the per-sample drop-in too
        per = core.levelling_step(per, g[k], a[k], float(t[k]))
    assert _lev_equal(got, ref) and _lev_equal(per, ref) and ref.n == 47
    assert np.flatnonzero(~used).tolist() == [5, 9, 20]


def test_strapdown_verdicts_match_on_bad_samples():
    # GIVEN a first sample, a NaN rate, time going back, a gap THEN the reference's verdicts and dt
    w = np.array([[0.1, 0.0, 0.0], [math.nan, 0, 0], [0.1, 0.2, 0.0], [0.2, 0.2, 0.0], [0.0, 0.1, 0.0],
                  [0.3, 0.0, 0.1], [0.3, 0.0, 0.1]])
    t = np.array([0.0, 0.01, 0.01, 0.01, 0.005, 0.5, 0.51])
    st, ref = strapdown_init(np.array([1.0, 0, 0, 0])), []
    for k in range(len(t)):
        st, d = strapdown_step(st, w[k], float(t[k]), PARAMS)
        ref.append((d.integrated, d.reason, d.dt_s))
    held, got = strapdown_init(np.array([1.0, 0, 0, 0])), []
    for k in range(len(t)):
        held, d = core.strapdown_step_held(held, w[k], float(t[k]), PARAMS)
        got.append((d.integrated, d.reason, d.dt_s))
    assert got == ref
    assert [r[1] for r in ref] == ["first sample", "non-finite sample", "", "time not increasing (dt=0.000000 s)",
                                   "time not increasing (dt=-0.005000 s)", "gap of 0.490 s not integrated", ""]
    assert np.array_equal(held.q_ref_from_sensor, st.q_ref_from_sensor)
