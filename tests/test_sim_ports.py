"""`azimuthd sim` serving several MAVLink ports, one of them a serial port (a pty pair, as a
hardware-in-the-loop bench wires it): every port gets the FC's messages, and what a companion
sends on one port reaches a ground station on another, as an FC's MAVLink routing forwards it."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import free_udp_port  # noqa: E402

WAIT_S = 90.0  # a bound for a busy machine, never a timing assertion


class PtyPeer:
    """The companion computer's end of the serial link: the pty master, parsed with pymavlink."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        os.set_blocking(self.master, False)
        self.device = os.ttyname(self.slave)
        self.mav = ardupilotmega.MAVLink(self, srcSystem=1, srcComponent=191)
        self.rx: list = []

    def write(self, buf) -> None:
        os.write(self.master, bytes(buf))

    def poll(self) -> None:
        try:
            data = os.read(self.master, 65536)
        except (BlockingIOError, OSError):
            return
        self.rx += self.mav.parse_buffer(data) or []

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


def _wait(cond, polls, timeout_s: float = WAIT_S) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        for p in polls:
            p()
        if cond():
            return True
        time.sleep(0.02)
    return False


def test_serial_and_udp_ports_with_forwarding(tmp_path):
    pty = PtyPeer()
    gcs_port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190)
    gcs_rx: list = []

    def gcs_poll():
        while (m := gcs.recv_msg()) is not None:
            gcs_rx.append(m)

    log = open(tmp_path / "sim.log", "w")
    sim = subprocess.Popen([sys.executable, "-m", "service.cli", "sim", "--scenario", "inclined_rail",
                            "--mavlink", f"serial:{pty.device}:57600", "--mavlink", f"udpout:127.0.0.1:{gcs_port}",
                            "--speed", "1", "--duration", "120"], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    try:
        # GIVEN the simulator on a serial port and a UDP port THEN both get the FC's HEARTBEAT
        def fc_heartbeat(msgs):
            return any(m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1 and m.get_srcComponent() == 1
                       for m in msgs)
        assert _wait(lambda: fc_heartbeat(pty.rx) and fc_heartbeat(gcs_rx), [pty.poll, gcs_poll]), \
            (tmp_path / "sim.log").read_text()

        # WHEN the companion sends on the serial port THEN the ground station on UDP gets it
        pty.mav.named_value_float_send(1234, b"azimuth", 231.5)
        assert _wait(lambda: any(m.get_type() == "NAMED_VALUE_FLOAT" and m.get_srcComponent() == 191
                                 for m in gcs_rx), [pty.poll, gcs_poll])

        # WHEN the ground station commands the FC itself THEN the FC answers on every port, and the
        # command (for the FC only) is not forwarded to the companion
        gcs.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                  mavutil.mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
        assert _wait(lambda: any(m.get_type() == "AUTOPILOT_VERSION" for m in pty.rx)
                     and any(m.get_type() == "AUTOPILOT_VERSION" for m in gcs_rx), [pty.poll, gcs_poll])
        assert not any(m.get_type() == "COMMAND_LONG" for m in pty.rx)
        assert sim.poll() is None
    finally:
        sim.send_signal(signal.SIGTERM)
        rc = sim.wait(30)
        log.close()
        gcs.close()
        pty.close()
    text = (tmp_path / "sim.log").read_text()
    assert rc == 0, text
    assert "serving 2 MAVLink ports" in text and "Traceback" not in text


def test_bad_endpoint_is_one_line_exit_2():
    out = subprocess.run([sys.executable, "-m", "service.cli", "sim", "--mavlink", "udpin:127.0.0.1"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert out.stderr.strip() == "azimuthd sim: error: bad MAVLink URL 'udpin:127.0.0.1': missing port: expected HOST:PORT"
