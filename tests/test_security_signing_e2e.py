"""MAVLink 2 signing end to end (issue 10, Security): the daemon as a process, this test as the FC.

GIVEN the daemon with a signing key file (mode 600), debug logging, and this test playing the
flight controller on UDP (unsigned telemetry, as an FC without signing sends) and routing a
ground station's commands to the daemon's component (as ArduPilot routes them)
THEN everything the daemon sends is signed, checked with an independent implementation of the
MAVLink 2 signing spec (hashlib here, not our module, not pymavlink);
WHEN the ground station sends an unsigned command, or one signed with the wrong key, or a signed
one replayed THEN the daemon neither answers nor acts, and says why (once);
WHEN it sends a correctly signed MAV_CMD_REQUEST_MESSAGE THEN the daemon ACKs it and sends the
message;
WHEN the daemon is stopped and started again THEN its outgoing signing timestamp continues above
the last one (persisted in the state directory), so a receiver never sees it go back;
AND nowhere (stdout, stderr at debug level, the state directory) does the key appear, in raw,
hex or base64 form;
AND a key file others can read stops the start with exit 2 and a message naming the file.
"""
from __future__ import annotations

import base64
import hashlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import free_udp_port, write_config  # noqa: E402
from conftest import HANG_S, cpu_seconds, wait_progressing  # noqa: E402
KEY = hashlib.sha256(b"azimuthd e2e test key").digest()
WRONG_KEY = hashlib.sha256(b"not the key").digest()
GCS = (255, 190)


def independent_signature_ok(frame: bytes, key: bytes) -> tuple[bool, int, int]:
    """MAVLink 2 signing spec: sig = SHA-256(key + frame up to and incl. timestamp)[:6].
    Returns (ok, link_id, timestamp)."""
    if frame[0] != 0xFD or not frame[2] & 0x01:
        return False, -1, -1
    ok = hashlib.sha256(key + frame[:-6]).digest()[:6] == frame[-6:]
    return ok, frame[-13], int.from_bytes(frame[-12:-6], "little")


def leaks(text: bytes, key: bytes = KEY) -> list[str]:
    forms = {"raw": key, "hex": key.hex().encode(), "HEX": key.hex().upper().encode(),
             "base64": base64.b64encode(key), "base64-nopad": base64.b64encode(key).rstrip(b"=")}
    return [name for name, f in forms.items() if f in text]


class FakeFc:
    """This test as ArduPilot: HEARTBEAT from 1/1, unsigned; routes a GCS's frames to the daemon."""

    def __init__(self, daemon_port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.dest = ("127.0.0.1", daemon_port)
        self.fc = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mav2.MAVLink(None)  # no key: decodes signed frames without judging them
        self.parser.robust_parsing = True
        self.received: list = []

    def heartbeat(self) -> None:
        self.send(self.fc.heartbeat_encode(mav2.MAV_TYPE_FIXED_WING, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                           mav2.MAV_STATE_STANDBY).pack(self.fc))

    def send(self, frame: bytes) -> None:
        self.sock.sendto(bytes(frame), self.dest)

    def pump(self, seconds: float) -> list:
        """Heartbeats at 5 Hz; collect the daemon's frames for ``seconds``."""
        got = []
        t_end = time.monotonic() + seconds
        next_hb = 0.0
        while time.monotonic() < t_end:
            if time.monotonic() >= next_hb:
                self.heartbeat()
                next_hb = time.monotonic() + 0.2
            try:
                data, _ = self.sock.recvfrom(65536)
            except socket.timeout:
                continue
            for m in self.parser.parse_buffer(data) or []:
                if m.get_type() != "BAD_DATA":
                    got.append(m)
        self.received += got
        return got

    def pump_until(self, cond, proc: subprocess.Popen, what: str) -> list:
        """Heartbeats at 5 Hz; collect the daemon's frames until ``cond(frames so far)``, for as
        long as the daemon works (its CPU time): a busy machine delays its answer, never loses it."""
        got: list = []

        def done():
            got.extend(self.pump(0.2))
            return cond(got)
        wait_progressing(done, lambda: cpu_seconds(proc), what)
        return got


def gcs_command(key: bytes | None, command: int, p1: float, timestamp: int | None = None) -> bytes:
    g = mav2.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1])
    if key is not None:
        g.signing.secret_key = key
        g.signing.sign_outgoing = True
        g.signing.link_id = 3
        g.signing.timestamp = timestamp or int((time.time() - 1420070400) * 1e5)
    return bytes(g.command_long_encode(1, 191, command, 0, p1, 0, 0, 0, 0, 0, 0).pack(g))


def acks_to_gcs(msgs: list) -> list:
    return [m for m in msgs if m.get_type() == "COMMAND_ACK" and (m.target_system, m.target_component) == GCS]


def ours(msgs: list, mtype: str) -> list:
    return [m for m in msgs if m.get_srcComponent() == 191 and m.get_type() == mtype]


def first_ack(msgs: list, command: int | None = None) -> int | None:
    """Index of the first ACK to the ground station (of ``command`` when given), None if none."""
    return next((i for i, m in enumerate(msgs) if acks_to_gcs([m]) and command in (None, m.command)), None)


def daemon_config(tmp: Path, port: int, mavlink: dict | None = None, log_level: str = "info") -> Path:
    """The example config (bench/sitl.py write_config) for a daemon listening on ``port``."""
    return write_config(tmp / "azimuthd.toml", {
        "mavlink": {"url": f"udpin:127.0.0.1:{port}", **(mavlink or {})}, "site": {"lat_deg": 47.0, "lon_deg": 8.0},
        "zenoh": {"enabled": False}, "service": {"state_dir": str(tmp / "state"), "log_level": log_level}})


def _config(tmp: Path, key_file: Path, port: int) -> Path:
    return daemon_config(tmp, port, {"signing_key_file": str(key_file)}, log_level="debug")


def _start(cfg: Path, log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "service.cli", "run", "--config", str(cfg)], cwd=ROOT,
                            stdout=open(log, "wb"), stderr=subprocess.STDOUT, env=env)


def _wait_started(p: subprocess.Popen, log: Path, timeout_s: float = HANG_S) -> None:
    """Until the daemon logs its start, for as long as it works (its imports alone took > 60 s of
    wall time at load 20); ``timeout_s`` only detects a hang."""
    def started():
        if p.poll() is not None:
            raise AssertionError(f"daemon exited {p.returncode}: {log.read_text()[-2000:]}")
        return b"msg=started" in log.read_bytes()
    wait_progressing(started, lambda: cpu_seconds(p), "daemon did not start", hang_s=timeout_s)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("signing")
    key_file = tmp / "mavlink_signing.key"
    key_file.write_text(KEY.hex() + "\n")
    os.chmod(key_file, 0o600)
    port = free_udp_port()
    cfg = _config(tmp, key_file, port)
    res: dict = {"tmp": tmp}
    log1 = tmp / "daemon1.log"
    p = _start(cfg, log1)
    try:
        _wait_started(p, log1)
        fc = FakeFc(port)
        # each step waits for what the daemon does in answer (it handles its input in order), for
        # as long as it works: a busy machine changes when, never what, it answers
        res["startup"] = fc.pump_until(lambda f: ours(f, "HEARTBEAT") and ours(f, "COMMAND_LONG"), p,
                                       "no HEARTBEAT and SET_MESSAGE_INTERVAL from the daemon")
        # an unsigned command, one signed with the wrong key: no answer, each rejection logged
        fc.send(gcs_command(None, mav2.MAV_CMD_REQUEST_MESSAGE, mav2.MAVLINK_MSG_ID_HEARTBEAT))
        fc.send(gcs_command(WRONG_KEY, mav2.MAV_CMD_REQUEST_MESSAGE, mav2.MAVLINK_MSG_ID_HEARTBEAT))
        res["after_bad"] = fc.pump_until(lambda f: all(w in log1.read_bytes() for w in (
            b"unsigned_command_rejected", b"signature_rejected")), p, "the bad commands' rejections not logged")
        # a correctly signed one: ACK + the message
        good = gcs_command(KEY, mav2.MAV_CMD_REQUEST_MESSAGE, mav2.MAVLINK_MSG_ID_HEARTBEAT)
        fc.send(good)
        res["after_good"] = fc.pump_until(
            lambda f: (i := first_ack(f)) is not None and ours(f[i:], "HEARTBEAT"), p,
            "no ACK and HEARTBEAT for the signed request")
        # the same frame replayed, then a signed command we do not provide (answered, not
        # ignored): any answer to the replay would come before the answer to the second
        fc.send(good)
        fc.send(gcs_command(KEY, mav2.MAV_CMD_DO_FENCE_ENABLE, 0))
        after = fc.pump_until(lambda f: first_ack(f, mav2.MAV_CMD_DO_FENCE_ENABLE) is not None, p,
                              "no ACK for the signed fence command")
        i = first_ack(after, mav2.MAV_CMD_DO_FENCE_ENABLE)
        res["after_replay"], res["after_fence"] = after[:i], after[i:]
        res["all1"] = list(fc.received)
        p.send_signal(signal.SIGTERM)
        res["rc1"] = p.wait(HANG_S)
        res["log1"] = log1.read_bytes()
        # restart: the signing timestamp continues from the saved one
        res["saved"] = (tmp / "state" / "signing.json").read_text()
        log2 = tmp / "daemon2.log"
        p = _start(cfg, log2)
        _wait_started(p, log2)
        fc2 = FakeFc(port)
        res["second_run"] = fc2.pump_until(lambda f: ours(f, "HEARTBEAT"), p, "no HEARTBEAT after the restart")
        p.send_signal(signal.SIGTERM)
        res["rc2"] = p.wait(HANG_S)
        res["log2"] = log2.read_bytes()
        res["state_files"] = {f.name: f.read_bytes() for f in (tmp / "state").iterdir() if f.is_file()}
    finally:
        if p.poll() is None:
            p.kill()
    return res


def test_everything_the_daemon_sends_is_signed_with_the_key(flight):
    frames = [m for m in flight["all1"] if m.get_srcComponent() == 191]
    assert len(frames) >= 3, "the daemon sent nothing"
    types = {m.get_type() for m in frames}
    assert {"HEARTBEAT", "COMMAND_LONG"} <= types  # its heartbeat and its SET_MESSAGE_INTERVAL requests
    now_ts = (time.time() - 1420070400) * 1e5
    stamps = []
    for m in frames:
        ok, link_id, ts = independent_signature_ok(bytes(m.get_msgbuf()), KEY)
        assert ok, f"{m.get_type()} not signed with the key"
        assert link_id == 0
        stamps.append(ts)
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)  # strictly increasing
    assert abs(stamps[0] - now_ts) < 600 * 1e5  # near the wall clock (10-us units since 2015)


def test_unsigned_and_wrongly_signed_commands_get_no_answer_and_are_logged(flight):
    assert acks_to_gcs(flight["after_bad"]) == []
    log = flight["log1"].decode()
    assert "unsigned_command_rejected" in log and "signature_rejected" in log


def test_a_signed_request_is_acked_and_answered_a_replay_is_not(flight):
    acks = acks_to_gcs(flight["after_good"])
    assert [(a.command, a.result) for a in acks] == [(mav2.MAV_CMD_REQUEST_MESSAGE, mav2.MAV_RESULT_ACCEPTED)]
    assert independent_signature_ok(bytes(acks[0].get_msgbuf()), KEY)[0]
    hb = [m for m in flight["after_good"] if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 191]
    assert hb, "the requested HEARTBEAT was not sent"
    assert acks_to_gcs(flight["after_replay"]) == []
    fence = acks_to_gcs(flight["after_fence"])
    assert [(a.command, a.result) for a in fence] == [(mav2.MAV_CMD_DO_FENCE_ENABLE, mav2.MAV_RESULT_DENIED)]


def test_clean_stops_and_the_timestamp_never_goes_back_across_a_restart(flight):
    assert flight["rc1"] == 0 and flight["rc2"] == 0
    import json
    saved = json.loads(flight["saved"])["payload"]["timestamp_10us"]
    last_run1 = max(independent_signature_ok(bytes(m.get_msgbuf()), KEY)[2]
                    for m in flight["all1"] if m.get_srcComponent() == 191)
    assert saved >= last_run1
    run2 = [independent_signature_ok(bytes(m.get_msgbuf()), KEY) for m in flight["second_run"]
            if m.get_srcComponent() == 191]
    assert run2 and all(ok for ok, _l, _t in run2)
    assert min(t for _o, _l, t in run2) > saved


def test_the_key_appears_nowhere(flight):
    assert b"mavlink signing on" in flight["log1"] and b"key_fingerprint=" in flight["log1"]
    for name in ("log1", "log2"):
        assert leaks(flight[name]) == [], name
    for fname, data in flight["state_files"].items():
        assert leaks(data) == [], fname


def test_a_key_file_others_can_read_stops_the_start(tmp_path):
    key_file = tmp_path / "k"
    key_file.write_text(KEY.hex())
    os.chmod(key_file, 0o644)
    cfg = _config(tmp_path, key_file, free_udp_port())
    r = subprocess.run([sys.executable, "-m", "service.cli", "run", "--config", str(cfg), "--duration", "5"],
                       cwd=ROOT, capture_output=True, timeout=60)
    assert r.returncode == 2
    assert str(key_file).encode() in r.stderr and b"permissions 0644" in r.stderr
    assert leaks(r.stdout + r.stderr) == []
