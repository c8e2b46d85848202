"""The live simulated autopilot, as users run it: `python -m sim ...` in its own process, a
pymavlink client on the other end of UDP.

The machine may be busy: rates are measured in the simulator's own clock (time_usec,
time_boot_ms), counts against what the simulator says it sent (its ``sim stopped: ... sent=``
line) with what the client's kernel dropped accounted, and waits run until a number of messages
or an FC time is reached; the wall clock only detects a hang (conftest.HANG_S)."""
from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import HANG_S, udp_kernel_drops

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
G0 = 9.80665


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class SimProc:
    def __init__(self, *args: str):
        self.port = _free_udp_port()
        self.proc = subprocess.Popen([sys.executable, "-m", "sim", "--mavlink", f"udpin:127.0.0.1:{self.port}", *args],
                                     cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.port}", source_system=255,
                                            source_component=190, dialect="ardupilotmega")
        deadline = time.monotonic() + HANG_S
        self.hb = None
        while self.hb is None and time.monotonic() < deadline:  # udpin: the sim waits for us to speak
            self.c.mav.heartbeat_send(18, 8, 0, 0, 0)
            self.hb = self.c.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
        if self.hb is None:
            self.close()
            raise RuntimeError(f"simulator did not answer: {self.proc.stdout.read() if self.proc.stdout else ''}")

    def command(self, cmd: int, *params: float, timeout: float = HANG_S):
        p = list(params) + [0.0] * (7 - len(params))
        self.c.mav.command_long_send(1, 1, cmd, 0, *p)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            m = self.c.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
            if m is not None and m.command == cmd:
                return m.result
        return None

    def set_rate(self, msg_id: int, hz: float):
        return self.command(511, msg_id, 1e6 / hz if hz > 0 else -1)

    def kernel_drops(self) -> int:
        """Datagrams to this client the kernel dropped (its receive buffer was full)."""
        return udp_kernel_drops(self.c.port)

    def stop(self) -> dict:
        """Stop the simulator; its own account: ``simulated_s``, ``wall_s``, ``achieved_speed``
        and ``sent`` (messages sent, by type) from its ``sim stopped`` line."""
        if self.proc.poll() is None:
            self.proc.terminate()
        out, _ = self.proc.communicate(timeout=HANG_S)
        line = next(ln for ln in out.splitlines() if "sim stopped:" in ln)
        vals = dict(kv.split("=", 1) for kv in line.split("sim stopped:")[1].split())
        return {"simulated_s": float(vals["simulated_s"]), "wall_s": float(vals["wall_s"]),
                "achieved_speed": float(vals["achieved_speed"]), "sent": json.loads(vals["sent"])}

    def close(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.c.close()


@pytest.fixture
def sim_factory():
    procs = []

    def make(*args):
        p = SimProc(*args)
        procs.append(p)
        return p
    yield make
    for p in procs:
        p.close()


def _fc_s(m) -> float:
    """The FC (simulator) time stamp of a message, s."""
    return m.time_usec * 1e-6 if hasattr(m, "time_usec") else m.time_boot_ms * 1e-3


def _collect(c, types, done) -> dict[str, list]:
    """Messages of ``types`` (by type, in arrival order) until ``done(got)``: a count or an FC
    time span reached, whatever the machine's speed. The wall clock only detects a hang."""
    got: dict[str, list] = {t: [] for t in types}
    end = time.monotonic() + HANG_S
    while not done(got):
        assert time.monotonic() < end, f"hang: {({k: len(v) for k, v in got.items()})} after {HANG_S:g} s"
        m = c.recv_match(type=list(types), blocking=True, timeout=0.2)
        if m is not None:
            got[m.get_type()].append(m)
    return got


def _fc_span_s(msgs) -> float:
    return _fc_s(msgs[-1]) - _fc_s(msgs[0]) if len(msgs) > 1 else 0.0


def test_raw_imu_rates_50_200_400_hz_in_fc_time_never_faster_than_real_time(sim_factory):
    """GIVEN the real-time simulator WHEN a client requests RAW_IMU at 50, 200, 400 Hz THEN in
    the simulator's clock the messages come exactly 1/rate apart (time_usec), every missing one is
    a datagram the client's kernel dropped, and the simulator never ran faster than real time (its
    own simulated vs wall time). A busy machine may slow it down: that is no failure."""
    s = sim_factory("--scenario", "inclined_rail", "--duration", "0")
    assert s.hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA and s.hb.type == 1
    # nothing but HEARTBEAT/SIMSTATE before a request: 3 HEARTBEATs (2 s of the simulator's 1 Hz)
    pre = _collect(s.c, ("HEARTBEAT", "RAW_IMU"), lambda g: len(g["HEARTBEAT"]) >= 3)
    assert pre["RAW_IMU"] == []
    for hz in (50.0, 200.0, 400.0):
        assert s.set_rate(27, hz) == 0
        t_asked = _collect(s.c, ("RAW_IMU",), lambda g: len(g["RAW_IMU"]) >= 1)["RAW_IMU"][0]
        settle_s = _fc_s(t_asked) + 0.1  # the request lands between two messages of the old rate
        drops0 = s.kernel_drops()
        got = _collect(s.c, ("RAW_IMU",), lambda g: bool(g["RAW_IMU"]) and _fc_s(g["RAW_IMU"][-1]) >= settle_s + 1.5)
        drops = s.kernel_drops() - drops0
        tus = np.array([m.time_usec for m in got["RAW_IMU"] if _fc_s(m) >= settle_s], dtype=np.int64)
        interval_us = 1e6 / hz
        steps = np.diff(tus) / interval_us
        assert np.all(np.abs(steps - np.round(steps)) * interval_us <= 1.0), (hz, np.unique(np.diff(tus)))
        assert np.all(np.round(steps) >= 1) and np.median(np.diff(tus)) == pytest.approx(interval_us, abs=1.0)
        missing = int(np.sum(np.round(steps) - 1))
        assert missing <= drops, (hz, missing, drops)  # each one lost is counted by the kernel
        assert len(tus) - 1 + missing == round((tus[-1] - tus[0]) / interval_us)
    own = s.stop()
    assert own["achieved_speed"] <= 1.0 + 1e-3, own  # paced: never ahead of the wall clock


def test_live_raw_imu_matches_truth_within_configured_errors(sim_factory, tmp_path):
    """Lockstep-fast run (x10) through rest, boost and climb with known gyro/accel biases, zero
    scale/misalignment, a 20 deg yawed IMU mount and an error-free magnetometer: every RAW_IMU
    matches the truth log (rate, specific force, field, rotated into the sensor frame and averaged
    over the message interval) within bias + 5 sigma noise + half an LSB."""
    log = tmp_path / "truth.npz"
    gb, ab = [0.004, -0.003, 0.002], [0.05, -0.04, 0.03]
    s = sim_factory("--scenario", "inclined_rail", "--speed", "10", "--duration", "30", "--imu-grade", "tactical",
                    "--truth-log", str(log), "--truth-log-rate", "250", "--set", "autopilot.base_rate_hz=250",
                    "--set", "launcher.rest_s=5", "--set", f"imu.gyro_bias_rad_s={gb}",
                    "--set", f"imu.accel_bias_m_s2={ab}", "--set", "imu.gyro_scale=[0,0,0]",
                    "--set", "imu.accel_scale=[0,0,0]", "--set", "imu.gyro_misalignment=[[0,0,0],[0,0,0],[0,0,0]]",
                    "--set", "imu.accel_misalignment=[[0,0,0],[0,0,0],[0,0,0]]",
                    "--set", "imu.mount_euler_deg=[0,0,20]", "--set", "mag.hard_iron_gauss=[0,0,0]",
                    "--set", "mag.soft_iron=[[1,0,0],[0,1,0],[0,0,1]]", "--set", "mag.site_distortion_ned_gauss=[0,0,0]",
                    "--set", "imu.mag_noise_gauss=0.0")
    assert s.set_rate(27, 50) == 0
    msgs = []
    end = time.monotonic() + HANG_S
    while s.proc.poll() is None:  # the whole 30 s flight, however long the machine takes
        assert time.monotonic() < end, "hang"
        m = s.c.recv_match(type="RAW_IMU", blocking=True, timeout=0.2)
        if m is not None:
            msgs.append(m)
    while (m := s.c.recv_match(type="RAW_IMU", blocking=True, timeout=0.5)) is not None:
        msgs.append(m)  # what was still queued when it exited
    own = s.stop()
    z = np.load(log)
    t = z["time_s"]
    C_sb = z["site_C_body_from_sensor"].T
    q = np.column_stack([z["qw"], z["qx"], z["qy"], z["qz"]])
    w_b = np.column_stack([z["omega_x_rad_s"], z["omega_y_rad_s"], z["omega_z_rad_s"]])
    f_b = np.column_stack([z["f_x_m_s2"], z["f_y_m_s2"], z["f_z_m_s2"]])
    B_n = np.column_stack([z["field_n_gauss"], z["field_e_gauss"], z["field_d_gauss"]])
    sent = own["sent"]["RAW_IMU"]
    assert sent >= 1450  # 50 Hz for the 30 s of its own clock, less the time before our request
    assert sent - s.kernel_drops() <= len(msgs) <= sent  # any not received: dropped by our kernel
    n_compared = 0
    base_hz, n_avg = 250, 5  # a 50 Hz message averages 5 base samples
    tact_gyro_sigma = 0.15 * math.pi / 180 / 60 * math.sqrt(base_hz)  # per base sample
    tact_acc_sigma = 30e-6 * G0 * math.sqrt(base_hz)
    worst = np.zeros(3)
    moved = False
    for m in msgs[::7]:
        k = int(round(m.time_usec * 1e-6 * base_hz))
        if k < n_avg + 1 or k >= len(t):
            continue
        sl = slice(k - n_avg + 1, k + 1)  # the base samples the 50 Hz message averages
        w_s = (w_b[sl] @ C_sb.T).mean(0)
        f_s = (f_b[sl] @ C_sb.T).mean(0)
        w_, x, y, zq = q[k]
        C_nb = np.array([[1 - 2 * (y * y + zq * zq), 2 * (x * y - w_ * zq), 2 * (x * zq + w_ * y)],
                         [2 * (x * y + w_ * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w_ * x)],
                         [2 * (x * zq - w_ * y), 2 * (y * zq + w_ * x), 1 - 2 * (x * x + y * y)]])
        b_s = C_sb @ C_nb.T @ B_n[k]
        g_err = np.array([m.xgyro, m.ygyro, m.zgyro]) / 1000.0 - (w_s + gb)
        a_err = np.array([m.xacc, m.yacc, m.zacc]) * G0 / 1000.0 - (f_s + ab)
        m_err = np.array([m.xmag, m.ymag, m.zmag]) / 1000.0 - b_s
        lim_g = 5 * tact_gyro_sigma / math.sqrt(n_avg) + 0.5e-3 + 1e-5
        lim_a = 5 * tact_acc_sigma / math.sqrt(n_avg) + 0.5e-3 * G0 + 2e-3
        assert np.all(np.abs(g_err) < lim_g), (m.time_usec, g_err)
        assert np.all(np.abs(a_err) < lim_a), (m.time_usec, a_err)
        assert np.all(np.abs(m_err) < 0.5e-3 + 1e-6), (m.time_usec, m_err)
        worst = np.maximum(worst, [np.abs(g_err).max(), np.abs(a_err).max(), np.abs(m_err).max()])
        moved |= np.linalg.norm(f_s) > 20.0
        n_compared += 1
    assert moved  # the boost was inside the compared window
    assert n_compared >= 100


def test_rtl_turns_true_heading_toward_home(sim_factory):
    """GIVEN the vehicle climbing away from home on heading 060 WHEN MAV_CMD_NAV_RETURN_TO_LAUNCH
    is sent THEN it is ACCEPTED, HEARTBEAT shows RTL (11), and within 20 s of simulated time the
    true ground track (SIMSTATE) points within 15 deg of home and the distance to home decreases."""
    s = sim_factory("--scenario", "inclined_rail", "--speed", "20", "--duration", "0", "--set", "autopilot.base_rate_hz=200",
                    "--set", "launcher.rest_s=5", "--set", "wind.gust_sigma_m_s=0.0")
    assert s.set_rate(30, 10) == 0
    home = None
    t_boot = 0.0
    while t_boot < 40.0:  # launched at 5 s, climbing out toward 060
        m = s.c.recv_match(type=["SIMSTATE", "ATTITUDE"], blocking=True, timeout=HANG_S)
        assert m is not None, "hang"
        if m.get_type() == "SIMSTATE" and home is None:
            home = (m.lat * 1e-7, m.lng * 1e-7)
        if m.get_type() == "ATTITUDE":
            t_boot = m.time_boot_ms / 1000.0
    assert s.command(20) == 0
    t_cmd = t_boot
    track = []
    mode = None
    while t_boot < t_cmd + 30.0:
        m = s.c.recv_match(type=["SIMSTATE", "ATTITUDE", "HEARTBEAT"], blocking=True, timeout=HANG_S)
        assert m is not None, "hang"
        if m.get_type() == "ATTITUDE":
            t_boot = m.time_boot_ms / 1000.0
        elif m.get_type() == "HEARTBEAT":
            mode = m.custom_mode
        else:
            track.append((t_boot, m.lat * 1e-7, m.lng * 1e-7))
    assert mode == 11

    def brg_dist(lat1, lon1, lat2, lon2):
        la1, la2, dl = math.radians(lat1), math.radians(lat2), math.radians(lon2 - lon1)
        b = math.atan2(math.sin(dl) * math.cos(la2), math.cos(la1) * math.sin(la2) - math.sin(la1) * math.cos(la2) * math.cos(dl))
        d = 6371e3 * math.hypot(la2 - la1, dl * math.cos(la1))
        return math.degrees(b) % 360, d

    ok_after = None
    for (t0, a0, b0), (t1, a1, b1) in zip(track[:-1], track[1:]):
        if t1 - t0 <= 0:
            continue
        course, _ = brg_dist(a0, b0, a1, b1)
        to_home, _ = brg_dist(a1, b1, *home)
        err = (course - to_home + 180) % 360 - 180
        if abs(err) < 15 and ok_after is None:
            ok_after = t1 - t_cmd
    d_start = brg_dist(*home, *track[0][1:])[1]
    d_end = brg_dist(*home, *track[-1][1:])[1]
    assert ok_after is not None and ok_after < 20.0, ok_after
    assert d_end < d_start - 100.0


def test_px4_personality_sends_highres_imu_and_no_raw_imu(sim_factory):
    s = sim_factory("--scenario", "vertical_launch", "--personality", "px4", "--duration", "0")
    assert s.hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_PX4
    assert s.set_rate(27, 100) == 4  # RAW_IMU: FAILED, this autopilot does not have it
    assert s.set_rate(105, 100) == 0
    got = _collect(s.c, ("HIGHRES_IMU", "RAW_IMU"), lambda g: _fc_span_s(g["HIGHRES_IMU"]) >= 1.0)
    assert got["RAW_IMU"] == []  # none in a second of its clock
    hr = got["HIGHRES_IMU"]
    assert np.median(np.diff([m.time_usec for m in hr])) == pytest.approx(10_000, abs=1)  # 100 Hz, FC clock
    m = hr[-1]
    # nose-up on the tube at rest: x axis up -> specific force +g along x
    assert m.xacc == pytest.approx(9.81, abs=0.3) and abs(m.zacc) < 0.5
    assert m.fields_updated & 0x1FFF == 0x1FFF


def test_reboot_fault_restarts_time_boot_and_forgets_stream_rates(sim_factory):
    """GIVEN an FC reboot at 5 s (1 s silence) WHEN it happens THEN the streams stop (rates back to
    defaults), and after a new request time_usec has restarted near zero."""
    s = sim_factory("--scenario", "inclined_rail", "--duration", "0", "--speed", "2",
                    "--set", "faults.reboot_at_s=5.0", "--set", "faults.reboot_silence_s=1.0")
    assert s.set_rate(27, 50) == 0
    # HEARTBEAT (1 Hz) is sent at whole seconds of the FC clock: of the three after a RAW_IMU from
    # 4.5 s on, the first is at 5 s (sent with the last RAW_IMU, or not at all: the reboot), the
    # second and third are the new boot's (after the 5-6 s silence). Between those two, nothing
    # from the stream requested before the reboot.
    after: list = []  # messages in arrival order once a RAW_IMU from 4.5 s on was seen
    before = 0
    end = time.monotonic() + HANG_S
    while sum(m.get_type() == "HEARTBEAT" for m in after) < 3:
        assert time.monotonic() < end, ("hang", before, [m.get_type() for m in after])
        m = s.c.recv_match(type=["RAW_IMU", "HEARTBEAT"], blocking=True, timeout=0.2)
        if m is None:
            continue
        if before > 4.5e6:
            after.append(m)
        elif m.get_type() == "RAW_IMU":
            before = max(before, m.time_usec)
    hb = [i for i, m in enumerate(after) if m.get_type() == "HEARTBEAT"]
    assert all(m.time_usec <= 5_000_000 for m in after[:hb[1]] if m.get_type() == "RAW_IMU")
    assert [m.get_type() for m in after[hb[1]:]] == ["HEARTBEAT"] * 2  # stopped: rates back to defaults
    assert s.set_rate(27, 50) == 0
    m = s.c.recv_match(type="RAW_IMU", blocking=True, timeout=HANG_S)
    assert m is not None and m.time_usec < 3.0e6  # time_boot restarted near zero


def test_gnss_loss_is_signalled_in_sys_status_and_ekf_flags(sim_factory):
    s = sim_factory("--scenario", "runway_gnss_denied", "--duration", "0", "--speed", "5",
                    "--set", "gnss.lost_at_s=4.0")
    assert s.set_rate(1, 5) == 0 and s.set_rate(193, 5) == 0
    # 8 s of the simulator's clock at 5 Hz: GNSS lost at 4 s
    got = _collect(s.c, ("SYS_STATUS", "EKF_STATUS_REPORT"),
                   lambda g: min(len(g["SYS_STATUS"]), len(g["EKF_STATUS_REPORT"])) >= 40)
    seen = {"gps_ok": False, "gps_lost": False, "ekf_ok": False, "ekf_degraded": False}
    for m in got["SYS_STATUS"]:
        seen["gps_ok" if m.onboard_control_sensors_health & 32 else "gps_lost"] = True
    for m in got["EKF_STATUS_REPORT"]:
        seen["ekf_ok" if m.flags & 16 else "ekf_degraded"] = True
    assert all(seen.values()), seen


def test_cli_bad_arguments_and_listing():
    from sim.cli import main
    assert main(["--imu-grade", "navigation"]) == 2
    assert main(["--scenario", "no_such_scenario", "--mavlink", "udpin:127.0.0.1:0"]) == 2
    assert main(["--list-scenarios"]) == 0


def _track_until(s, t_end, types=("SIMSTATE", "ATTITUDE", "HEARTBEAT")):
    """Collect (time_boot_s, msg) until ATTITUDE says time_boot >= t_end (ATTITUDE must stream)."""
    out, t = [], 0.0
    while t < t_end:
        m = s.c.recv_match(type=list(types), blocking=True, timeout=1.0)
        assert m is not None
        if m.get_type() == "ATTITUDE":
            t = m.time_boot_ms / 1000.0
        out.append((t, m))
    return out


def _bearing_deg(lat1, lon1, lat2, lon2):
    la1, la2, dl = map(math.radians, (lat1, lat2, lon2 - lon1))
    return math.degrees(math.atan2(math.sin(dl) * math.cos(la2),
                                   math.cos(la1) * math.sin(la2) - math.sin(la1) * math.cos(la2) * math.cos(dl))) % 360


def test_reposition_loiter_mode_and_external_yaw_are_obeyed(sim_factory, tmp_path):
    """DO_REPOSITION (COMMAND_INT) to a point 1.5 km south-east: ACCEPTED, GUIDED (15), and within
    25 s the ground track points at it; then DO_SET_MODE LOITER (12): the vehicle circles (stays
    within 3 loiter radii of where it was). ODOMETRY yaws sent meanwhile land in the truth log."""
    log = tmp_path / "t.npz"
    s = sim_factory("--scenario", "inclined_rail", "--speed", "25", "--duration", "0", "--truth-log", str(log),
                    "--set", "autopilot.base_rate_hz=200",
                    "--set", "launcher.rest_s=2", "--set", "wind.gust_sigma_m_s=0.0")
    assert s.set_rate(30, 10) == 0
    tr = _track_until(s, 35.0)
    home = next((m.lat * 1e-7, m.lng * 1e-7) for _, m in tr if m.get_type() == "SIMSTATE")
    tgt = (home[0] - 0.0095, home[1] + 0.014)  # ~1.05 km S, ~0.95 km E at 47.4 N
    s.c.mav.command_int_send(1, 1, mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 192, 0, 0,
                             -1, 0, 0, float("nan"), int(tgt[0] * 1e7), int(tgt[1] * 1e7), 120.0)
    ack = s.c.recv_match(type="COMMAND_ACK", blocking=True, timeout=3.0)
    assert ack is not None and ack.command == 192 and ack.result == 0
    q = [math.cos(0.5), 0.0, 0.0, math.sin(0.5)]  # yaw 1 rad
    s.c.mav.odometry_send(0, 1, 2, float("nan"), float("nan"), float("nan"), q, float("nan"), float("nan"),
                          float("nan"), float("nan"), float("nan"), float("nan"), [float("nan")] * 20 + [0.01],
                          [float("nan")] * 21)
    t_cmd = tr[-1][0]
    tr = _track_until(s, t_cmd + 25.0)
    assert any(m.get_type() == "HEARTBEAT" and m.custom_mode == 15 for _, m in tr)
    pos = [(t, m.lat * 1e-7, m.lng * 1e-7) for t, m in tr if m.get_type() == "SIMSTATE"]
    (_, a0, b0), (_, a1, b1) = pos[-3], pos[-1]
    err = (_bearing_deg(a0, b0, a1, b1) - _bearing_deg(a1, b1, *tgt) + 180) % 360 - 180
    assert abs(err) < 15.0
    assert s.command(176, 1, 12) == 0  # ArduPlane LOITER
    t_l = tr[-1][0]
    tr = _track_until(s, t_l + 40.0)
    assert any(m.get_type() == "HEARTBEAT" and m.custom_mode == 12 for _, m in tr)
    pos = np.array([(m.lat * 1e-7, m.lng * 1e-7) for _, m in tr if m.get_type() == "SIMSTATE"])
    d_m = np.hypot((pos[:, 0] - a1) * 111.2e3, (pos[:, 1] - b1) * 111.2e3 * math.cos(math.radians(a1)))
    assert d_m.max() < 3 * 120.0 + 50.0
    assert s.command(176, 1, 7) == 2  # a mode the simulator does not fly: DENIED
    s.close()
    z = np.load(log)
    assert z["ext_yaw_rad"].size == 1 and z["ext_yaw_rad"][0] == pytest.approx(1.0, abs=1e-6)
    assert z["ext_yaw_var_rad2"][0] == pytest.approx(0.01)


def test_link_faults_drop_duplicate_corrupt_and_request_data_stream(sim_factory):
    """20 % drops, 10 % duplicates, 5 % corrupted packets on RAW_IMU requested with the legacy
    REQUEST_DATA_STREAM at 100 Hz: the client sees ~ (1 - 0.2) * 1.1 * (1 - 0.05) of the messages,
    repeated time_usec values, and CRC errors; the stream keeps going. 10 % of the ATTITUDE
    messages carry a NaN angle."""
    s = sim_factory("--scenario", "inclined_rail", "--duration", "0", "--speed", "2", "--seed", "4",
                    "--set", "faults.drop_rate=0.2", "--set", "faults.duplicate_rate=0.1",
                    "--set", "faults.corrupt_rate=0.05", "--set", "faults.nan_rate=0.1")
    s.c.mav.request_data_stream_send(1, 1, 1, 100, 1)
    s.c.mav.request_data_stream_send(1, 1, 10, 50, 1)
    _collect(s.c, ("RAW_IMU",), lambda g: len(g["RAW_IMU"]) >= 10)  # the requested rate is on
    drops0 = s.kernel_drops()
    both = _collect(s.c, ("RAW_IMU", "ATTITUDE"),  # 6 s of the simulator's clock
                    lambda g: min(_fc_span_s(g["RAW_IMU"]), _fc_span_s(g["ATTITUDE"])) >= 6.0)
    drops = s.kernel_drops() - drops0
    att = both["ATTITUDE"]
    n_nan = sum(not all(math.isfinite(v) for v in (m.roll, m.pitch, m.yaw)) for m in att)
    assert 0.04 * len(att) < n_nan < 0.2 * len(att), (n_nan, len(att))
    tus = [m.time_usec for m in both["RAW_IMU"]]
    span_samples = (tus[-1] - tus[0]) * 1e-6 * 100 + 1
    ratio = len(tus) / span_samples
    assert 0.70 < (len(tus) + drops) / span_samples and ratio < 0.97, (ratio, drops)  # our kernel's drops are not the fault's
    assert len(tus) - len(set(tus)) > 5  # duplicates
    assert s.c.mav.total_receive_errors > 0  # corrupted packets were rejected by CRC


def test_mag_dropout_sends_zero_mag_and_clears_health(sim_factory):
    s = sim_factory("--scenario", "inclined_rail", "--duration", "0", "--speed", "2",
                    "--set", 'faults.sensor_dropouts=[{sensor="mag", start_s=0.0, end_s=100.0}]')
    assert s.set_rate(27, 50) == 0 and s.set_rate(1, 5) == 0
    got = _collect(s.c, ("RAW_IMU", "SYS_STATUS"), lambda g: len(g["RAW_IMU"]) >= 50 and len(g["SYS_STATUS"]) >= 5)
    assert all((m.xmag, m.ymag, m.zmag) == (0, 0, 0) for m in got["RAW_IMU"])
    assert all(m.zacc < -900 for m in got["RAW_IMU"])  # the rest of the IMU still flows
    assert all(not m.onboard_control_sensors_health & 4 for m in got["SYS_STATUS"])


def test_ground_station_basics_params_scaled_imu_vfr_hud(sim_factory):
    """What MAVProxy/QGroundControl need: a parameter list that completes, PARAM_SET echoed,
    SCALED_IMU and VFR_HUD on request, AUTOPILOT_VERSION on REQUEST_MESSAGE."""
    s = sim_factory("--scenario", "inclined_rail", "--duration", "0")
    s.c.mav.param_request_list_send(1, 1)
    vals = {}
    end = time.monotonic() + HANG_S
    count = None
    while time.monotonic() < end and (count is None or len(vals) < count):
        m = s.c.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.3)
        if m is not None:
            vals[m.param_id] = m.param_value
            count = m.param_count
    assert count is not None and len(vals) == count and vals["SYSID_THISMAV"] == 1.0
    s.c.mav.param_set_send(1, 1, b"EK3_SRC1_YAW", 6.0, 9)
    m = s.c.recv_match(type="PARAM_VALUE", blocking=True, timeout=2.0)
    assert m is not None and m.param_id == "EK3_SRC1_YAW" and m.param_value == 6.0
    assert s.set_rate(26, 20) == 0 and s.set_rate(74, 5) == 0
    s.c.mav.command_long_send(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0)  # REQUEST_MESSAGE AUTOPILOT_VERSION
    got = _collect(s.c, ("SCALED_IMU", "VFR_HUD", "AUTOPILOT_VERSION", "COMMAND_ACK"),
                   lambda g: len(g["SCALED_IMU"]) >= 15 and len(g["VFR_HUD"]) >= 3 and g["AUTOPILOT_VERSION"]
                   and any(a.command == 512 for a in g["COMMAND_ACK"]))
    assert next(a.result for a in got["COMMAND_ACK"] if a.command == 512) == 0
    assert np.median(np.diff([x.time_boot_ms for x in got["SCALED_IMU"]])) == 50  # 20 Hz in the FC clock
    m = got["SCALED_IMU"][-1]
    assert m.zacc < -900 and m.xacc > 200  # at rest on the 15 deg rail
