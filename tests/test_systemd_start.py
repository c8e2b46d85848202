"""The daemon's start as systemd (Type=notify) sees it: READY=1 arrives, and what the start costs in
CPU seconds stays under a bound (issue 19: start to READY <= 2 s). CPU, not wall time: on a busy
machine the wall time is the scheduler's, the CPU time is the work the start needs."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import free_udp_port, write_config  # noqa: E402

HANG_S = 300.0   # a hang detector for a busy machine, never a timing assertion
CPU_TO_READY_MAX_S = 1.6
"""Measured (bench/daemon_start.py, modules compiled from source as in this test's environment,
load 10): 1.08-1.17 s of CPU after the change, 2.83-2.93 s while KF1/KF2 imported filterpy (and
scipy.stats through it) and the daemon imported pymavlink's mavutil (its "all" dialects)."""
HEAVY_MODULES = ("scipy", "filterpy", "matplotlib", "pandas", "pymavlink.mavutil", "pymavlink.dialects.v20.all")


def test_ready_arrives_and_the_start_costs_under_the_cpu_bound(tmp_path):
    # GIVEN the daemon with a NOTIFY_SOCKET, as the unit starts it (no FC, zenoh off)
    cfg = write_config(tmp_path / "azimuthd.toml", {
        "mavlink": {"url": f"udpin:127.0.0.1:{free_udp_port()}"}, "site": {"lat_deg": 47.0, "lon_deg": 8.0},
        "service": {"state_dir": str(tmp_path / "state")}, "zenoh": {"enabled": False},
        "outputs": {"extra_mavlink_urls": []}})
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.settimeout(0.2)
    env = dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify.sock"))
    with open(tmp_path / "daemon.log", "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "run", "--config", str(cfg)], cwd=ROOT,
                                env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        # WHEN READY=1 arrives
        daemon = psutil.Process(proc.pid)
        t_hang = time.monotonic() + HANG_S
        ready = None
        while ready is None:
            try:
                msg = sock.recv(4096).decode()
            except TimeoutError:
                assert proc.poll() is None, f"daemon exited {proc.returncode}: {(tmp_path / 'daemon.log').read_text()}"
                assert time.monotonic() < t_hang, "no READY=1 (hang detector)"
                continue
            if "READY=1" in msg:
                ready = msg
                cpu = daemon.cpu_times()
    finally:
        proc.terminate()
        proc.wait(60.0)
        sock.close()
    # THEN the start cost less CPU than the bound, and the daemon stopped cleanly on SIGTERM
    cpu_s = cpu.user + cpu.system
    assert cpu_s <= CPU_TO_READY_MAX_S, f"start to READY cost {cpu_s:.2f} s of CPU"
    assert proc.returncode == 0


def test_the_daemon_imports_no_heavy_module():
    # GIVEN a fresh interpreter WHEN it imports what `azimuthd run` imports before READY
    code = ("import sys, service.cli, service.daemon; "
            f"print(' '.join(m for m in {HEAVY_MODULES!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    # THEN none of the modules that cost a start whole seconds is loaded
    assert out.stdout.split() == []
