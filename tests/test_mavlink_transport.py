"""Serial (pty), TCP client with reconnect, TCP server: the link over every stream transport."""
import os
import pty
import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.samples import ImuSample


class _FdWriter:
    def __init__(self, write):
        self.write = write


def _fc_mav(write, sysid=1):
    return mavlink2.MAVLink(_FdWriter(write), srcSystem=sysid, srcComponent=1)


def _heartbeat(mav):
    mav.heartbeat_send(mavlink2.MAV_TYPE_FIXED_WING, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)


def _poll_until(link, cond, timeout_s=2.0, also=None):
    items = []
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        items += link.poll(0.01)
        if also is not None:
            also()
        if cond(items):
            break
    return items


def _kinds(items):
    return [i.kind for i in items if isinstance(i, LinkEvent)]


def _read_all(read):
    parser = mavlink2.MAVLink(None)
    out = []
    while True:
        try:
            data = read()
        except (BlockingIOError, OSError):
            break
        if not data:
            break
        out += parser.parse_buffer(data) or []
    return out


def test_serial_pty_heartbeat_and_decode():
    master, slave = pty.openpty()
    name = os.ttyname(slave)
    os.close(slave)
    os.set_blocking(master, False)
    link = MavlinkLink(LinkConfig(url=f"serial:{name}:921600"))
    try:
        fc = _fc_mav(lambda b: os.write(master, bytes(b)))
        _heartbeat(fc)
        fc.raw_imu_send(5_000_000, 0, 0, -1000, 10, 0, 0, 100, 0, 0)
        items = _poll_until(link, lambda it: any(isinstance(i, ImuSample) for i in it))
        assert "autopilot_detected" in _kinds(items) and link.connected
        imu = [i for i in items if isinstance(i, ImuSample)]
        assert imu[0].time_fc_s == pytest.approx(5.0) and imu[0].gyro_rad_s[0] == pytest.approx(0.01)
        time.sleep(0.05)
        got = _read_all(lambda: os.read(master, 4096))
        types = [m.get_type() for m in got]
        assert "HEARTBEAT" in types and "COMMAND_LONG" in types  # serial sends before learning too
        # the port disappears (USB unplugged): counted, reported, no exception
        os.close(master)
        items = _poll_until(link, lambda it: "transport_error" in _kinds(it), timeout_s=1.0)
        assert "transport_error" in _kinds(items) and "link_lost" in _kinds(items)
        assert not link.connected and link.stats.transport_errors >= 1
        link.poll(0.01)
    finally:
        link.close()


def test_serial_device_missing_at_start_does_not_raise():
    link = MavlinkLink(LinkConfig(url="serial:/dev/does-not-exist-azimuthd:57600", reconnect_backoff_s=0.01,
                                  reconnect_backoff_max_s=0.02))
    try:
        items = link.poll(0.05) + link.poll(0.05)
        assert "transport_error" in _kinds(items) and "/dev/does-not-exist-azimuthd" in link.last_error
        assert link.stats.transport_errors >= 2  # it keeps retrying
    finally:
        link.close()


def test_tcp_client_reconnects_and_rerequests_rates():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(2.0)
    port = server.getsockname()[1]
    link = MavlinkLink(LinkConfig(url=f"tcp:127.0.0.1:{port}", reconnect_backoff_s=0.05, ack_timeout_s=0.05,
                                  request_tries=1))
    try:
        link.poll(0.01)
        conn, _ = server.accept()
        conn.setblocking(False)
        fc = _fc_mav(conn.sendall)
        _heartbeat(fc)
        items = _poll_until(link, lambda it: "autopilot_detected" in _kinds(it))
        assert link.connected
        conn.close()  # the FC side drops the TCP connection
        items = _poll_until(link, lambda it: "link_lost" in _kinds(it))
        assert "transport_error" in _kinds(items) and "link_lost" in _kinds(items)
        conn2 = None

        def accept():
            nonlocal conn2
            if conn2 is None:
                server.settimeout(0.0)
                try:
                    conn2, _ = server.accept()
                except BlockingIOError:
                    pass
        items = _poll_until(link, lambda it: "reconnect" in _kinds(it), also=accept)
        assert "reconnect" in _kinds(items) and link.stats.reconnects == 1
        while conn2 is None:
            accept()
        conn2.setblocking(False)
        fc = _fc_mav(conn2.sendall)
        _heartbeat(fc)
        items = _poll_until(link, lambda it: "rates_requested" in _kinds(it))
        assert _kinds(items)[:2] == ["link_restored", "rates_requested"] and link.connected
        time.sleep(0.05)
        got = _read_all(lambda: conn2.recv(4096))
        assert any(m.get_type() == "COMMAND_LONG" and m.command == 511 for m in got)
        conn2.close()
    finally:
        link.close()
        server.close()


def test_tcpin_serves_a_client():
    link = MavlinkLink(LinkConfig(url="tcpin:127.0.0.1:0"))
    try:
        port = link.local_address[1]
        cli = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        cli.setblocking(False)
        fc = _fc_mav(cli.sendall, sysid=7)
        _heartbeat(fc)
        _poll_until(link, lambda it: "autopilot_detected" in _kinds(it))
        assert link.target_system == 7
        _poll_until(link, lambda it: False, timeout_s=0.05)
        got = _read_all(lambda: cli.recv(4096))
        hb = [m for m in got if m.get_type() == "HEARTBEAT"]
        assert hb and (hb[0].get_srcSystem(), hb[0].get_srcComponent()) == (7, 191)
        cli.close()
        link.poll(0.02)  # client gone: back to listening, no error
        assert link.stats.transport_errors == 0
    finally:
        link.close()


def test_udpout_sends_heartbeat_before_hearing_anything():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(1.0)
    link = MavlinkLink(LinkConfig(url=f"udpout:127.0.0.1:{rx.getsockname()[1]}", system_id=3))
    try:
        link.poll(0.0)
        data, _ = rx.recvfrom(1024)
        hb = mavlink2.MAVLink(None).parse_buffer(data)[0]
        assert hb.get_type() == "HEARTBEAT" and (hb.get_srcSystem(), hb.get_srcComponent()) == (3, 191)
    finally:
        link.close()
        rx.close()


def test_serial_slow_reader_gets_whole_frames_only():
    """A full serial buffer never puts half a frame on the wire: frames queue whole, the overflow
    is dropped whole and counted, the rest is flushed by poll()."""
    master, slave = pty.openpty()
    name = os.ttyname(slave)
    os.close(slave)
    os.set_blocking(master, False)
    link = MavlinkLink(LinkConfig(url=f"serial:{name}:115200", system_id=1))
    try:
        sent = sum(link.send(link.mav.attitude_encode(k, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)) for k in range(12000))
        assert 0 < sent < 12000 and link.stats.send_errors == 12000 - sent  # the overflow, counted
        parser = mavlink2.MAVLink(None)
        got = []
        t_end = time.monotonic() + 5.0
        while time.monotonic() < t_end and len(got) < sent:
            link.poll(0.001)
            try:
                got += [m for m in (parser.parse_buffer(os.read(master, 65536)) or [])]
            except BlockingIOError:
                pass
        att = [m for m in got if m.get_type() == "ATTITUDE"]
        assert len(att) == sent and not [m for m in got if m.get_type() == "BAD_DATA"]
        assert [m.time_boot_ms for m in att] == sorted(m.time_boot_ms for m in att)
    finally:
        link.close()
        os.close(master)
