"""MavlinkLink end to end over loopback UDP (and a pty serial port): a fake autopilot built from
pymavlink's own encoder talks to the link; we check identity, heartbeats, rate requests, decoding,
filtering, fault counting and recovery."""
from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.samples import (CommandAck, FcAttitude, FcEkfStatus, FcHeartbeat, FcSysStatus, ImuSample,
                                PressureSample)

G0 = 9.80665


class _SockWriter:
    def __init__(self, fc):
        self.fc = fc

    def write(self, buf):
        self.fc.sock.sendto(bytes(buf), self.fc.dest)


class FakeFc:
    """A minimal autopilot on a UDP socket: sends what the test tells it, records what it gets."""

    def __init__(self, dest, sysid=1, compid=1, autopilot=mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                 ack_result=mavlink2.MAV_RESULT_ACCEPTED):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.dest = dest
        self.mav = mavlink2.MAVLink(_SockWriter(self), srcSystem=sysid, srcComponent=compid)
        self.parser = mavlink2.MAVLink(None)
        self.autopilot = autopilot
        self.ack_result = ack_result  # None: never ACK
        self.received: list = []
        self.rx_times: dict = {}

    def heartbeat(self, armed=False):
        self.mav.heartbeat_send(mavlink2.MAV_TYPE_FIXED_WING, self.autopilot,
                                mavlink2.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0, 7, mavlink2.MAV_STATE_ACTIVE)

    def pump(self):
        """Read what the link sent; ACK SET_MESSAGE_INTERVAL like an autopilot."""
        while True:
            try:
                data, _ = self.sock.recvfrom(65536)
            except BlockingIOError:
                return
            for m in self.parser.parse_buffer(data) or []:
                self.received.append(m)
                self.rx_times[id(m)] = time.monotonic()
                if (m.get_type() == "COMMAND_LONG" and m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
                        and self.ack_result is not None):
                    self.mav.command_ack_send(m.command, self.ack_result, 0, 0, m.get_srcSystem(), m.get_srcComponent())

    def of_type(self, t):
        return [m for m in self.received if m.get_type() == t]

    def close(self):
        self.sock.close()


def _link(clock=time.monotonic, **kw) -> MavlinkLink:
    kw.setdefault("url", "udpin:127.0.0.1:0")
    return MavlinkLink(LinkConfig(**kw), clock=clock)


def _run(link, fc, seconds, step=0.005):
    """Poll the link and pump the fake FC for a while; return everything the link produced."""
    out = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        out += link.poll(step)
        fc.pump()
    out += link.poll(0.0)
    return out


@pytest.fixture
def pair():
    link = _link()
    fc = FakeFc(("127.0.0.1", link.local_address[1]))
    yield link, fc
    link.close()
    fc.close()


def _events(items, kind=None):
    return [i for i in items if isinstance(i, LinkEvent) and (kind is None or i.kind == kind)]


def test_detects_autopilot_learns_sysid_and_requests_rates(pair):
    link, fc = pair
    fc.mav.srcSystem = 42
    fc.heartbeat()
    items = _run(link, fc, 0.3)
    det = _events(items, "autopilot_detected")
    assert len(det) == 1 and "ardupilot" in det[0].detail
    assert link.fc_autopilot == "ardupilot" and link.target_system == 42 and link.target_component == 1
    assert link.connected
    assert link.mav.srcSystem == 42  # we speak as the vehicle's system
    hb = [i for i in items if isinstance(i, FcHeartbeat)]
    assert hb and hb[0].autopilot == "ardupilot" and hb[0].system_id == 42 and not hb[0].armed
    reqs = [m for m in fc.of_type("COMMAND_LONG") if m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL]
    asked = {int(m.param1): m.param2 for m in reqs}
    # ArduPilot: RAW_IMU at 200 Hz (5000 us), SCALED_PRESSURE 50 Hz, ATTITUDE 50 Hz, EKF + SYS_STATUS 2 Hz
    assert asked[mavlink2.MAVLINK_MSG_ID_RAW_IMU] == pytest.approx(5000.0)
    assert asked[mavlink2.MAVLINK_MSG_ID_SCALED_PRESSURE] == pytest.approx(20000.0)
    assert asked[mavlink2.MAVLINK_MSG_ID_ATTITUDE] == pytest.approx(20000.0)
    assert asked[mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT] == pytest.approx(500000.0)
    assert mavlink2.MAVLINK_MSG_ID_ESTIMATOR_STATUS not in asked
    assert mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU not in asked  # RAW_IMU is enough on ArduPilot
    for m in reqs:
        assert (m.target_system, m.target_component) == (42, 1)
        assert (m.get_srcSystem(), m.get_srcComponent()) == (42, 191)
    assert _events(items, "rates_acked")
    assert link.stats.rate_results["RAW_IMU"] == "accepted"
    assert any(isinstance(i, CommandAck) for i in items)


def test_px4_requests_highres_not_raw_imu(pair):
    link, fc = pair
    fc.autopilot = mavlink2.MAV_AUTOPILOT_PX4
    fc.heartbeat()
    _run(link, fc, 0.3)
    assert link.fc_autopilot == "px4"
    ids = {int(m.param1) for m in fc.of_type("COMMAND_LONG")}
    assert mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU in ids and mavlink2.MAVLINK_MSG_ID_ESTIMATOR_STATUS in ids
    assert mavlink2.MAVLINK_MSG_ID_RAW_IMU not in ids and mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT not in ids


def test_heartbeat_at_1hz_with_our_identity(pair):
    link, fc = pair
    fc.heartbeat()  # udpin: the link can only answer once the FC has talked
    _run(link, fc, 2.25)
    hbs = fc.of_type("HEARTBEAT")
    assert len(hbs) == 3  # t = 0 (as soon as the FC's address is known), 1, 2 s
    dt = np.diff([fc.rx_times[id(h)] for h in hbs])
    np.testing.assert_allclose(dt, [1.0, 1.0], atol=0.1)
    for hb in hbs:
        assert hb.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
        assert hb.autopilot == mavlink2.MAV_AUTOPILOT_INVALID
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 191)
        assert hb.get_header().incompat_flags == 0 and hb._msgbuf[0] == 253  # MAVLink 2 frame
    assert link.stats.heartbeats_sent >= len(hbs)


def test_decodes_every_input_message_in_si_units(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    fc.mav.raw_imu_send(1_000_000, 10, -20, -1000, 100, -200, 300, 250, -30, 400)
    fc.mav.scaled_pressure_send(1000, 1013.25, 0.5, 2150)
    fc.mav.attitude_send(1010, 0.1, -0.2, 3.0, 0.01, 0.02, -0.03)
    fc.mav.ekf_status_report_send(mavlink2.EKF_ATTITUDE | mavlink2.EKF_POS_HORIZ_ABS, 0.1, 0.2, 0.3, 0.4, 0.0)
    fc.mav.sys_status_send(7, 7, 3, 250, 12600, -1, -1, 5, 0, 0, 0, 0, 0)
    items = _run(link, fc, 0.15)
    imu = [i for i in items if isinstance(i, ImuSample)]
    assert len(imu) == 1
    s = imu[0]
    assert s.source == "RAW_IMU" and s.time_fc_s == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(s.accel_m_s2, [0.010 * G0, -0.020 * G0, -1.000 * G0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.gyro_rad_s, [0.1, -0.2, 0.3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.mag_gauss, [0.25, -0.03, 0.4], rtol=0, atol=1e-12)
    p = [i for i in items if isinstance(i, PressureSample)][0]
    assert p.press_abs_pa == pytest.approx(101325.0, abs=1e-2) and p.press_diff_pa == pytest.approx(50.0, abs=1e-4)
    assert p.temperature_k == pytest.approx(294.65, abs=1e-9) and p.time_fc_s == pytest.approx(1.0)
    a = [i for i in items if isinstance(i, FcAttitude)][0]
    assert (a.roll_rad, a.pitch_rad, a.yaw_rad) == pytest.approx((0.1, -0.2, 3.0), abs=1e-7)
    assert a.time_fc_s == pytest.approx(1.010)
    np.testing.assert_allclose(a.rates_rad_s, [0.01, 0.02, -0.03], atol=1e-8)
    e = [i for i in items if isinstance(i, FcEkfStatus)][0]
    assert e.attitude_ok and e.horiz_pos_ok and e.source == "EKF_STATUS_REPORT"
    assert e.compass_variance == pytest.approx(0.4, abs=1e-7)
    st = [i for i in items if isinstance(i, FcSysStatus)][0]
    assert st.gyro_healthy is True and st.accel_healthy is True and st.mag_healthy is False
    assert st.baro_healthy is None and st.battery_voltage_v == pytest.approx(12.6)
    assert st.load_fraction == pytest.approx(0.25)
    for i in imu + [p, a]:
        assert i.time_rx_s > 0


def test_ignores_other_components_and_own_echo(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    gimbal = mavlink2.MAVLink(_SockWriter(fc), srcSystem=1, srcComponent=154)
    gimbal.raw_imu_send(2_000_000, 0, 0, -1000, 0, 0, 0, 1, 1, 1)
    echo = mavlink2.MAVLink(_SockWriter(fc), srcSystem=1, srcComponent=191)
    echo.attitude_send(2000, 0, 0, 0, 0, 0, 0)
    gcs = mavlink2.MAVLink(_SockWriter(fc), srcSystem=255, srcComponent=190)
    gcs.heartbeat_send(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    items = _run(link, fc, 0.1)
    assert not [i for i in items if isinstance(i, (ImuSample, FcAttitude))]
    assert link.stats.foreign_messages == 2 and link.stats.own_echoes == 1
    assert link.target_system == 1


def test_corrupt_bytes_are_counted_not_raised(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    good = fc.mav.raw_imu_encode(3_000_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0).pack(fc.mav)
    bad = bytearray(good)
    bad[15] ^= 0xFF  # payload byte: CRC fails
    rng = np.random.default_rng(7)
    fc.sock.sendto(bytes(bad), fc.dest)
    fc.sock.sendto(rng.integers(0, 256, 300, dtype=np.uint8).tobytes().replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00"), fc.dest)
    unknown = bytearray(fc.mav.raw_imu_encode(3_000_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0).pack(fc.mav))
    fc.sock.sendto(bytes(unknown[:7]) + bytes([0x99, 0x99, 0x00]) + bytes(unknown[10:]), fc.dest)  # msgid 39321
    fc.mav.raw_imu_send(3_005_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    items = _run(link, fc, 0.15)
    assert link.stats.crc_errors == 1
    assert link.stats.framing_errors >= 1
    assert link.stats.unknown_ids == 1 and 39321 in link.stats.unknown_id_set
    assert [i.time_fc_s for i in items if isinstance(i, ImuSample)] == [pytest.approx(3.005)]
    d = link.stats.as_dict()
    assert d["crc_errors"] == 1 and d["bad_data"] >= 2
    assert json.loads(json.dumps(d))["unknown_id_set"] == [39321]  # JSON-ready


def test_non_finite_rejected_and_counted(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    fc.mav.attitude_send(100, float("nan"), 0, 0, 0, 0, 0)
    fc.mav.highres_imu_send(1_000_000, 0, 0, -9.8, float("inf"), 0, 0, 0.2, 0, 0.4, 1013.0, 0, 0, 20.0, 0xFFFF)
    fc.mav.scaled_pressure_send(1000, float("nan"), 0.0, 2000)
    items = _run(link, fc, 0.15)
    assert not [i for i in items if isinstance(i, (ImuSample, FcAttitude, PressureSample))]
    assert link.stats.non_finite_rejects == {"ATTITUDE": 1, "HIGHRES_IMU": 1, "SCALED_PRESSURE": 1}


def test_sequence_gaps_counted(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    for k in range(10):
        if k in (3, 4, 7):
            fc.mav.seq = (fc.mav.seq + 1) % 256  # "lost" on the wire
            continue
        fc.mav.raw_imu_send(1_000_000 + 5000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    _run(link, fc, 0.15)
    assert link.stats.seq_lost == 3


def test_rates_rerequested_after_fc_reboot(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    for k in range(5):
        fc.mav.raw_imu_send(600_000_000 + 5000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    _run(link, fc, 0.1)
    n_before = len(fc.of_type("COMMAND_LONG"))
    fc.mav.raw_imu_send(2_000_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)  # time restarted: rebooted
    fc.mav.raw_imu_send(2_005_000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    items = _run(link, fc, 0.3)
    assert len(_events(items, "fc_reboot")) == 1
    assert any("FC rebooted" in e.detail for e in _events(items, "rates_requested"))
    assert len(fc.of_type("COMMAND_LONG")) > n_before
    t = [i.time_fc_s for i in items if isinstance(i, ImuSample)]
    assert len(t) == 2 and t[0] > 600.02 and t[1] - t[0] == pytest.approx(0.005, abs=1e-9)


def test_fallback_to_request_data_stream_without_ack():
    link = _link(ack_timeout_s=0.05, request_tries=2)
    fc = FakeFc(("127.0.0.1", link.local_address[1]), ack_result=None)
    try:
        fc.heartbeat()
        items = _run(link, fc, 0.9)
        sets = [m for m in fc.of_type("COMMAND_LONG") if m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL]
        # two messages in a row without any ACK (2 tries each): the FC does not speak it, give up
        assert [int(m.param1) for m in sets] == [mavlink2.MAVLINK_MSG_ID_RAW_IMU] * 2 + \
            [mavlink2.MAVLINK_MSG_ID_SCALED_PRESSURE] * 2
        assert sorted({m.confirmation for m in sets}) == [0, 1]
        rds = {m.req_stream_id: m.req_message_rate for m in fc.of_type("REQUEST_DATA_STREAM")}
        assert rds == {1: 200, 2: 2, 10: 50, 12: 2}
        assert all(m.start_stop == 1 for m in fc.of_type("REQUEST_DATA_STREAM"))
        assert link.stats.rate_results["RAW_IMU"] == "data_stream"
        assert any("fallback REQUEST_DATA_STREAM" in e.detail for e in _events(items, "rates_requested"))
    finally:
        link.close()
        fc.close()


class FakeClock:
    def __init__(self, t=100.0):
        self.t = t

    def __call__(self):
        return self.t


def test_link_lost_and_restored_rerequests_rates():
    clock = FakeClock()
    link = _link(clock=clock, link_timeout_s=2.0)
    fc = FakeFc(("127.0.0.1", link.local_address[1]))
    try:
        fc.heartbeat()
        _run(link, fc, 0.1)
        assert link.connected
        clock.t += 2.5
        items = _run(link, fc, 0.05)
        assert [e.kind for e in _events(items)] == ["link_lost"] and not link.connected
        n_before = len(fc.of_type("COMMAND_LONG"))
        clock.t += 10.0
        fc.heartbeat()
        items = _run(link, fc, 0.1)
        kinds = [e.kind for e in _events(items)]
        assert kinds[:2] == ["link_restored", "rates_requested"] and link.connected
        assert len(fc.of_type("COMMAND_LONG")) > n_before
        assert link.stats.link_losses == 1
    finally:
        link.close()
        fc.close()


def test_send_never_raises_on_dead_link():
    link = _link()
    msg = link.mav.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert link.send(msg) is False  # udpin: nobody to send to yet
    assert link.stats.send_no_peer >= 1 and link.stats.send_errors == 0
    link.close()
    assert link.send(msg) is False
    assert link.poll(0.01) == []
    assert link.stats.send_errors == 1
    bad = link.mav.attitude_encode(0, "not a number", 0.0, 0.0, 0.0, 0.0, 0.0)
    link2 = _link()
    assert link2.send(bad) is False and link2.stats.send_errors == 1  # cannot pack: counted
    link2.close()


def test_rates_hz_over_window():
    clock = FakeClock()
    link = _link(clock=clock)
    fc = FakeFc(("127.0.0.1", link.local_address[1]))
    try:
        fc.heartbeat()
        _run(link, fc, 0.05)
        for k in range(21):  # 10 ms apart in fake receive time
            fc.mav.raw_imu_send(1_000_000 + 10_000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
            time.sleep(0.002)
            link.poll(0.02)
            clock.t += 0.010
        assert link.stats.rates_hz()["RAW_IMU"] == pytest.approx(100.0, rel=0.05)
        assert link.stats.as_dict()["messages_by_type"]["RAW_IMU"] == 21
    finally:
        link.close()
        fc.close()


def test_time_wrap_and_gap_reported_through_the_link(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    wrap = 1 << 32
    for t_ms in (wrap - 40, wrap - 20, 0, 20):
        fc.mav.scaled_pressure_send(t_ms, 1000.0, 0.0, 2000)
    # ArduPilot's RAW_IMU counter (uint32 us) of the same FC, 49.7 days after boot: wrapped ~1000
    # times already (silently unwrapped: it is its first sample), then a 0.7 s gap > imu_gap_s 0.5
    for dt_s in (0.1, 0.105, 0.805):
        fc.mav.raw_imu_send(round((wrap / 1000.0 + dt_s) * 1e6) % (1 << 32), 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    items = _run(link, fc, 0.15)
    kinds = [e.kind for e in _events(items)]
    assert kinds.count("time_wrap") == 1 and kinds.count("time_gap") == 1
    tp = [p.time_fc_s for p in items if isinstance(p, PressureSample)]
    np.testing.assert_allclose(np.diff(tp), [0.02, 0.02, 0.02], atol=1e-9)
    assert tp[2] == pytest.approx(wrap / 1000.0)
    assert link.stats.time_wraps == 1 and link.stats.time_gaps == 1
    ti = [i.time_fc_s for i in items if isinstance(i, ImuSample)]
    np.testing.assert_allclose(ti, np.array([0.1, 0.105, 0.805]) + wrap / 1000.0, atol=1e-6)


def test_reordered_imu_sample_dropped_never_backwards(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    for t_us in (1_000_000, 1_010_000, 1_005_000, 1_015_000):
        fc.mav.raw_imu_send(t_us, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    items = _run(link, fc, 0.1)
    t = [i.time_fc_s for i in items if isinstance(i, ImuSample)]
    assert t == pytest.approx([1.0, 1.01, 1.015])
    assert link.stats.stale_time_drops == 1 and not _events(items, "fc_reboot")


def test_one_imu_source_only(pair):
    link, fc = pair
    fc.heartbeat()
    _run(link, fc, 0.1)
    for k in range(3):
        fc.mav.raw_imu_send(1_000_000 + 5000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
        fc.mav.scaled_imu_send(1000 + 5 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0)
    items = _run(link, fc, 0.1)
    assert [i.source for i in items if isinstance(i, ImuSample)] == ["RAW_IMU"] * 3


def test_px4_highres_imu_and_pressure_source(pair):
    link, fc = pair
    fc.autopilot = mavlink2.MAV_AUTOPILOT_PX4
    fc.heartbeat()
    _run(link, fc, 0.1)
    fc.mav.highres_imu_send(1_000_000, 0, 0, -9.8, 0, 0, 0.1, 0.2, 0, 0.4, 1000.0, 1.0, 0, 20.0, 0x1FFF)
    items = _run(link, fc, 0.05)
    p = [i for i in items if isinstance(i, PressureSample)]
    assert [x.source for x in p] == ["HIGHRES_IMU"] and p[0].press_abs_pa == pytest.approx(1e5)
    fc.mav.scaled_pressure_send(1010, 1000.5, 0.0, 2000)  # once SCALED_PRESSURE flows it wins
    fc.mav.highres_imu_send(1_020_000, 0, 0, -9.8, 0, 0, 0.1, 0.2, 0, 0.4, 1000.0, 1.0, 0, 20.0, 0x1FFF)
    items = _run(link, fc, 0.05)
    assert [x.source for x in items if isinstance(x, PressureSample)] == ["SCALED_PRESSURE"]
    imu = [x for x in items if isinstance(x, ImuSample)]
    assert imu[0].source == "HIGHRES_IMU" and imu[0].gyro_rad_s[2] == pytest.approx(0.1)


def test_silent_stream_is_rerequested_a_few_times():
    clock = FakeClock()
    link = _link(clock=clock, stream_recheck_s=5.0)
    fc = FakeFc(("127.0.0.1", link.local_address[1]))
    try:
        fc.heartbeat()
        _run(link, fc, 0.1)
        assert link.stats.rate_results["RAW_IMU"] == "accepted"
        n0 = len(fc.of_type("COMMAND_LONG"))
        rerequests = []
        for _ in range(8):  # 8 x 5.5 s with heartbeats but no RAW_IMU at all
            clock.t += 5.5
            fc.heartbeat()
            fc.mav.sys_status_send(0, 0, 0, 0, 0, -1, -1, 0, 0, 0, 0, 0, 0)
            items = _run(link, fc, 0.06)
            rerequests += [e for e in _events(items, "rates_requested") if "silent" in e.detail]
        assert len(rerequests) == 3 and "RAW_IMU" in rerequests[0].detail
        assert "SYS_STATUS" not in rerequests[0].detail  # that one is flowing
        assert len(fc.of_type("COMMAND_LONG")) > n0
    finally:
        link.close()
        fc.close()


@pytest.mark.parametrize("kw, fragment", [
    ({"url": "udpin:0.0.0.0:99999"}, "port 99999 out of range"),
    ({"component_id": 0}, "component_id must be an integer in [1, 255]"),
    ({"system_id": 256}, "system_id must be an integer in [1, 255]"),
    ({"heartbeat_hz": 0.0}, "heartbeat_hz must be in (0, 50]"),
    ({"link_timeout_s": -1.0}, "link_timeout_s must be in (0, 3600]"),
    ({"imu_gap_s": float("nan")}, "imu_gap_s must be in"),
    ({"stream_rates_hz": {"RAW_IMUU": 10.0}}, "unknown MAVLink message 'RAW_IMUU'"),
    ({"stream_rates_hz": {"RAW_IMU": 0.0}}, "stream_rates_hz['RAW_IMU'] must be in (0, 1000] Hz"),
    ({"imu_source": "IMU"}, "imu_source must be 'auto' or one of"),
    ({"reconnect_backoff_s": 2.0, "reconnect_backoff_max_s": 1.0}, "reconnect_backoff_max_s must be >="),
])
def test_link_config_errors_name_the_field(kw, fragment):
    kw.setdefault("url", "udpin:0.0.0.0:14550")
    with pytest.raises(ValueError) as exc:
        LinkConfig(**kw)
    assert fragment in str(exc.value)
