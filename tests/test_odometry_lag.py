"""ODOMETRY the FC would misdate is held back (mavlink_io/output_gate.py FcLagMeter, ODOMETRY_MAX_LAG_S).

ArduPlane SITL with the daemon 26-74 s behind its input (a machine at load 32): ArduPilot dated every
ODOMETRY 0.55 s before its arrival (its jitter correction clamps the lag at 500 ms), EKF3's yaw
innovations were 65-179 deg and all rejected, and its yaw drifted to +9 deg after the GNSS cut."""
from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.rotations import quat_from_euler
from mavlink_io.output_gate import ODOMETRY_MAX_LAG_S, FcLagMeter
from mavlink_io.outputs import OutputScheduler
from mavlink_io.navsolution import NavSolution


def solution(t_fc: float) -> NavSolution:
    return NavSolution(t_fc, t_fc, "in-flight", quat_from_euler(0.0, 0.0, 1.0), 0.0, 0.0, np.zeros(3),
                       roll_sigma_rad=math.radians(0.5), pitch_sigma_rad=math.radians(0.5), heading_rad=1.0,
                       heading_sigma_rad=math.radians(2.0), heading_source="azimuth", heading_valid=True)


def feed(meter: FcLagMeter, t_fc: np.ndarray, rx: np.ndarray) -> None:
    for a, b in zip(t_fc.tolist(), rx.tolist()):
        meter.on_sample(a, b)


def test_a_daemon_that_keeps_up_has_the_transport_delay_only():
    """GIVEN 60 s of a 50 Hz IMU arriving 5-45 ms after its sample (seeded jitter), the local clock
    1000 s ahead of the FC's WHEN each solution is computed on arrival THEN its lag is that delay
    above the smallest one (< 41 ms), far below the limit."""
    rng = np.random.default_rng(15)
    t = np.arange(0.0, 60.0, 0.02)
    rx = 1000.0 + t + rng.uniform(0.005, 0.045, t.size)
    m = FcLagMeter()
    lags = []
    for a, b in zip(t.tolist(), rx.tolist()):
        m.on_sample(a, b)
        lags.append(m.lag_s(a, b))
    assert max(lags[50:]) < 0.041 and min(lags) >= -1e-12
    assert ODOMETRY_MAX_LAG_S == 0.2


def test_a_daemon_behind_its_input_sees_its_backlog():
    """GIVEN a link that kept up for 10 s WHEN the daemon then works through input queued 0.5 s, then
    30 s, behind THEN the lag is the backlog, less the relaxation (0.5 % of the time since the offset
    was last seen)."""
    t = np.arange(0.0, 10.0, 0.02)
    m = FcLagMeter()
    feed(m, t, t + 0.01)
    late = np.arange(10.0, 12.0, 0.02)
    feed(m, late, late + 0.51)    # each read 0.5 s late
    assert m.lag_s(11.98, 11.98 + 0.51) == pytest.approx(0.5 - 0.005 * 2.5, abs=1e-3)
    feed(m, late + 2.0, late + 2.0 + 30.01)
    assert m.lag_s(13.98, 13.98 + 30.01) == pytest.approx(30.0 - 0.005 * 34.0, abs=1e-3)
    m.reset()   # an FC reboot: learnt again from the next sample
    assert m.lag_s(0.0, 5.0) == 0.0


def test_an_fc_clock_slower_than_ours_is_not_a_lag():
    """GIVEN SITL running at 0.995 of its speedup (FC time 0.5 % slower than the local clock) for 120 s
    WHEN every solution is computed on arrival THEN the lag stays below 15 ms (the relaxation of
    5 ms/s absorbs the rate)."""
    t = np.arange(0.0, 120.0, 0.02)
    rx = t / 0.995 + 0.01
    m = FcLagMeter()
    feed(m, t, rx)
    assert m.lag_s(t[-1], rx[-1]) < 0.015


def test_a_late_solution_gets_no_odometry_and_is_counted():
    """GIVEN the ODOMETRY slot due WHEN the solution is late THEN no ODOMETRY goes, the count says so,
    ATTITUDE still goes (within its rate of the local clock, counted as sent behind: fused by no EKF,
    outputs.CATCH_UP_MAX_LAG_S); WHEN the next one is in time THEN ODOMETRY goes again."""
    s = OutputScheduler({"ATTITUDE": 50.0, "ODOMETRY": 10.0})
    msgs = s.messages(solution(1.0), 100.0, late=True)
    assert [m.get_type() for m in msgs if m.get_type() == "ODOMETRY"] == [] and s.odometry_late == 1
    assert "ATTITUDE" in [m.get_type() for m in msgs] and s.slots_behind["ATTITUDE"] == 1
    assert s.slots_late["ODOMETRY"] == 1 and s.slots_late["ATTITUDE"] == 0
    msgs = s.messages(solution(1.1), 100.1, late=False)
    assert [m.get_type() for m in msgs].count("ODOMETRY") == 1 and s.odometry_late == 1
