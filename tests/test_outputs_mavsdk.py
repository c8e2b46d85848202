"""A real MAVLink client: MAVSDK (4.x, the bundled C library, no mavsdk_server) reads what we send.

MAVSDK discovers our component (system id, component 191, HEARTBEAT MAV_TYPE_ONBOARD_CONTROLLER)
as a "Companion Computer" of a system without autopilot; Telemetry on that System decodes our
ATTITUDE / ATTITUDE_QUATERNION into attitude_euler and our ODOMETRY into odometry.
MAVSDK's Telemetry.heading comes from GLOBAL_POSITION_INT, which we do not send (we have no
position), so our heading is read from the quaternion (attitude_euler yaw, odometry q) and from
NAMED_VALUE_FLOAT hdg_deg through MAVSDK's MavlinkDirect plugin.

test_mavsdk_reads_our_encoders: our OutputScheduler's bytes, sent from this process.
test_mavsdk_reads_the_running_daemon: the simulator and the daemon as processes (bench/sitl.py),
the daemon mirroring its outputs to an extra udpout endpoint where MAVSDK listens; MAVSDK's
values are compared with what the daemon publishes on Zenoh and sends over MAVLink.
"""
from __future__ import annotations

import json
import math
import socket
import sys
import threading
import time

import numpy as np
import pytest
from pymavlink import mavutil

from estimators.rotations import euler_from_quat, quat_from_euler
from mavlink_io import outputs
from service.solution import NavSolution

mavsdk = pytest.importorskip("mavsdk")
from mavsdk import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.plugins.mavlink_direct import MavlinkDirect  # noqa: E402
from mavsdk.plugins.telemetry import Telemetry  # noqa: E402

OUR_SYSID = 3


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


class MavsdkClient:
    """MAVSDK as a ground station listening on udpin://127.0.0.1:PORT, recording everything."""

    def __init__(self, port: int):
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        result = self.mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        assert int(result) == 0, f"MAVSDK connection failed: {result!r}"
        self.euler: list = []
        self.odometry: list = []
        self.named: list[dict] = []
        self.system = None

    def attach(self, timeout_s: float, system_id: int | None = None) -> None:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            for s in self.mavsdk.get_systems():
                if system_id is None or s.get_system_id() == system_id:
                    if 191 in s.component_ids():
                        self.system = s
                        break
            if self.system is not None:
                break
            time.sleep(0.05)
        assert self.system is not None, "MAVSDK did not discover our component 191"
        self.telemetry = Telemetry(self.system)
        self.direct = MavlinkDirect(self.system)
        self.telemetry.subscribe_attitude_euler(lambda e, _: self.euler.append(
            (e.timestamp_us, e.roll_deg, e.pitch_deg, e.yaw_deg, time.monotonic())))
        self.telemetry.subscribe_odometry(lambda o, _: self.odometry.append(o))
        self.direct.subscribe_message("NAMED_VALUE_FLOAT",
                                      lambda m, _: self.named.append(json.loads(m.fields_json)))

    def close(self) -> None:
        self.mavsdk.destroy()


def make_sol(k: int) -> NavSolution:
    t = k * 0.005
    yaw = math.radians(200.0 + 10.0 * math.sin(t))  # ATTITUDE yaw crosses into negative
    roll, pitch = 0.1 + 0.05 * math.sin(2 * t), -0.2
    return NavSolution(time_fc_s=10.0 + t, time_rx_s=time.monotonic(), phase="in-flight",
                       q_nav_from_body=quat_from_euler(roll, pitch, yaw), roll_rad=roll,
                       pitch_rad=pitch, rates_body_rad_s=np.array([0.0, 0.0, 0.1]),
                       roll_sigma_rad=0.01, pitch_sigma_rad=0.01, heading_rad=yaw,
                       heading_sigma_rad=math.radians(2.0), heading_source="azimuth",
                       heading_valid=True, azimuth_rad=math.radians(199.0),
                       azimuth_sigma_rad=math.radians(1.0))


def test_mavsdk_reads_our_encoders():
    port = free_udp_port()
    client = MavsdkClient(port)
    out = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=OUR_SYSID,
                                     source_component=191)
    sched = outputs.OutputScheduler(profile=outputs.ODOMETRY_PROFILES["px4"])
    sent_att: dict[int, tuple] = {}
    sent_quat: dict[int, tuple] = {}
    stop = threading.Event()

    def sender():
        k = 0
        while not stop.is_set():
            if k % 100 == 0:
                out.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                       mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                       mavutil.mavlink.MAV_STATE_ACTIVE)
            for msg in sched.messages(make_sol(k), time.monotonic()):
                if msg.get_msgId() == 30:
                    sent_att[msg.time_boot_ms] = (msg.roll, msg.pitch, msg.yaw)
                elif msg.get_msgId() == 31:
                    sent_quat[msg.time_boot_ms] = (msg.q1, msg.q2, msg.q3, msg.q4)
                out.mav.send(msg)
            k += 1
            time.sleep(0.005)

    th = threading.Thread(target=sender, daemon=True)
    th.start()
    try:
        client.attach(10.0, OUR_SYSID)
        t_end = time.monotonic() + 10.0
        while time.monotonic() < t_end and (len(client.euler) < 40 or len(client.odometry) < 10
                                            or len(client.named) < 8):
            time.sleep(0.05)
    finally:
        stop.set()
        th.join(2.0)
        client.close()
        out.close()
    assert len(client.euler) >= 40 and len(client.odometry) >= 10 and len(client.named) >= 8
    # attitude_euler: every update matches the ATTITUDE (or the quaternion) we sent at its time
    matched = 0
    for ts_us, roll_deg, pitch_deg, yaw_deg, _ in client.euler:
        t_ms = ts_us // 1000
        assert t_ms in sent_att, t_ms
        r, p, y = sent_att[t_ms]
        assert roll_deg == pytest.approx(math.degrees(r), abs=2e-4)
        assert pitch_deg == pytest.approx(math.degrees(p), abs=2e-4)
        assert wrap180(yaw_deg - math.degrees(y)) == pytest.approx(0.0, abs=2e-4)
        matched += 1
    assert matched == len(client.euler)
    # odometry: q is our attitude; its yaw is our heading; covariance as documented
    for o in client.odometry:
        q = np.array([o.q.w, o.q.x, o.q.y, o.q.z])
        _, _, yaw = euler_from_quat(q)
        k = round((o.time_usec / 1e6 - 10.0) / 0.005)
        assert abs(wrap180(math.degrees(yaw) - math.degrees(make_sol(k).heading_rad))) < 1e-3
        cov = o.pose_covariance.covariance_matrix
        assert len(cov) == 21 and cov[0] == cov[6] == cov[11] == 1e6
        assert cov[20] == pytest.approx(math.radians(2.0) ** 2, rel=1e-6)
        assert (o.position_body.x_m, o.position_body.y_m, o.position_body.z_m) == (0.0, 0.0, 0.0)
        assert math.isnan(o.velocity_body.x_m_s) and math.isnan(o.angular_velocity_body.yaw_rad_s)
    # heading for ground stations: NAMED_VALUE_FLOAT through MAVSDK's MavlinkDirect
    names = {m["name"] for m in client.named}
    assert names == {"phase", "az_deg", "hdg_deg", "hdg_sd_deg"}
    for m in client.named:
        if m["name"] == "hdg_deg":
            k = round((m["time_boot_ms"] / 1e3 - 10.0) / 0.005)
            assert m["value"] == pytest.approx(math.degrees(make_sol(k).heading_rad), abs=0.01)


# --- the running daemon ----------------------------------------------------------------------

def _sitl_module():
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "bench" / "sitl.py"
    spec = importlib.util.spec_from_file_location("azimuthd_bench_sitl", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def start_sitl(mavsdk_port: int, zenoh_listen: str | None = None, rest_s: float = 3.0):
    """Simulator + daemon (bench/sitl.py) with the daemon's outputs mirrored to the harness's
    pymavlink listener AND to MAVSDK's port; optionally Zenoh on a loopback endpoint."""
    import tomllib
    sitl = _sitl_module()
    s = sitl.Sitl(scenario="inclined_rail", speed=1.0,
                  sim_args=["--set", f"launcher.rest_s={rest_s}"])
    with open(s.config_path, "rb") as f:
        cfg = tomllib.load(f)
    cfg["outputs"]["extra_mavlink_urls"] = [f"udpout:127.0.0.1:{s.out_port}",
                                            f"udpout:127.0.0.1:{mavsdk_port}"]
    if zenoh_listen is not None:
        cfg["zenoh"].update({"enabled": True, "mode": "peer", "listen": [zenoh_listen],
                             "connect": []})
    sitl.write_config(s.config_path, cfg)
    return s


def test_mavsdk_reads_the_running_daemon():
    """MAVSDK's attitude_euler equals, sample for sample (same time_boot_ms), the ATTITUDE the
    daemon sent to a second endpoint; yaw is NaN in both while the daemon has no heading."""
    port = free_udp_port()
    client = MavsdkClient(port)
    s = start_sitl(port)
    try:
        with s:
            client.attach(20.0)
            # levelled (roll/pitch sent), launched, and some in-flight samples
            assert s.wait_for(lambda: "in-flight" in s.log("daemon") and len(client.euler) > 100,
                              30.0), s.log("daemon")[-2000:]
            s.wait_for(lambda: False, 2.0)
            listener_att = {round(t * 1000): (r, p, y) for t, r, p, y, _ in s.listener.attitude}
            euler = list(client.euler)
            ids = (client.system.get_system_id(), client.system.component_ids())
    finally:
        client.close()
    assert ids == (1, [191])  # the simulated FC's system id, our component
    matched = 0
    for ts_us, roll_deg, pitch_deg, yaw_deg, _ in euler:
        key = ts_us // 1000
        if key not in listener_att:  # the listener may have started a moment later
            continue
        r, p, y = listener_att[key]
        assert roll_deg == pytest.approx(math.degrees(r), abs=2e-4)
        assert pitch_deg == pytest.approx(math.degrees(p), abs=2e-4)
        if math.isnan(y):
            assert math.isnan(yaw_deg)
        else:
            assert wrap180(yaw_deg - math.degrees(y)) == pytest.approx(0.0, abs=2e-4)
        matched += 1
    assert matched >= 0.9 * len(euler) and matched > 100
    # the rail points the nose 15 deg up; MAVSDK sees that pitch before the launch
    assert any(abs(e[2] - 15.0) < 1.0 for e in euler)
