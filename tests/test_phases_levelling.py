"""Levelling that does not need a perfectly still block (estimators/levelling.py, service/phases.py).

GIVEN blocks of IMU samples (seeded), WHEN they are levelled THEN a stationary vehicle whose
accelerometer vibrates at the blade-pass frequency levels on the mean (its standard error, not its
raw std, is judged), at 25 Hz as at 200 Hz; a slow tilt drift or a handled vehicle does not; a
rate below what levelling needs says so with the rate; a vibrating stream whose 2 s blocks are
each too noisy levels on the merged longer window; and the quietest window is the one kept.
"""
import math

import numpy as np

from estimators.levelling import (LevellingParams, LevellingState, levelling_merge, levelling_result,
                                  levelling_step)
from service.phases import PhaseParams, PhaseState, phase_step

G = 9.80665
ROLL, PITCH = math.radians(3.0), math.radians(-2.0)
F_REST = np.array([G * math.sin(PITCH), -G * math.cos(PITCH) * math.sin(ROLL), -G * math.cos(PITCH) * math.cos(ROLL)])
BIAS = np.array([0.002, -0.001, 0.0015])
LP = LevellingParams(min_samples=20)


def vibrating(rng, t, accel_rms, gyro_rms=0.0, freq_hz=137.0):
    """Gyro and accel samples at times t: at rest + a sinusoidal vibration per axis + white noise."""
    ph = rng.uniform(0, 2 * math.pi, 3)
    s = np.sqrt(2) * np.sin(2 * math.pi * freq_hz * t[:, None] + ph)
    accel = F_REST + accel_rms * s + rng.normal(0, 0.02, (len(t), 3))
    gyro = BIAS + gyro_rms * s[:, ::-1] + rng.normal(0, 1e-3, (len(t), 3))
    return gyro, accel


def level(t, gyro, accel, params=LP):
    st = LevellingState()
    for k in range(len(t)):
        st = levelling_step(st, gyro[k], accel[k], float(t[k]))
    return st, levelling_result(st, params)


def test_vibrating_but_stationary_levels_on_the_mean_at_200_and_25_hz():
    rng = np.random.default_rng(11)
    for rate in (200.0, 25.0):
        t = np.arange(0, 4.0, 1 / rate)
        _, res = level(t, *vibrating(rng, t, accel_rms=0.8 if rate == 200 else 0.3, gyro_rms=0.005))
        assert res.ok, (rate, res.reason)
        # the error is within 3 sigma of the noise of the mean (the bias allowance is not in this data)
        assert abs(res.roll_rad - ROLL) < 3 * res.tilt_noise_rad + 1e-4
        assert abs(res.pitch_rad - PITCH) < 3 * res.tilt_noise_rad + 1e-4
        assert res.accel_std_m_s2 > 0.25 and "Hz over" in res.figures()


def test_a_slow_tilt_drift_fails_on_the_batch_means():
    """The tilt drifts 8 deg in 2 s (std 0.4 m/s^2 per sample): white-noise statistics of the mean
    would pass it (tilt noise 0.1 deg), the batch means show it (0.8 deg > 0.5 deg)."""
    t = np.arange(0, 2.0, 0.005)
    drift = np.radians(8.0) * t / 2.0
    accel = np.stack([np.zeros_like(t), -G * np.sin(drift), -G * np.cos(drift)], 1)
    gyro = np.tile(BIAS, (len(t), 1))
    _, res = level(t, gyro, accel)
    assert not res.ok and "tilt noise" in res.reason and res.noisy
    # the same samples without their times (no batches) would have passed: the drift is the point
    st = LevellingState()
    for k in range(len(t)):
        st = levelling_step(st, gyro[k], accel[k])
    assert levelling_result(st, LP).ok


def test_too_few_samples_says_the_rate():
    t = np.arange(0, 2.0, 1.0)  # 1 Hz
    _, res = level(t, np.tile(BIAS, (len(t), 1)), np.tile(F_REST, (len(t), 1)))
    assert not res.ok and res.reason == "2 of 20 still samples in 1.0 s (2 Hz)"


def test_merged_blocks_equal_one_long_block():
    rng = np.random.default_rng(3)
    t = np.arange(0, 4.0, 0.02)
    gyro, accel = vibrating(rng, t, 0.8, 0.01)
    whole, _ = level(t, gyro, accel)
    a, _ = level(t[:100], gyro[:100], accel[:100])
    b, _ = level(t[100:], gyro[100:], accel[100:])
    m = levelling_merge(a, b)
    assert m.n == whole.n
    np.testing.assert_allclose(m.accel_mean_m_s2, whole.accel_mean_m_s2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.accel_m2, whole.accel_m2, rtol=1e-10)
    np.testing.assert_allclose(m.gyro_m2, whole.gyro_m2, rtol=1e-10)


def run_phases(t, gyro, accel, params=PhaseParams(levelling=LP), evidence=None):
    st, events = PhaseState(), []
    for k in range(len(t)):
        st, ev = phase_step(st, gyro[k], accel[k], float(t[k]), params, evidence)
        events += [(float(t[k]), *e) for e in ev]
    return st, events


def test_a_vibrating_25_hz_stream_levels_on_the_longer_window():
    """GIVEN 25 Hz samples with 0.8 m/s^2 rms vibration from the first sample (a log that starts
    with the motors running) WHEN the phases cut 2 s blocks THEN each block is too noisy alone
    (tilt noise > 0.5 deg), the merged window levels, and its tilt is right."""
    rng = np.random.default_rng(5)
    t = np.arange(0, 12.0, 0.04)
    st, ev = run_phases(t, *vibrating(rng, t, 0.8, 0.005))
    not_still = [d for _t, k, d in ev if k == "not_still"]
    assert not_still and all("tilt noise" in d for d in not_still)
    t_lev = next(tt for tt, k, _d in ev if k == "levelled")
    assert t_lev <= 8.01 and st.level.duration_s > 3.9
    assert abs(st.level.roll_rad - ROLL) < math.radians(0.5) and abs(st.level.pitch_rad - PITCH) < math.radians(0.5)
    assert not st.started_in_flight


def test_the_quietest_window_is_kept_and_a_moved_vehicle_relevels():
    """GIVEN a quiet block, then the motors spin up (vibrating blocks at the same attitude), then
    the vehicle is set down at another tilt WHEN the phases run THEN the quiet block's levelling
    is kept through the vibration, and the new tilt replaces it."""
    rng = np.random.default_rng(8)
    t = np.arange(0, 10.0, 0.005)
    gyro, accel = vibrating(rng, t, 0.0)
    gv, av = vibrating(rng, t, 0.6, 0.005)
    spin = t >= 2.5
    gyro[spin], accel[spin] = gv[spin], av[spin]
    st, _ = run_phases(t, gyro, accel)
    assert st.level is not None and st.level_time_s < 2.5 and st.level.accel_std_m_s2 < 0.1
    tilt = math.radians(4.0)
    moved = t >= 6.0
    c, s_ = math.cos(tilt), math.sin(tilt)
    R = np.array([[1, 0, 0], [0, c, -s_], [0, s_, c]])
    accel[moved] = accel[moved] @ R.T
    st, ev = run_phases(t, gyro, accel)
    assert st.level_time_s > 6.0 and any(k == "levelled" and "tilt changed by 4.0" in d for _t, k, d in ev)
