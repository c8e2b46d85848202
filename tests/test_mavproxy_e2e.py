"""End to end as a user wires a vehicle (docs/VEHICLE.md, "With MAVProxy"): the simulator as the
flight controller, MAVProxy (from PyPI, non-interactive) as the router with one --out to azimuthd
and one to the ground station, the daemon mirroring its outputs to the ground station with --out,
and a pymavlink ground station that must see the FC's messages and azimuthd's (component 191)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from pymavlink import mavutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import free_udp_port, scenario_site, write_config  # noqa: E402

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"  # the test extra's MAVProxy, beside this Python
WAIT_S = 150.0  # a bound for a busy machine, never a timing assertion


def test_sim_mavproxy_daemon_ground_station(tmp_path):
    assert MAVPROXY.exists(), f"{MAVPROXY} missing: `make venv` installs MAVProxy (the test extra)"
    fc_port, az_port, gcs_port = free_udp_port(), free_udp_port(), free_udp_port()
    cfg = write_config(tmp_path / "azimuthd.toml", {
        **scenario_site("inclined_rail"), "service": {"state_dir": str(tmp_path / "state")},
        "zenoh": {"enabled": False}})
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190)
    py = [sys.executable, "-m", "service.cli"]
    commands = {
        # the FC waits until MAVProxy (its ground-station side) speaks
        "sim": [*py, "sim", "--scenario", "inclined_rail", "--mavlink", f"udpin:127.0.0.1:{fc_port}", "--speed", "1"],
        # --streamrate=-1: MAVProxy asks for no stream rates, azimuthd asks for its own
        "mavproxy": [sys.executable, str(MAVPROXY), f"--master=udpout:127.0.0.1:{fc_port}",
                     f"--out=udpout:127.0.0.1:{az_port}", f"--out=udpout:127.0.0.1:{gcs_port}",
                     "--streamrate=-1", "--daemon", "--non-interactive", f"--state-basedir={tmp_path}"],
        "daemon": [*py, "run", "--config", str(cfg), "--mavlink", f"udpin:127.0.0.1:{az_port}",
                   "--out", f"udpout:127.0.0.1:{gcs_port}"],
    }
    procs: dict[str, subprocess.Popen] = {}
    logs = {}
    seen: dict[tuple[int, int, str], int] = {}
    try:
        for name in ("daemon", "sim", "mavproxy"):
            logs[name] = open(tmp_path / f"{name}.log", "w")
            procs[name] = subprocess.Popen(commands[name], cwd=ROOT if name != "mavproxy" else tmp_path,
                                           env=dict(os.environ, PYTHONUNBUFFERED="1"),
                                           stdin=subprocess.DEVNULL, stdout=logs[name], stderr=subprocess.STDOUT)
        wanted = {(1, 1, "HEARTBEAT"), (1, 1, "ATTITUDE"), (1, 191, "HEARTBEAT"), (1, 191, "ATTITUDE"),
                  (1, 191, "ODOMETRY")}
        t_end = time.monotonic() + WAIT_S
        while time.monotonic() < t_end and not wanted <= set(seen):
            msg = gcs.recv_match(blocking=True, timeout=0.5)
            if msg is not None and msg.get_type() != "BAD_DATA":
                key = (msg.get_srcSystem(), msg.get_srcComponent(), msg.get_type())
                seen[key] = seen.get(key, 0) + 1
            for name, p in procs.items():
                assert p.poll() is None, f"{name} exited {p.returncode}: {(tmp_path / f'{name}.log').read_text()[-2000:]}"
        # THEN the ground station has the FC (through MAVProxy) and azimuthd (its --out)
        assert wanted <= set(seen), f"missing {wanted - set(seen)}; seen {sorted(seen)}"
        # AND azimuthd's heading feed reached the FC through MAVProxy (the simulated FC logs what it got)
        t_end = time.monotonic() + WAIT_S
        while "external yaw (ODOMETRY from 1/191)" not in (tmp_path / "sim.log").read_text():
            assert time.monotonic() < t_end, "the FC never got azimuthd's ODOMETRY through MAVProxy"
            time.sleep(0.2)
    finally:
        for p in procs.values():
            p.send_signal(signal.SIGTERM)
        for name, p in procs.items():
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(10)
        for f in logs.values():
            f.close()
        gcs.close()
    daemon_log = (tmp_path / "daemon.log").read_text()
    assert "Traceback" not in daemon_log and "level=error" not in daemon_log, daemon_log[-3000:]

