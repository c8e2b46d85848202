"""Outputs at their configured rates whatever the IMU rate, and nothing meaningless published.

Against ArduPlane's stock parameters RAW_IMU came at 1 Hz and the daemon's ATTITUDE/ODOMETRY followed
it (1 Hz, against the documented >= 5 Hz), and at 1 Hz it published a heading while its roll/pitch
sigma was 85 deg. Now the daemon's loop publishes the last solution brought to the send time by its
body rates (mavlink_io/output_gate.py), none older than max_extrapolation_s, and cuts what its sigma
calls meaningless."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.output_gate import OutputLimits, extrapolate_solution, gate_solution
from mavlink_io.outputs import OutputScheduler
from mavlink_io.navsolution import NavSolution
from estimators.rotations import euler_from_quat, quat_from_euler


def solution(t_fc=10.0, t_rx=100.0, roll=0.1, pitch=-0.05, hdg=1.0, rates=(0.0, 0.0, 0.0), tilt_sd_deg=0.5,
             hdg_sd_deg=2.0, valid=True) -> NavSolution:
    return NavSolution(t_fc, t_rx, "in-flight", quat_from_euler(roll, pitch, hdg), roll, pitch, np.array(rates),
                       roll_sigma_rad=math.radians(tilt_sd_deg), pitch_sigma_rad=math.radians(tilt_sd_deg),
                       heading_rad=hdg, heading_sigma_rad=math.radians(hdg_sd_deg), heading_source="azimuth",
                       heading_valid=valid)


# --- extrapolation: analytical cases -------------------------------------------------------

def test_level_yaw_rate_advances_the_heading_by_rate_times_age():
    s = extrapolate_solution(solution(roll=0.0, pitch=0.0, hdg=1.0, rates=(0, 0, 0.3)), 100.1, 0.15)
    assert s.heading_rad == pytest.approx(1.03, abs=1e-12)
    assert s.roll_rad == pytest.approx(0.0, abs=1e-12) and s.pitch_rad == pytest.approx(0.0, abs=1e-12)
    assert s.time_fc_s == pytest.approx(10.1) and s.time_rx_s == 100.1
    assert euler_from_quat(s.q_nav_from_body)[2] == pytest.approx(1.03, abs=1e-12)


def test_body_roll_rate_at_level_advances_roll_only():
    s = extrapolate_solution(solution(roll=0.0, pitch=0.0, hdg=2.0, rates=(0.5, 0, 0)), 100.1, 0.15)
    assert s.roll_rad == pytest.approx(0.05, abs=1e-12)
    assert s.pitch_rad == pytest.approx(0.0, abs=1e-12) and s.heading_rad == pytest.approx(2.0, abs=1e-12)


def test_too_old_is_no_solution_and_now_is_unchanged():
    sol = solution(rates=(0.1, 0.2, 0.3))
    assert extrapolate_solution(sol, 100.151, 0.15) is None
    assert extrapolate_solution(sol, 100.0, 0.15) is sol


# --- the gate ------------------------------------------------------------------------------

def _ids(sched, sol, now):
    return sorted({m.get_msgId() for m in sched.messages(sol, now)})


def test_tilt_sigma_over_the_limit_sends_no_attitude_but_the_heading_value():
    lim = OutputLimits(math.radians(10.0), math.radians(15.0), 0.15)
    g = gate_solution(solution(tilt_sd_deg=10.5), lim)
    assert g.roll_rad is None and g.q_nav_from_body is None and "roll/pitch sigma 10.5 deg > 10" in g.flags["outputs"]
    sched = OutputScheduler()
    msgs = sched.messages(g, 0.0)
    assert {m.get_msgId() for m in msgs} == {251}  # no ATTITUDE (30), quaternion (31), ODOMETRY (331)
    assert "hdg_deg" in {m.name for m in msgs}
    assert gate_solution(solution(tilt_sd_deg=9.9), lim).roll_rad == 0.1  # under the limit: untouched


def test_heading_sigma_over_the_limit_sends_attitude_with_nan_yaw_only():
    lim = OutputLimits(math.radians(10.0), math.radians(15.0), 0.15)
    g = gate_solution(solution(hdg_sd_deg=15.2), lim)
    assert not g.heading_valid and g.heading_rad is None and "heading sigma 15.2 deg > 15" in g.flags["outputs"]
    msgs = OutputScheduler().messages(g, 0.0)
    assert {m.get_msgId() for m in msgs} == {30, 251}
    att = next(m for m in msgs if m.get_msgId() == 30)
    assert math.isnan(att.yaw) and att.roll == pytest.approx(0.1)
    assert "hdg_deg" not in {m.name for m in msgs if m.get_msgId() == 251}


# --- the daemon: rates whatever the IMU rate -------------------------------------------------

class _Link:
    """What the daemon's publishing needs from MavlinkLink: send() and our system id."""

    def __init__(self):
        self.sent = []
        self.mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)

    def send(self, msg):
        self.sent.append(msg)
        return True


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    from service.config import validate
    from service.daemon import Daemon
    cfg = validate({"site": {"lat_deg": 47.0, "lon_deg": 8.0}, "zenoh": {"enabled": False},
                    "service": {"state_dir": str(tmp_path_factory.mktemp("state"))},
                    "azimuth": {"solve_in_background": False},
                    "outputs": {"attitude_hz": 50.0, "odometry_hz": 10.0, "attitude_to_fc": True}})
    d = Daemon(cfg)
    yield d
    d.pipeline.solver.close()


def _fly(d, imu_hz: float, seconds: float = 2.0, loop_s: float = 0.005, lag_s: float = 0.0, **kw) -> dict:
    """GIVEN solutions every 1/imu_hz s, WHEN the daemon's loop runs every loop_s: what it sends."""
    d.link = _Link()
    d.scheduler = OutputScheduler(dict(d.scheduler.rates_hz))
    d.scheduler.odometry_allowed = True
    d.last_solution = None
    d._last_sent_fc_s = -math.inf  # each flight here starts its FC clock anew (as after an FC reboot)
    n_loop = int(round(seconds / loop_s))
    every = int(round(1.0 / imu_hz / loop_s))
    for k in range(n_loop):
        now = 1000.0 + k * loop_s
        if k % every == 0:
            d.last_solution = solution(t_fc=10.0 + k * loop_s, t_rx=now - lag_s, rates=(0.0, 0.0, 0.2), **kw)
            d._last_solution_s = now
        d._publish_due(now)
    out = {}
    for m in d.link.sent:
        out[m.get_type()] = out.get(m.get_type(), 0) + 1
    out["odometry_times_us"] = [m.time_usec for m in d.link.sent if m.get_type() == "ODOMETRY"]
    return out


def test_outputs_at_their_rates_from_a_25_hz_imu(daemon):
    sent = _fly(daemon, 25.0)  # what ArduPlane grants at its stock SCHED_LOOP_RATE
    assert sent["ATTITUDE"] == 100 and sent["ATTITUDE_QUATERNION"] == 100  # 50 Hz for 2 s
    assert sent["ODOMETRY"] == 20  # 10 Hz
    # each carries its solution's own FC stamp (on the 40 ms IMU steps: 80 or 120 ms apart), 100 ms
    # on average
    t = np.diff(sent["odometry_times_us"])
    assert np.all(t % 40_000 == 0) and np.mean(t) == pytest.approx(100_000, abs=10_000)


def test_a_1_hz_imu_gives_outputs_only_while_the_solution_is_fresh(daemon):
    sent = _fly(daemon, 1.0, seconds=4.0)
    # each sample is published for max_extrapolation_s = 0.15 s: 8 ATTITUDE slots of 20 ms, 2 of
    # ODOMETRY's 100 ms (the slots re-synchronise after each gap), then nothing until the next sample
    assert sent["ATTITUDE"] == 4 * 8
    assert sent["ODOMETRY"] == 4 * 2


def test_meaningless_sigmas_are_not_published_by_the_daemon(daemon):
    sent = _fly(daemon, 25.0, tilt_sd_deg=85.0)  # the 1 Hz ArduPlane run: roll/pitch sigma 85 deg
    assert "ATTITUDE" not in sent and "ATTITUDE_QUATERNION" not in sent and "ODOMETRY" not in sent


def test_attitude_not_sent_to_the_fc_when_switched_off(daemon):
    daemon.attitude_to_fc = False
    try:
        sent = _fly(daemon, 25.0, seconds=0.5)
    finally:
        daemon.attitude_to_fc = True
    assert "ATTITUDE" not in sent and "ATTITUDE_QUATERNION" not in sent
    assert sent["ODOMETRY"] == 5 and sent["NAMED_VALUE_FLOAT"] > 0


def test_a_loop_behind_a_burst_still_publishes_its_late_solutions(daemon):
    """Each solution produced 0.3 s after its sample was received (a loop working off a burst): it
    is sent with its own time stamps, not dropped as too old and not pushed 0.3 s forward."""
    sent = _fly(daemon, 25.0, seconds=1.0, lag_s=0.3)
    assert sent["ATTITUDE"] == 50 and sent["ODOMETRY"] == 10
    t_fc_us = np.array(sent["odometry_times_us"])
    assert np.all(t_fc_us % 40_000 == 0)  # on the 25 Hz sample times: not extrapolated


def test_a_burst_of_solutions_in_one_poll_is_published_at_the_rates(daemon):
    """One poll returning 1 s of 25 Hz samples (the loop behind, the burst worked off in 1 s of
    daemon time, every solution 1-2 s behind the FC's clock): each slot is taken by its own sample and
    sent with it, at most at the configured rate of the local clock (counted as sent behind), not one
    message per poll; no ODOMETRY (older than the FC's EKFs date a measurement,
    outputs.CATCH_UP_MAX_LAG_S). tests/test_output_slots.py has bursts handled faster than the rate."""
    from mavlink_io.samples import ImuSample
    t = [2000.0]
    daemon.clock = lambda: t[0]
    daemon.link = _Link()
    daemon.scheduler = OutputScheduler(dict(daemon.scheduler.rates_hz))
    daemon.scheduler.odometry_allowed = True
    sols = iter([solution(t_fc=50.0 + k * 0.04, t_rx=1999.0, rates=(0.0, 0.0, 0.1)) for k in range(25)])

    class _Pipe:  # what dispatch needs from the Pipeline: one solution per IMU sample
        counters = daemon.pipeline.counters
        def on_imu(self, s):
            t[0] += 0.04  # 40 ms of daemon time per sample
            return next(sols)
        step_imu = on_imu  # the daemon's message path (Pipeline.step_imu)
        def drain_events(self):
            return []
    real, daemon.pipeline = daemon.pipeline, _Pipe()
    try:
        for k in range(25):
            daemon.dispatch(ImuSample(50.0 + k * 0.04, 1999.0, np.zeros(3), np.zeros(3), None, "RAW_IMU"))
    finally:
        daemon.pipeline, daemon.clock = real, __import__("time").monotonic
    sent = [m.get_type() for m in daemon.link.sent]
    assert sent.count("ATTITUDE") == 25 and daemon.scheduler.slots_behind["ATTITUDE"] == 25  # every 40 ms slot
    # the 10 Hz ODOMETRY slots pass without one: these solutions lag the FC's clock by 1-2 s, which
    # ArduPilot would misdate (mavlink_io/output_gate.ODOMETRY_MAX_LAG_S, tests/test_odometry_lag.py)
    assert sent.count("ODOMETRY") == 0 and daemon.scheduler.odometry_late == 10
    # and the 50 Hz slots between two 25 Hz samples had none of their own (no idle loop to fill them)
    assert daemon.scheduler.slots_late["ODOMETRY"] == 10 and daemon.scheduler.slots_gap["ATTITUDE"] == 24


def test_given_a_sender_that_stalls_then_resumes_when_outputs_go_on_then_their_time_never_goes_back(daemon):
    """The last solution is brought forward by its local age while the sender is silent; when it
    resumes, its samples are older than that prediction: nothing is sent until the FC time passes
    what was already sent (receivers such as the FC's EKF must never see time go back)."""
    d = daemon
    d.link = _Link()
    d.scheduler = OutputScheduler(dict(d.scheduler.rates_hz))
    d.scheduler.odometry_allowed = True
    d._last_sent_fc_s = -math.inf
    t_fc, loop_s = 10.0, 0.005
    for k in range(400):                      # 2 s of loop; samples every 20 ms, none in 0.5-1.0 s
        now = 1000.0 + k * loop_s
        if k % 4 == 0 and not 100 <= k < 200:
            d.last_solution = solution(t_fc=t_fc, t_rx=now, rates=(0.0, 0.0, 0.2))
            d._last_solution_s = now
            t_fc += 0.02                      # the FC clock paused with the sender: it resumes at 10.5 s
        d._publish_due(now)
    t_ms = [m.time_boot_ms for m in d.link.sent if m.get_type() == "ATTITUDE"]
    assert len(t_ms) > 50 and all(b >= a for a, b in zip(t_ms, t_ms[1:])), t_ms
