"""A run that starts in flight in the middle of a manoeuvre: the take-off roll (an ArduPilot DataFlash
log starts at arming; a daemon restarted by systemd starts wherever the flight is).

GIVEN the simulated runway take-off (sim/scenarios/runway_takeoff.toml: the roll at 2.5 m/s^2 from
14 s, rotation at 16 m/s, a 3 m/s climb-out, a 90 deg turn at 25 deg bank, level flight; consumer
IMU at 50 Hz, ArduPlane's stream rate) whose feed starts 1 s into the take-off roll, with the FC's
HEARTBEAT saying armed and flying and its attitude trusted,
WHEN it is fed to a fresh Pipeline
THEN the run is read as started in flight (attitude filter C started from the FC's tilt, its gyro
bias from the FC's calibrated stream: service/phases.py InFlightParams.gyro_bias_sigma_rad_s), and
from 15 s after the start to 60 s after it (the climb-out and the turn) roll and pitch are within
2.5 deg of the truth and within 3 published sigmas for >= 95 % of the rows.

The flight is cut at 75 s: in the level leg after the turn the roll error grows to 3-3.6 deg, outside
3 sigma, from a start at REST too (seed 0, measured 80-90 s: 3.64 deg, 44 % within 3 sigma), i.e.
method C's own behaviour in this flight, not the start's (reported; estimators/polar_attitude.py).

Before the bias prior (C's built-in 0.5 deg/s) the take-off's sustained acceleration went into the
bias and the tilt: seed 0 pitch 7.0 deg 11-21 s after the start (75 % within 3 sigma), roll 3.2 deg;
seed 1 roll 5.2 deg 51-61 s after it (18 % within 3 sigma). With it: 1.9 / 2.2 and 1.0 / 0.9 deg.
"""
import numpy as np
import pytest

from test_pipeline_started_in_flight import feed_simulated, tilt_errors

SCENARIO = "runway_takeoff"
RATE_HZ = 50.0
ROLL_START_S = 14.0   # the scenario's [launcher] rest_s: the take-off roll begins
FEED_FROM_S = ROLL_START_S + 1.0
SETTLE_S = 15.0


def fly(seed: int, feed_from_s: float = FEED_FROM_S, duration_s: float = FEED_FROM_S + 60.0, rate_hz: float = RATE_HZ):
    return feed_simulated(SCENARIO, seed, rate_hz, feed_from_s, duration_s)


@pytest.mark.parametrize("seed", [0, 1])
def test_started_on_the_take_off_roll_settles_within_its_sigma(seed):
    run, p, sols, events = fly(seed)
    sif = [d for k, d in events if k == "started_in_flight"]
    assert len(sif) == 1 and p.phase.started_in_flight and p.phase.level is None
    att = [d for k, d in events if k == "attitude" and d.startswith("started in flight")]
    assert len(att) == 1 and "the trusted FC attitude" in att[0] and "gyro bias 0 +- 0.20 deg/s (the FC's calibrated gyro at" in att[0]
    a = tilt_errors(run, sols, with_time=True)
    late = a[a[:, 0] >= FEED_FROM_S + SETTLE_S]
    assert len(late) > 40 * RATE_HZ / 2   # the climb-out and the turn are scored (filter rows at 25-50 Hz)
    roll_max, pitch_max = float(np.abs(late[:, 1]).max()), float(np.abs(late[:, 2]).max())
    cover = float(np.mean((np.abs(late[:, 1]) <= 3 * late[:, 3]) & (np.abs(late[:, 2]) <= 3 * late[:, 4])))
    assert roll_max < 2.5 and pitch_max < 2.5, (roll_max, pitch_max)
    assert cover >= 0.95, cover
    # the magnetometer: not judged disturbed against field references taken with the tilt C had
    # levelled on the accelerating roll (they are dropped at the start in flight)
    md = [d for k, d in events if k == "magnetic_disturbance"]
    assert not any(d.startswith("rejected") for d in md), md
    assert sum(s.heading_valid for s in sols if s.time_fc_s >= FEED_FROM_S + SETTLE_S) >= 0.95 * len(late)


def test_a_stream_too_slow_to_resolve_the_fc_gyro_keeps_the_wide_bias_prior():
    """25 Hz (the real ArduCopter RTL log's IMU rate): below twice ArduPilot's 20 Hz gyro filter the
    samples alias the FC's rate, and C keeps its own bias and turn-on prior (InFlightParams
    calibrated_gyro_min_rate_hz)."""
    _run, p, _sols, events = fly(0, duration_s=FEED_FROM_S + 4.0, rate_hz=25.0)
    att = [d for k, d in events if k == "attitude" and d.startswith("started in flight")]
    assert len(att) == 1 and "gyro bias prior 0.50 deg/s: a 25 Hz stream does not resolve the FC's gyro" in att[0]
