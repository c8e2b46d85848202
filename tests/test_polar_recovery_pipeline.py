"""Issue 18's recovery tests through the daemon's Pipeline (both of method C's filters and what
it publishes) on the simulator's IMU (sim.offline: its own Earth field and sensor errors, a
consumer IMU with scale-factor and bias errors), IMU samples only (no FC, no air data).
GIVEN the body at pitch +90 deg / upside down / spinning at ~500 deg/s WHEN it returns to level
and rests THEN the published roll/pitch and heading are back within their published sigma within
a stated time. Truth only scores."""
import math

import numpy as np
import pytest

from mavlink_io.samples import ImuSample
from service.config import validate
from service.pipeline import Pipeline
from sim.offline import simulate

IMU_HZ = 50.0
REST_S = 10.0
BACK_S = 0.5
"""The stated time: from this long after the return to level, every published solution counts."""
SEGMENTS = [  # after the 10 s rest: (name of the event ending at the next rest or None, segment)
    (None, {"duration_s": 3.0, "by_deg": [0.0, 90.0, 0.0]}),        # pitch up to +90 deg
    (None, {"duration_s": 2.0, "by_deg": [0.0, 0.0, 0.0]}),         # held
    ("pitch_90", {"duration_s": 3.0, "by_deg": [0.0, -90.0, 0.0]}),  # back to level
    (None, {"duration_s": 5.0, "by_deg": [0.0, 0.0, 0.0]}),
    (None, {"duration_s": 2.0, "by_deg": [180.0, 0.0, 0.0]}),       # upside down
    (None, {"duration_s": 2.0, "by_deg": [0.0, 0.0, 0.0]}),         # held
    ("upside_down", {"duration_s": 2.0, "by_deg": [180.0, 0.0, 0.0]}),
    (None, {"duration_s": 5.0, "by_deg": [0.0, 0.0, 0.0]}),
    ("spin_500", {"duration_s": 2.0, "by_deg": [0.0, 0.0, 720.0]}),  # yaw spin, peak ~540 deg/s
    (None, {"duration_s": 5.0, "by_deg": [0.0, 0.0, 0.0]}),
]


def _windows():
    """event -> (time it is back at level, end of the rest after it) (s)."""
    t, out = REST_S, {}
    for name, seg in SEGMENTS:
        t += seg["duration_s"]
        if name is not None:
            out[name] = (t, None)
        else:
            for k, (t0, t1) in out.items():
                if t1 is None:
                    out[k] = (t0, t)
    return out


@pytest.fixture(scope="module")
def flight():
    run = simulate("any_motion_handheld", seed=5, imu_rate_hz=IMU_HZ,
                   duration_s=REST_S + sum(s["duration_s"] for _, s in SEGMENTS),
                   overrides={"motion": {"segments": [s for _, s in SEGMENTS]}})
    s = run.site
    p = Pipeline(validate({
        "site": {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"],
                 "decimal_year": s["decimal_year"]},
        "launch": {"case": "aligned", "vehicle": "hand"}, "heading": {"use_fc_yaw": False},
        "azimuth": {"solve_in_background": False}, "mavlink": {"imu_rate_hz": IMU_HZ}}))
    rows = []   # t, tilt error, tilt sigma (larger of roll/pitch), heading error, heading sigma (deg)
    for k, t in enumerate(run.time_s.tolist()):
        sol = p.on_imu(ImuSample(t, t, run.gyro_rad_s[k].copy(), run.accel_m_s2[k].copy(),
                                 run.mag_gauss[k].copy(), "RAW_IMU", 0))
        if sol is None or sol.q_nav_from_body is None or not sol.heading_valid:
            continue
        qt, qe = run.truth.q_nav_from_body[k], np.asarray(sol.q_nav_from_body)
        e = np.array([qe[0] * qt[0] + qe[1] * qt[1] + qe[2] * qt[2] + qe[3] * qt[3],
                      -qe[0] * qt[1] + qe[1] * qt[0] - qe[2] * qt[3] + qe[3] * qt[2],
                      -qe[0] * qt[2] + qe[1] * qt[3] + qe[2] * qt[0] - qe[3] * qt[1],
                      -qe[0] * qt[3] - qe[1] * qt[2] + qe[2] * qt[1] + qe[3] * qt[0]])   # q_est (x) q_true^-1
        heading = math.degrees(math.remainder(2.0 * math.atan2(e[3], e[0]), 2.0 * math.pi))
        tilt = math.degrees(2.0 * math.acos(min(1.0, math.hypot(e[0], e[3]))))   # the swing's angle
        rows.append((t, tilt, math.degrees(max(sol.roll_sigma_rad, sol.pitch_sigma_rad)), heading,
                     math.degrees(sol.heading_sigma_rad)))
    return np.array(rows)


@pytest.mark.parametrize("event", ["pitch_90", "upside_down", "spin_500"])
def test_given_an_extreme_attitude_when_back_at_level_then_roll_pitch_and_heading_within_sigma(flight, event):
    t_level, t_end = _windows()[event]
    r = flight[(flight[:, 0] >= t_level + BACK_S) & (flight[:, 0] <= t_end)]
    assert len(r) >= int((t_end - t_level - BACK_S) * IMU_HZ) - 2      # published all along
    # THEN from BACK_S after the return: the tilt (roll/pitch) within 2 published sigma and under
    # 1 deg, the heading within 2 published sigma and under 2 deg. Measured (seed 5, worst per
    # event pitch_90 / upside_down / spin_500): tilt 0.45 / 0.19 / 0.17 deg, at most 0.76 / 0.21 /
    # 0.40 sigma; heading 0.95 / 1.08 / 1.49 deg, at most 0.21 / 0.41 / 0.64 sigma
    assert np.all(r[:, 1] <= 2.0 * r[:, 2]) and np.max(r[:, 1]) < 1.0, (np.max(r[:, 1]), np.min(r[:, 2]))
    assert np.all(np.abs(r[:, 3]) <= 2.0 * r[:, 4]) and np.max(np.abs(r[:, 3])) < 2.0, \
        (np.max(np.abs(r[:, 3])), np.min(r[:, 4]))
