"""The daemon under systemd (Type=notify), as its own process with a NOTIFY_SOCKET we listen on:
READY=1 once it is up, before any flight controller answers; "waiting for heartbeat" until one
does; SIGHUP saves and checks the config but never stops it; a bad host is refused at start."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import free_udp_port, write_config  # noqa: E402

WAIT_S = 90.0  # a bound for a busy machine, never a timing assertion


def _config(tmp: Path, port: int, **outputs) -> Path:
    return write_config(tmp / "azimuthd.toml", {
        "mavlink": {"url": f"udpin:127.0.0.1:{port}"}, "site": {"lat_deg": 47.0, "lon_deg": 8.0},
        "service": {"state_dir": str(tmp / "state")}, "zenoh": {"enabled": False}, "outputs": outputs})


class Notifications:
    """The NOTIFY_SOCKET end systemd would hold."""

    def __init__(self, path: Path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.seen: list[str] = []

    def wait_for(self, pred, timeout_s: float = WAIT_S) -> str:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            self.sock.settimeout(max(0.05, t_end - time.monotonic()))
            try:
                msg = self.sock.recv(4096).decode()
            except (TimeoutError, socket.timeout):
                break
            self.seen.append(msg)
            if pred(msg):
                return msg
        raise AssertionError(f"no such notification; got {self.seen}")


def _wait_log(path: Path, text: str, proc: subprocess.Popen, timeout_s: float = WAIT_S) -> str:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        log = path.read_text()
        if text in log:
            return log
        assert proc.poll() is None, f"daemon exited {proc.returncode}:\n{log}"
        time.sleep(0.1)
    raise AssertionError(f"{text!r} not logged:\n{path.read_text()}")


def _fake_fc_heartbeat(port: int) -> None:
    from pymavlink import mavutil
    fc = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        fc.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_FIXED_WING, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                              0, 0, mavutil.mavlink.MAV_STATE_STANDBY)
    finally:
        fc.close()


def test_ready_before_the_fc_then_waiting_then_sighup_never_stops_it(tmp_path):
    port = free_udp_port()
    cfg = _config(tmp_path, port)
    note = Notifications(tmp_path / "notify.sock")
    log_path = tmp_path / "daemon.log"
    env = dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify.sock"))
    with open(log_path, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "run", "--config", str(cfg)], cwd=ROOT,
                                env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        # GIVEN no flight controller WHEN the daemon starts THEN READY=1 (a unit on a bench does not fail)
        first = note.wait_for(lambda m: "READY=1" in m)
        assert first == f"READY=1\nSTATUS=waiting for the flight controller on udpin:127.0.0.1:{port}"
        log = _wait_log(log_path, "waiting for heartbeat on", proc)
        assert f'msg="waiting for heartbeat on udpin:127.0.0.1:{port} (no flight controller has answered yet)"' in log

        # WHEN SIGHUP with the file unchanged THEN state saved, config checked, still running
        proc.send_signal(signal.SIGHUP)
        _wait_log(log_path, 'msg="SIGHUP: the config file is unchanged"', proc)
        assert 'msg="SIGHUP: state saved"' in log_path.read_text()

        # WHEN the file changed THEN the changed keys are named, a restart applies them
        cfg.write_text(cfg.read_text().replace("attitude_hz = 50.0", "attitude_hz = 25.0"))
        proc.send_signal(signal.SIGHUP)
        log = _wait_log(log_path, "SIGHUP: the config file changed", proc)
        assert "changed=outputs.attitude_hz " in log

        # WHEN the file is broken THEN an error naming the key, and the daemon runs on
        cfg.write_text(cfg.read_text().replace("attitude_hz = 25.0", "attitude_hz = 9000.0"))
        proc.send_signal(signal.SIGHUP)
        log = _wait_log(log_path, "SIGHUP: the config file is not valid", proc)
        assert "outputs.attitude_hz: must be in [1, 400], got 9000" in log
        assert proc.poll() is None

        # WHEN the FC's HEARTBEAT arrives THEN STATUS says so (READY was already sent, once)
        _fake_fc_heartbeat(port)
        note.wait_for(lambda m: m == "STATUS=flight controller link up")
        assert sum("READY=1" in m for m in note.seen) == 1
    finally:
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(30)
        note.sock.close()
    assert rc == 0
    assert "Traceback" not in log_path.read_text()


@pytest.mark.parametrize("args, expected", [
    (["--mavlink", "udpin:notahost.invalid:14550"],
     "azimuthd: config error: --mavlink: bad MAVLink URL 'udpin:notahost.invalid:14550': host 'notahost.invalid' "
     "does not resolve"),
    (["--out", "udp://127.0.0.1:14550"],
     "azimuthd: config error: --out: bad MAVLink URL 'udp://127.0.0.1:14550': udp:// listens (MAVSDK's meaning) "
     "and a ground station does not speak first: to send to it write udpout:127.0.0.1:14550"),
    (["--out", "udpbcast:255.255.255.255:14550"], "UDP broadcast is not supported"),
])
def test_bad_urls_stop_the_start_with_one_line(tmp_path, capsys, args, expected):
    from service.cli import main
    cfg = _config(tmp_path, free_udp_port())
    assert main(["run", "--config", str(cfg), *args]) == 2
    err = capsys.readouterr().err
    assert expected in err and len(err.strip().splitlines()) == 1


def test_sighup_saves_what_the_flight_learnt_and_the_loop_runs_on(tmp_path, monkeypatch):
    """GIVEN a daemon whose flight has a magnetometer-error estimate WHEN SIGHUP arrives THEN the
    next loop step writes it to the state directory, and the daemon is not asked to stop."""
    from estimators.mag_error_kf import kf1_init
    from service.config import load
    from service.daemon import Daemon
    cfg = load(_config(tmp_path, free_udp_port()))
    cfg["azimuth"]["solve_in_background"] = False  # no worker process to start and join here
    d = Daemon(cfg)
    learnt = kf1_init()
    monkeypatch.setattr(d.pipeline, "kf1_estimate", lambda: learnt)
    d.open()
    try:
        files_before = set((tmp_path / "state").iterdir()) if (tmp_path / "state").exists() else set()
        d._on_sighup(signal.SIGHUP, None)
        d.step(0.0)
        written = set((tmp_path / "state").iterdir()) - files_before
        assert [p.name for p in written] == [d.calibration.store.path.name]
        assert not d.stop_requested and not d.reload_requested
    finally:
        d.close()
