"""End to end against ArduPlane SITL (ArduPilot's own firmware and physics, ../shared/tools): the
real daemon connected by TCP to SERIAL1, as a user would connect it.

GIVEN ArduPlane with VISO_TYPE 1 / EK3_SRC1_YAW 6 and a mission that flies out of the fence in the
      daemon's config, GNSS cut 20 s after arming
WHEN  the daemon runs with the example config (site, URL, geofence set)
THEN  ArduPilot says EKF3 took its yaw from our ODOMETRY (STATUSTEXT "EKF3 IMU0 yaw aligned" after
      our first ODOMETRY), it ACCEPTED the daemon's divert command (COMMAND_ACK to component 191)
      and its mode became RTL (HEARTBEAT custom_mode), with the true track inside the fence.

Everything is asserted on what ArduPilot said and did, never on timing: the flight ends on the
FC's clock, not the wall clock. Skipped, with the reason, when the SITL binary is absent.
"""
from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench import ardupilot_sitl as aps  # noqa: E402

SITL = aps.sitl_dir()
MISSING = aps.sitl_missing(SITL)
needs_sitl = pytest.mark.skipif(MISSING is not None, reason=MISSING or "")


# --- the harness's own arithmetic (no SITL) ---------------------------------------------------------

def test_score_recovers_known_errors():
    # GIVEN a truth with a 10 deg/s turn and an estimate 1 deg high in roll, -2 deg in pitch, +3 deg
    #       in heading across the +-180 deg wrap, the yaw unknown (NaN) for its first quarter
    t = np.arange(0.0, 40.0, 0.02)
    yaw = np.radians(170.0 + 10.0 * t)
    truth = {"t": t, "roll": np.radians(20.0) * np.sin(t), "pitch": np.radians(5.0) * np.cos(t),
             "yaw": (yaw + np.pi) % (2 * np.pi) - np.pi, "lat": np.zeros_like(t), "lon": np.zeros_like(t)}
    te = t[::2] + 0.01                      # estimate times between truth samples
    est_yaw = (np.radians(173.0 + 10.0 * te) + np.pi) % (2 * np.pi) - np.pi
    est_yaw[: te.size // 4] = np.nan
    est = {"t": te, "roll": np.radians(20.0) * np.sin(te) + np.radians(1.0),
           "pitch": np.radians(5.0) * np.cos(te) - np.radians(2.0), "yaw": est_yaw}
    # WHEN it is scored over [5, 35) s
    s = aps.score(est, truth, 5.0, 35.0)
    # THEN the constant errors come back (interpolation of a smooth truth: < 0.01 deg) and the
    #      heading coverage is the fraction of the window with a yaw
    assert s["roll_rms_deg"] == pytest.approx(1.0, abs=0.01)
    assert s["pitch_rms_deg"] == pytest.approx(2.0, abs=0.01)
    assert s["heading_rms_deg"] == pytest.approx(3.0, abs=0.01)
    assert s["heading_mean_deg"] == pytest.approx(3.0, abs=0.01)
    assert s["heading_coverage"] == pytest.approx(25.0 / 30.0, abs=0.01)


def test_vqf_frames_give_ned_heading_and_frd_tilt():
    pytest.importorskip("vqf")
    # GIVEN a body at rest, rolled 10 deg right and pitched 5 deg up, nose east: specific force
    #       f = C_body_from_ned (0, 0, -g) and the field (0.2, 0, 0.4) G NED seen in FRD
    roll, pitch, yaw = np.radians([10.0, 5.0, 90.0])
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    C_ned_from_frd = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                               [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                               [-sp, sr * cp, cr * cp]])
    n = 3000
    raw = {"t": np.arange(n) * 0.01, "gyro_rad_s": np.zeros((n, 3)),
           "accel_m_s2": np.tile(C_ned_from_frd.T @ [0.0, 0.0, -9.80665], (n, 1)),
           "mag_gauss": np.tile(C_ned_from_frd.T @ [0.2, 0.0, 0.4], (n, 1))}
    home = (0.0, 0.0, 0.0, 0.0)
    # WHEN VQF runs on it through the harness's frame conversion
    out = aps.run_vqf(raw, home)
    # THEN roll, pitch and the magnetic heading (+ the WMM declination) are the body's
    assert math.degrees(out["roll"][-1]) == pytest.approx(10.0, abs=0.05)
    assert math.degrees(out["pitch"][-1]) == pytest.approx(5.0, abs=0.05)
    assert math.degrees(out["yaw"][-1] - aps.declination_rad(home)) == pytest.approx(90.0, abs=0.05)


def test_fence_clearance_and_mission_geometry():
    home = aps.DEFAULT_HOME
    fence = aps.fence_square(home, 2000.0)
    # a point 1500 m north of home is 500 m inside; 2300 m north is 300 m outside
    lat_lon = [aps.offset_deg(home[0], home[1], 0.0, d) for d in (1500.0, 2300.0)]
    d = aps.clearance_m(home, fence, np.array([p[0] for p in lat_lon]), np.array([p[1] for p in lat_lon]))
    assert d[0] == pytest.approx(500.0, abs=1.0) and d[1] == pytest.approx(-300.0, abs=1.0)
    # the outbound leg crosses that fence; the square stays > 2.3 km inside the 4 km one
    out = aps.mission("plane", "outbound", home, 1)
    sq = aps.mission("quadplane", "square", home, 1)
    assert out[1].command == aps.CMD_TAKEOFF and sq[1].command == aps.CMD_VTOL_TAKEOFF
    assert aps.clearance_m(home, fence, np.array([out[-1].lat_deg]), np.array([out[-1].lon_deg]))[0] < -3000.0
    inner = aps.clearance_m(home, aps.fence_square(home, aps.INSIDE_FENCE_HALF_SIZE_M),
                            np.array([m.lat_deg for m in sq]), np.array([m.lon_deg for m in sq]))
    assert inner.min() > 2300.0


# --- the flight ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    # instance 2: ports 5780-5783, apart from the bench's default -I 1
    # $AZIMUTHD_DAEMON_SRC: run the daemon from another source tree (e.g. `git archive HEAD`)
    src = ["--daemon-src", os.environ["AZIMUTHD_DAEMON_SRC"]] if os.environ.get("AZIMUTHD_DAEMON_SRC") else []
    args = aps.build_parser().parse_args(["-I", "2", "--speedup", "2", "--rest-s", "4", "--flight-wall-limit-s", "300",
                                          *src])
    args.sitl_dir = SITL
    if not all(aps.port_free(p) for p in aps.sitl_ports(args.instance).values()):
        pytest.skip(f"SITL instance -I {args.instance} ports are in use")
    rundir = tmp_path_factory.mktemp("ardupilot") / "flight"
    return aps.fly(aps.quick_flight(rtl_hold_s=3.0), args, rundir, log=lambda *_: None)


@needs_sitl
@pytest.mark.timeout(400)
def test_ardupilot_fuses_our_odometry_yaw(flight):
    ev = aps.odometry_evidence(flight)
    assert ev["odometry_sent"] > 0, f"the daemon sent no ODOMETRY; daemon log:\n{flight.daemon_log_tail}"
    assert ev["odometry_fused"], (f"no 'EKF3 IMU0 yaw aligned' after our first ODOMETRY at "
                                  f"{ev['first_odometry_fc_s']} s; ArduPilot said: {flight.texts}")


@needs_sitl
@pytest.mark.timeout(400)
def test_ardupilot_obeys_our_divert(flight):
    d = aps.divert_evidence(flight)
    assert d["commands_sent"] >= 1, f"no divert command; daemon log:\n{flight.daemon_log_tail}"
    assert d["acked"], f"divert not accepted: {d['acks']}"
    assert d["mode_changed_to_rtl"], f"mode never became RTL: {flight.modes}"
    assert not math.isnan(flight.cut_fc_s) and d["rtl_fc_s"] > flight.cut_fc_s, \
        f"RTL at {d['rtl_fc_s']} s came before the GNSS cut at {flight.cut_fc_s} s: not a GNSS-denied divert"
    assert d["min_true_clearance_m"] > 0.0, f"the true track left the fence by {-d['min_true_clearance_m']:.0f} m"
