"""Restarts (issue 10), end to end: the simulator and the daemon as processes (bench/sitl.py).

GIVEN the daemon flying against the simulator
WHEN it gets SIGTERM THEN it exits 0 with its calibration saved (a valid, checksummed file);
WHEN it is restarted, SIGKILLed and restarted again (as systemd's Restart=on-failure does)
THEN the file survives the kill byte for byte, and the restarted daemon resumes the same flight's
calibration with the completed history unchanged;
WHEN the file is truncated or garbage THEN the daemon starts anyway, sets it aside as
``*.corrupt`` and says so in its log, and runs (links up, clean exit).
Waits are for log lines and exits; their deadlines only detect a hang (a busy machine may take
long to start a Python process).
"""
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import ROOT, Sitl  # noqa: E402

from conftest import HANG_S  # noqa: E402

from service.calibration_keeper import CALIBRATION_FILE  # noqa: E402
from service.calibration_store import CalibrationStore  # noqa: E402


def _wait_log(path: Path, text: str, timeout_s: float, proc=None) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if path.exists() and text in path.read_text():
            return True
        if proc is not None and proc.poll() is not None:
            return path.exists() and text in path.read_text()
        time.sleep(0.1)
    return False


def _start_daemon(s: Sitl, name: str):
    out = open(s.workdir / name, "w")
    p = subprocess.Popen(s.daemon_cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    s.daemon = p  # Sitl.stop() ends the current one
    return p, s.workdir / name


def _term(p) -> int:
    p.send_signal(signal.SIGTERM)
    return p.wait(HANG_S)


@pytest.fixture(scope="module")
def restarts():
    with Sitl(scenario="inclined_rail", speed=2.0, seed=4, sim_args=["--duration", "400"]) as s:
        cal = s.workdir / "state" / CALIBRATION_FILE
        res = {"workdir": s.workdir, "cal": cal}
        # 1. SIGTERM: clean shutdown, calibration saved
        log1 = s.workdir / "daemon.log"
        res["up1"] = _wait_log(log1, "flight controller link up", HANG_S, s.daemon)
        time.sleep(2.0)
        res["rc1"] = _term(s.daemon)
        res["log1"] = log1.read_text()
        res["bytes1"] = cal.read_bytes() if cal.exists() else b""
        res["hist1"] = CalibrationStore(cal).load()
        # 2. restart, SIGKILL once it runs
        p2, log2 = _start_daemon(s, "daemon2.log")
        res["up2"] = _wait_log(log2, "flight controller link up", HANG_S, p2)
        time.sleep(2.0)
        p2.send_signal(signal.SIGKILL)
        res["rc2"] = p2.wait(10)
        res["log2"] = log2.read_text()
        res["bytes_after_kill"] = cal.read_bytes() if cal.exists() else b""
        # 3. restart after the kill: resumes; clean stop
        p3, log3 = _start_daemon(s, "daemon3.log")
        res["up3"] = _wait_log(log3, "flight controller link up", HANG_S, p3)
        time.sleep(1.0)
        res["rc3"] = _term(p3)
        res["log3"] = log3.read_text()
        res["hist3"] = CalibrationStore(cal).load()
        # 4. a damaged file: truncated
        data = cal.read_bytes()
        cal.write_bytes(data[:len(data) // 2])
        p4, log4 = _start_daemon(s, "daemon4.log")
        res["up4"] = _wait_log(log4, "flight controller link up", HANG_S, p4)
        time.sleep(1.0)
        res["rc4"] = _term(p4)
        res["log4"] = log4.read_text()
        res["corrupt_files"] = sorted(p.name for p in cal.parent.glob(CALIBRATION_FILE + ".corrupt*"))
        res["hist4"] = CalibrationStore(cal).load()
        # 5. garbage (not JSON at all)
        cal.write_bytes(b"\x00\xffnot json\n" * 10)
        p5, log5 = _start_daemon(s, "daemon5.log")
        res["up5"] = _wait_log(log5, "flight controller link up", HANG_S, p5)
        res["rc5"] = _term(p5)
        res["log5"] = log5.read_text()
        res["corrupt_files5"] = sorted(p.name for p in cal.parent.glob(CALIBRATION_FILE + ".corrupt*"))
    return res


def test_sigterm_clean_shutdown_with_calibration_saved(restarts):
    r = restarts
    assert r["up1"] and r["rc1"] == 0
    assert "msg=\"signal received, shutting down\" signal=SIGTERM" in r["log1"]
    assert "msg=\"calibration saved\"" in r["log1"] and "msg=stopped" in r["log1"]
    assert "level=error" not in r["log1"] and "Traceback" not in r["log1"]
    h = r["hist1"]
    assert h.status == "loaded" and h.current is not None and h.current.flight_id >= 1


def test_sigkill_leaves_the_file_intact_and_restart_resumes_it(restarts):
    r = restarts
    assert r["up2"] and r["rc2"] == -signal.SIGKILL
    assert "msg=stopped" not in r["log2"]  # it really died, no shutdown path ran
    assert r["bytes_after_kill"] == r["bytes1"]  # the kill did not touch the file
    fid = r["hist1"].current.flight_id
    assert "resuming the calibration of the flight in progress" in r["log2"]
    assert "resuming the calibration of the flight in progress" in r["log3"]
    assert f"flight={fid} " in r["log3"] and "status=loaded" in r["log3"]
    assert r["up3"] and r["rc3"] == 0
    h3 = r["hist3"]
    assert h3.status == "loaded" and h3.current.flight_id == fid
    assert h3.completed == r["hist1"].completed  # the completed history unchanged across the restarts
    assert not list(r["cal"].parent.glob("*.tmp.*"))


def test_truncated_calibration_file_set_aside_daemon_runs(restarts):
    r = restarts
    assert r["up4"] and r["rc4"] == 0
    assert "calibration file damaged, set aside" in r["log4"]
    assert "Traceback" not in r["log4"]
    assert r["corrupt_files"] == [CALIBRATION_FILE + ".corrupt"]
    assert r["hist4"].status == "loaded"  # the daemon wrote a fresh, valid file at its shutdown


def test_garbage_calibration_file_set_aside_daemon_runs(restarts):
    r = restarts
    assert r["up5"] and r["rc5"] == 0
    assert "calibration file damaged, set aside" in r["log5"] and "Traceback" not in r["log5"]
    assert r["corrupt_files5"] == [CALIBRATION_FILE + ".corrupt", CALIBRATION_FILE + ".corrupt.1"]
