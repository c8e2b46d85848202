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
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench import ardupilot_sitl as aps  # noqa: E402

SITL = aps.sitl_dir()
MISSING = aps.sitl_missing(SITL)
pytestmark = [pytest.mark.skipif(MISSING is not None, reason=MISSING or ""), pytest.mark.timeout(400)]


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    # instance 3: ports 5790-5793, apart from the bench's default -I 1 and other users of -I 2
    args = aps.build_parser().parse_args(["-I", "3", "--speedup", "2", "--rest-s", "4", "--flight-wall-limit-s", "300"])
    args.sitl_dir = SITL
    if not all(aps.port_free(p) for p in aps.sitl_ports(args.instance).values()):
        pytest.skip(f"SITL instance -I {args.instance} ports are in use")
    rundir = tmp_path_factory.mktemp("ardupilot") / "flight"
    return aps.fly(aps.quick_flight(rtl_hold_s=3.0), args, rundir, log=lambda *_: None)


def test_ardupilot_fuses_our_odometry_yaw(flight):
    ev = aps.odometry_evidence(flight)
    assert ev["odometry_sent"] > 0, f"the daemon sent no ODOMETRY; daemon log:\n{flight.daemon_log_tail}"
    assert ev["odometry_fused"], (f"no 'EKF3 IMU0 yaw aligned' after our first ODOMETRY at "
                                  f"{ev['first_odometry_fc_s']} s; ArduPilot said: {flight.texts}")


def test_ardupilot_obeys_our_divert(flight):
    d = aps.divert_evidence(flight)
    assert d["commands_sent"] >= 1, f"no divert command; daemon log:\n{flight.daemon_log_tail}"
    assert d["acked"], f"divert not accepted: {d['acks']}"
    assert d["mode_changed_to_rtl"], f"mode never became RTL: {flight.modes}"
    assert not math.isnan(flight.cut_fc_s) and d["rtl_fc_s"] > flight.cut_fc_s, \
        f"RTL at {d['rtl_fc_s']} s came before the GNSS cut at {flight.cut_fc_s} s: not a GNSS-denied divert"
    assert d["min_true_clearance_m"] > 0.0, f"the true track left the fence by {-d['min_true_clearance_m']:.0f} m"
