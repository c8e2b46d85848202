"""MAVLink output encoders: what a fresh pymavlink parser decodes from our bytes."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from estimators.rotations import euler_from_quat, quat_from_euler, wrap_pi
from mavlink_io import outputs
from mavlink_io.navsolution import NavSolution

SYSID, COMPID = 7, mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER


def f32(x: float) -> float:
    return float(np.float32(x))


def make_solution(**kw) -> NavSolution:
    roll, pitch, yaw = math.radians(4.0), math.radians(-7.5), math.radians(231.25)
    base = dict(time_fc_s=123.456789, time_rx_s=5000.0, phase="in-flight",
                q_nav_from_body=quat_from_euler(roll, pitch, yaw), roll_rad=roll,
                pitch_rad=pitch, rates_body_rad_s=np.array([0.01, -0.02, 0.3]),
                roll_sigma_rad=math.radians(0.5), pitch_sigma_rad=math.radians(0.6),
                heading_rad=yaw, heading_sigma_rad=math.radians(2.0),
                heading_source="azimuth", heading_valid=True,
                azimuth_rad=math.radians(229.0), azimuth_sigma_rad=math.radians(1.5))
    base.update(kw)
    return NavSolution(**base)


def round_trip(msg):
    """Pack with our identity, parse the bytes with a fresh MAVLink parser."""
    sender = mavlink2.MAVLink(None, srcSystem=SYSID, srcComponent=COMPID)
    buf = msg.pack(sender)
    parser = mavlink2.MAVLink(None)
    decoded = parser.parse_buffer(buf)
    assert decoded is not None and len(decoded) == 1
    out = decoded[0]
    assert out.get_srcSystem() == SYSID and out.get_srcComponent() == COMPID
    return out


@pytest.mark.parametrize("profile_name", ["ardupilot", "px4", "mavlink"])
def test_odometry_decodes_with_nan_fields_and_documented_covariance(profile_name):
    sol = make_solution()
    profile = outputs.ODOMETRY_PROFILES[profile_name]
    m = round_trip(outputs.encode_odometry(sol, profile, reset_counter=3))
    assert m.get_msgId() == 331
    assert m.time_usec == 123456789
    # frames: what each autopilot accepts for an absolute heading (module docstring)
    expected_frame = {"ardupilot": mavlink2.MAV_FRAME_LOCAL_FRD,
                      "px4": mavlink2.MAV_FRAME_LOCAL_NED,
                      "mavlink": mavlink2.MAV_FRAME_LOCAL_NED}[profile_name]
    assert m.frame_id == expected_frame
    assert m.child_frame_id == mavlink2.MAV_FRAME_BODY_FRD
    # position: finite placeholder for the autopilots (NaN drops the yaw), NaN for the spec
    for v in (m.x, m.y, m.z):
        if profile_name == "mavlink":
            assert math.isnan(v)
        else:
            assert v == 0.0
    # velocity and rates unknown
    for v in (m.vx, m.vy, m.vz, m.rollspeed, m.pitchspeed, m.yawspeed):
        assert math.isnan(v)
    assert math.isnan(m.velocity_covariance[0])
    # q = our attitude, the yaw the FC will extract is our heading
    q = np.array(m.q)
    np.testing.assert_allclose(q, sol.q_nav_from_body, atol=2e-7)
    roll, pitch, yaw = euler_from_quat(q)
    assert abs(wrap_pi(yaw - sol.heading_rad)) < 1e-6
    # covariance: 21 elements, element 0 finite (else "whole matrix unknown"), diagonal at the
    # documented indices, every cross term 0
    cov = list(m.pose_covariance)
    assert len(cov) == 21 and all(math.isfinite(c) for c in cov)
    assert cov[0] == cov[6] == cov[11] == f32(1.0e6)
    assert cov[15] == f32(sol.roll_sigma_rad ** 2)
    assert cov[18] == f32(sol.pitch_sigma_rad ** 2)
    assert cov[20] == f32(sol.heading_sigma_rad ** 2)
    assert all(c == 0.0 for i, c in enumerate(cov) if i not in (0, 6, 11, 15, 18, 20))
    assert m.reset_counter == 3
    assert m.estimator_type == mavlink2.MAV_ESTIMATOR_TYPE_VISION
    assert m.quality == round(100 * (1 - 2.0 / 30.0))  # 93


def test_ardupilot_angle_error_from_our_covariance():
    """What ArduPilot's handle_odometry computes from our covariance (GCS_Common.cpp):
    angErr = cbrt(c15^2 + c18^2 + c20^2) -- documented in docs/OUTPUTS.md."""
    sol = make_solution()
    cov = outputs.pose_covariance(sol, outputs.ODOMETRY_PROFILES["ardupilot"])
    ang_err = (cov[15] ** 2 + cov[18] ** 2 + cov[20] ** 2) ** (1 / 3)
    by_hand = (math.radians(0.5) ** 4 + math.radians(0.6) ** 4 + math.radians(2.0) ** 4) ** (1 / 3)
    assert ang_err == pytest.approx(by_hand, rel=1e-12)
    assert ang_err == pytest.approx(0.011453, rel=1e-4)  # rad: 0.66 deg, below the 5 deg floor


def test_odometry_only_with_usable_heading():
    prof = outputs.ODOMETRY_PROFILES["px4"]
    assert outputs.encode_odometry(make_solution(heading_valid=False), prof) is None
    assert outputs.encode_odometry(make_solution(heading_sigma_rad=None), prof) is None
    assert outputs.encode_odometry(make_solution(heading_sigma_rad=float("nan")), prof) is None
    assert outputs.encode_odometry(make_solution(q_nav_from_body=None), prof) is None
    with pytest.raises(ValueError, match="reset_counter"):
        outputs.encode_odometry(make_solution(), prof, reset_counter=256)


def test_unknown_tilt_sigma_uses_yaw_variance():
    sol = make_solution(roll_sigma_rad=None, pitch_sigma_rad=None)
    cov = outputs.pose_covariance(sol, outputs.ODOMETRY_PROFILES["ardupilot"])
    assert cov[15] == cov[18] == cov[20] == pytest.approx(sol.heading_sigma_rad ** 2)


def test_attitude_round_trip():
    sol = make_solution()
    m = round_trip(outputs.encode_attitude(sol))
    assert m.get_msgId() == 30
    assert m.time_boot_ms == 123457
    assert m.roll == f32(sol.roll_rad) and m.pitch == f32(sol.pitch_rad)
    assert m.yaw == f32(wrap_pi(sol.heading_rad))  # ATTITUDE yaw in [-pi, pi)
    assert (m.rollspeed, m.pitchspeed, m.yawspeed) == (f32(0.01), f32(-0.02), f32(0.3))


def test_attitude_without_heading_has_nan_yaw_and_no_quaternion():
    sol = make_solution(heading_valid=False)
    m = round_trip(outputs.encode_attitude(sol))
    assert math.isnan(m.yaw) and m.roll == f32(sol.roll_rad)
    assert outputs.encode_attitude_quaternion(sol) is None
    assert outputs.encode_attitude(make_solution(roll_rad=None)) is None


def test_attitude_quaternion_round_trip():
    # a negative-scalar input comes out as the positive representative of the same rotation
    q_in = -quat_from_euler(0.3, -0.2, 2.9)
    sol = make_solution(q_nav_from_body=q_in)
    m = round_trip(outputs.encode_attitude_quaternion(sol))
    assert m.get_msgId() == 31
    q = np.array([m.q1, m.q2, m.q3, m.q4])
    np.testing.assert_allclose(q, -q_in, atol=1e-7)
    assert m.time_boot_ms == 123457
    assert m.yawspeed == f32(0.3)


def test_named_values():
    msgs = [round_trip(m) for m in outputs.encode_named_values(make_solution())]
    values = {m.name: m.value for m in msgs}
    assert set(values) == {"phase", "az_deg", "hdg_deg", "hdg_sd_deg"}
    assert values["phase"] == 3.0
    assert values["az_deg"] == pytest.approx(229.0, abs=1e-4)
    assert values["hdg_deg"] == pytest.approx(231.25, abs=1e-4)
    assert values["hdg_sd_deg"] == pytest.approx(2.0, abs=1e-5)
    pre = outputs.encode_named_values(make_solution(phase="pre-launch", heading_valid=False,
                                                    azimuth_rad=None))
    assert [(round_trip(m).name, m.value) for m in pre] == [("phase", 1.0)]
    with pytest.raises(ValueError, match="10 characters"):
        outputs._named_value(0, "x" * 11, 0.0)


def test_scheduler_rates_over_ten_seconds_of_200hz_samples():
    rng = np.random.default_rng(0)
    sched = outputs.OutputScheduler({"ATTITUDE": 50.0, "ODOMETRY": 5.0,
                                     "NAMED_VALUE_FLOAT": 1.0, "ATTITUDE_QUATERNION": 0.0})
    counts: dict[int, int] = {}
    t0 = 1000.0
    for k in range(2000):  # 10 s at 200 Hz with 1 ms receive jitter
        now = t0 + k * 0.005 + rng.uniform(0.0, 0.001)
        sol = make_solution(time_fc_s=k * 0.005, time_rx_s=now)
        for m in sched.messages(sol, now):
            counts[m.get_msgId()] = counts.get(m.get_msgId(), 0) + 1
    assert counts[30] == 500
    assert counts[331] == 50
    assert counts.get(31, 0) == 0
    assert counts[251] == 10 * 4  # four named values per second


def test_scheduler_no_odometry_without_heading_and_resyncs_after_gap():
    sched = outputs.OutputScheduler()
    sol = make_solution(heading_valid=False)
    ids = {m.get_msgId() for m in sched.messages(sol, 0.0)}
    assert 331 not in ids and 31 not in ids and 30 in ids
    # slots on the FC clock (10 Hz: [k/10, (k+1)/10)); the solution above took ODOMETRY's slot 1234
    assert not sched.due("ODOMETRY", 123.49)  # the same slot
    assert sched.due("ODOMETRY", 200.0)  # the first sample in a later slot is due
    assert not sched.due("ODOMETRY", 200.05)
    assert sched.due("ODOMETRY", 200.1)
    gaps = sched.slots_gap["ODOMETRY"]
    assert sched.due("ODOMETRY", 205.0)  # gap: due at once, the slots without a sample counted
    assert sched.slots_gap["ODOMETRY"] - gaps == 48
    assert not sched.due("ODOMETRY", 205.09)
    assert sched.due("ODOMETRY", 205.1)
    assert not sched.due("ODOMETRY", 150.0)  # FC time going back (no reboot seen): nothing


def test_scheduler_validation():
    with pytest.raises(ValueError, match="ODOMETRY must be >= 5"):
        outputs.OutputScheduler({"ODOMETRY": 4.0})
    with pytest.raises(ValueError, match="unknown message 'GPS_INPUT'"):
        outputs.OutputScheduler({"GPS_INPUT": 5.0})
    with pytest.raises(ValueError, match="finite number >= 0"):
        outputs.OutputScheduler({"ATTITUDE": -1.0})


def test_reset_counter_counts_heading_discontinuities_only():
    """A blended source change is no reset (the ODOMETRY reset_counter stepped 15-17 times in 150 s
    against ArduPlane when it counted source names); a gap or a step beyond the rates is."""
    sched = outputs.OutputScheduler()
    t = [0.0]
    hdg = math.radians(231.25)
    still = np.zeros(3)

    def step(dt=0.1, **kw):
        t[0] += dt
        kw.setdefault("rates_body_rad_s", still)
        sol = make_solution(time_fc_s=100.0 + t[0], **kw)
        return [m for m in sched.messages(sol, t[0]) if m.get_msgId() == 331]

    assert step()[0].reset_counter == 0  # first valid heading: not a reset
    assert step()[0].reset_counter == 0
    assert step(heading_source="synthetic_ahrs")[0].reset_counter == 0  # the name changed, the heading did not
    assert step(heading_rad=hdg + math.radians(1.9))[0].reset_counter == 0  # < max(3 sigma = 6 deg, 2 deg)
    assert step(heading_rad=hdg + math.radians(9.0))[0].reset_counter == 1  # a 7.1 deg step: a reset
    # a 30 deg/s turn explains 3 deg per 0.1 s: no reset
    yaw_rate = np.array([0.0, 0.0, math.radians(30.0)])
    assert step(heading_rad=hdg + math.radians(12.0), rates_body_rad_s=yaw_rate)[0].reset_counter == 1
    assert step(heading_valid=False) == []
    assert step(heading_rad=hdg + math.radians(12.0))[0].reset_counter == 2  # regained after a gap


def test_profile_for_autopilot():
    assert outputs.odometry_profile_for_autopilot(
        mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA).name == "ardupilot"
    assert outputs.odometry_profile_for_autopilot(mavlink2.MAV_AUTOPILOT_PX4).name == "px4"
    assert outputs.odometry_profile_for_autopilot(None).name == "mavlink"
    assert outputs.odometry_profile_for_autopilot("ardupilot").name == "ardupilot"
    assert outputs.odometry_profile_for_autopilot("px4").name == "px4"
    assert outputs.odometry_profile_for_autopilot("other").name == "mavlink"


def test_time_validation():
    with pytest.raises(ValueError, match="time_fc_s"):
        outputs.encode_attitude(make_solution(time_fc_s=float("nan")))
