"""Levelling and take-off for the vehicles people fly, through the daemon's own Pipeline.

GIVEN a simulated flight (sim/scenarios: a multicopter whose log starts at arming with the
propellers spinning, a VTOL, a hand launch, a runway take-off at ArduPlane's 50 Hz, a 25 Hz
stream), fed as decoded MAVLink samples with the FC's HEARTBEAT saying armed, WHEN the Pipeline
runs with ``[launch] vehicle`` set THEN it levels before the take-off, detects the take-off
within 2 s of the true one (the truth only scores), and method A runs, or says in one line why
not. The Pipeline never sees the truth.
"""
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import feed_pipeline  # noqa: E402

from mavlink_io.samples import FcAttitude, FcHeartbeat, ImuSample, PressureSample  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402


def fly(scenario, rate_hz, vehicle, case="aligned", duration_s=None, seed=2, overrides=None):
    """Simulate, feed everything to a Pipeline (HEARTBEAT armed at 1 Hz from the first sample).
    Returns (run, pipeline, [(time_s, kind, detail)])."""
    run = simulate(scenario, seed=seed, imu_rate_hz=rate_hz, duration_s=duration_s, overrides=overrides)
    items = [(t, 2, ImuSample(t, t, g.copy(), a.copy(), m.copy(), "RAW_IMU", 0))
             for t, g, a, m in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss)]
    items += [(t, 1, PressureSample(t, t, p, d, k)) for t, p, d, k in
              zip(run.baro_time_s.tolist(), run.press_abs_pa.tolist(), run.press_diff_pa.tolist(),
                  run.temperature_k.tolist())]
    items += [(t, 0, FcAttitude(t, t, float(e[0]), float(e[1]), float(math.remainder(e[2], 2 * math.pi)),
                                np.zeros(3))) for t, e in zip(run.fc_time_s.tolist(), run.fc_euler_rad)]
    # ArduPilot HEARTBEAT, armed (base_mode 129), MAV_STATE_STANDBY: says nothing about flying
    items += [(t, -1, FcHeartbeat(t, 1, 1, "ardupilot", 2, 129, 0, 3, True))
              for t in np.arange(0.0, run.time_s[-1], 1.0).tolist()]
    items.sort(key=lambda x: (x[0], x[1]))
    s = run.site
    p = Pipeline(validate({"site": {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"],
                                    "decimal_year": s["decimal_year"]},
                           "mavlink": {"imu_rate_hz": rate_hz},
                           "launch": {"vehicle": vehicle, "case": case},
                           "azimuth": {"solve_in_background": False}}))
    events = []
    for _ in feed_pipeline(p, [it for _t, _o, it in items], events, timed_events=True):
        pass
    return run, p, events


def first(events, kind):
    return next(((t, d) for t, k, d in events if k == kind), (None, None))


def kinds(events):
    return [k for _t, k, _d in events]


def test_multicopter_log_from_arming_levels_then_detects_the_lift_off():
    """GIVEN a multicopter log that starts at arming with the propellers spinning (0.8 m/s^2 rms
    vibration from the first sample, ArduPilot's 50 Hz) WHEN it takes off 6 s later THEN it
    levels before the lift-off on the vibrating data, the take-off is within 2 s of the true
    lift-off (measured: 0.1 s), it is not taken for a start in flight, and method A runs."""
    run, p, events = fly("multicopter_takeoff", 50.0, "multicopter", duration_s=9.0)
    t_lift = run.truth.launch_time_s
    t_level, level = first(events, "levelled")
    assert t_level is not None and t_level < t_lift, level
    assert "accel std 0.7" in level or "accel std 0.8" in level  # it levelled on vibrating data
    # the tilt is right to the accelerometer-bias allowance (the truth scores: level ground)
    assert abs(p.phase.level.roll_rad) < 3 * p.phase.level.roll_sigma_rad
    assert abs(p.phase.level.pitch_rad) < 3 * p.phase.level.pitch_sigma_rad
    _t, detail = first(events, "takeoff")
    assert "vertical specific force" in detail
    assert abs(p.phase.launch_time_s - t_lift) < 2.0 and abs(p.phase.launch_time_s - t_lift) < 0.3
    assert "started_in_flight" not in kinds(events)
    assert not p.azimuth_status().startswith(("not run", "failed", "disabled")), p.azimuth_status()


def test_vtol_at_25_hz_levels_and_detects_the_lift_off():
    """GIVEN a VTOL streamed at 25 Hz (a log that never had 200 samples in a 2 s block), quiet
    on the ground, then 8 s with its lift motors spinning WHEN it lifts off THEN it levelled on
    the 25 Hz data and the lift-off is detected within 2 s (measured: 0.04 s)."""
    run, p, events = fly("vtol_takeoff", 25.0, "vtol", duration_s=23.0)
    t_level, level = first(events, "levelled")
    assert t_level is not None and t_level < run.truth.launch_time_s and "(26 Hz over 2.0 s)" in level
    assert abs(p.phase.launch_time_s - run.truth.launch_time_s) < 0.3
    assert not p.azimuth_status().startswith(("not run", "failed", "disabled")), p.azimuth_status()


def test_runway_take_off_at_50_hz_levels_and_detects_the_roll():
    """GIVEN ArduPlane's 50 Hz and a runway take-off with the engine running for 6 s before the
    roll WHEN it rolls THEN it levelled before (not "started in flight", the old failure), the
    roll's start is the take-off within 2 s (bench/takeoff_phases.py: <= 0.04 s over 3 seeds), and
    method A (case aligned) runs."""
    run, p, events = fly("runway_takeoff", 50.0, "runway", duration_s=17.0)
    t_level, _ = first(events, "levelled")
    assert t_level is not None and t_level < run.truth.launch_time_s
    assert "started_in_flight" not in kinds(events)
    _t, detail = first(events, "takeoff")
    assert "forward specific force" in detail
    assert abs(p.phase.launch_time_s - run.truth.launch_time_s) < 0.3
    assert not p.azimuth_status().startswith(("not run", "failed", "disabled")), p.azimuth_status()


def test_hand_launch_detects_the_throw_and_says_why_method_a_does_not_run():
    """GIVEN a hand launch (on the ground, picked up and pitched 10 deg, held, thrown) WHEN it is
    thrown THEN the throw is the take-off within 0.1 s (the pick-up is not), and method A says
    in one line why it does not run: the levelling on the ground no longer holds in the hand, and
    the attitude filter's tilt at the throw (measured sigma 1.56 deg in the hand's sway) is not
    good enough to level on."""
    run, p, events = fly("hand_launch", 50.0, "hand", case="inclined", duration_s=12.0)
    takeoffs = [(t, d) for t, k, d in events if k == "takeoff"]
    assert len(takeoffs) == 1 and abs(p.phase.launch_time_s - run.truth.launch_time_s) < 0.1
    why = [d for _t, k, d in events if k == "azimuth"]
    assert why and why[0].startswith("not run: the vehicle turned") and "since its last still block" in why[0]
    assert "the attitude filter's tilt sigma at the launch" in why[0]
    assert p.azimuth_status() == why[0]


def test_the_attitude_filter_tilt_becomes_a_levelling_that_gives_it_back(monkeypatch):
    """GIVEN the attitude filter's roll 3 deg, pitch 9 deg, sigma 0.3 deg at a launch after a
    pick-up, and a still block on the ground (its gyro bias) WHEN it is written as method A's
    levelling THEN levelling_result gives back that roll, pitch and sigma (the accelerometer-bias
    allowance added), and the block's gyro bias; a sigma above the limit is refused with why."""
    from estimators.levelling import LevellingState, levelling_result, levelling_step
    from estimators.polar_attitude import AttitudeEstimate
    from service.phases import PhaseState
    p = Pipeline(validate({"site": {"lat_deg": 47.0, "lon_deg": 8.0}, "imu": {"mount_yaw_deg": 90.0}}))
    block = LevellingState()
    rng = np.random.default_rng(4)
    for k in range(100):
        block = levelling_step(block, np.array([0.001, -0.002, 0.0005]) + rng.normal(0, 1e-3, 3),
                               np.array([0.0, 0.0, -9.80665]) + rng.normal(0, 0.02, 3), 0.02 * k)
    roll, pitch = math.radians(3.0), math.radians(9.0)
    for sigma_deg, ok in ((0.3, True), (1.2, False)):
        s2 = math.radians(sigma_deg) ** 2
        est = AttitudeEstimate(roll_rad=roll, pitch_rad=pitch, cov_roll_pitch_rad2=np.diag([s2, 0.5 * s2]),
                               gyro_bias_rad_s=np.zeros(3), q_P_from_body=np.array([1.0, 0, 0, 0]))
        # C's estimate as the Pipeline reads it (through its core backend: service/core_backend.py)
        monkeypatch.setattr(p, "core", dataclasses.replace(p.core, polar_attitude_estimate=lambda _st, e=est: e))
        p.phase = PhaseState(moved_rad=math.radians(10.0))
        lev, why = p._level_block_from_attitude_filter(block)
        if not ok:
            assert lev is None and "tilt sigma at the launch, 1.20 deg, is above the 0.5 deg" in why
            continue
        res = levelling_result(lev, p.phase_params.levelling)
        # the levelling is of the SENSOR axes: the 90 deg mount turns body roll/pitch into sensor pitch/-roll
        C_sb = p.C_body_from_sensor.T
        f_body = C_sb.T @ res.accel_mean_m_s2
        assert math.atan2(-f_body[1], -f_body[2]) == pytest.approx(roll, abs=1e-12)
        assert math.atan2(f_body[0], math.hypot(f_body[1], f_body[2])) == pytest.approx(pitch, abs=1e-12)
        assert res.ok and res.tilt_noise_rad == pytest.approx(math.radians(0.3), rel=1e-9)
        np.testing.assert_array_equal(res.gyro_bias_rad_s, block.gyro_mean_rad_s)
        assert "levelled on the attitude filter at the launch (roll 3.00 deg, pitch 9.00 deg, sigma 0.30 deg)" in why
