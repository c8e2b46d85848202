"""Bad input to `azimuthd replay`: a clear one-line message on stderr, exit code 2, no traceback,
no half-written CSV."""
import subprocess
import sys
from pathlib import Path

import pytest

from service.replay import main

DATA = Path("/work/shared/data")
TLOG = DATA / "arducopter-flight.tlog"
VTOL = DATA / "px4-vtol-airspeed-small.ulg"
ROOT = Path(__file__).resolve().parents[1]


def _run(capsys, *argv):
    rc = main([*map(str, argv), "--no-progress"])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.parametrize("ext,what", [(".tlog", "not a MAVLink telemetry log"),
                                      (".ulg", "not a readable PX4 ULog"),
                                      (".bin", "not an ArduPilot DataFlash log")])
def test_a_non_log_file(tmp_path, capsys, ext, what):
    p = tmp_path / f"notes{ext}"
    p.write_text("take-off at 10:00, wind 5 kt from the west\n" * 20)
    out = tmp_path / "o.csv"
    rc, _, err = _run(capsys, p, "--site", "1,2", "--output", out)
    assert rc == 2 and what in err and str(p) in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "o.csv.part").exists()


def test_unknown_extension_and_missing_file(tmp_path, capsys):
    p = tmp_path / "flight.csv"
    p.write_text("a,b\n")
    rc, _, err = _run(capsys, p)
    assert rc == 2 and "unknown log type '.csv'" in err and ".tlog, .bin, .ulg" in err
    rc, _, err = _run(capsys, tmp_path / "nope.ulg")
    assert rc == 2 and "no such file" in err
    (tmp_path / "empty.tlog").write_bytes(b"")
    rc, _, err = _run(capsys, tmp_path / "empty.tlog")
    assert rc == 2 and "empty file" in err


@pytest.mark.skipif(not (TLOG.exists() and VTOL.exists()), reason="shared real logs not available")
def test_truncated_logs(tmp_path, capsys):
    # a tlog cut after its first few records: no IMU sample at all
    t = tmp_path / "cut.tlog"
    t.write_bytes(TLOG.read_bytes()[:300])
    rc, _, err = _run(capsys, t, "--site", "1,2")
    assert rc == 2 and "no IMU samples" in err and "IMU (gyro + accelerometer): none" in err
    # a ULog cut inside its definitions: no sensor_combined
    u = tmp_path / "cut.ulg"
    u.write_bytes(VTOL.read_bytes()[:3000])
    rc, out, err = _run(capsys, u, "--site", "1,2")
    assert rc == 2 and "no sensor_combined" in err and out == ""
    # a tlog cut in the middle of a record: replayed up to the cut, the cut reported
    t.write_bytes(TLOG.read_bytes()[:200_000] + b"\x00\x00\x00")
    rc, out, err = _run(capsys, t)
    assert rc == 0 and "incomplete record (truncated log)" in out


def test_bad_options(tmp_path, capsys):
    p = tmp_path / "x.tlog"
    p.write_bytes(b"\x00" * 10)
    assert _run(capsys, p, "--site", "91,0")[0] == 2
    rc, _, err = _run(capsys, p, "--plot", tmp_path / "x.jpg")
    assert rc == 2 and "PNG" in err
    rc, _, err = _run(capsys, p, "--output", tmp_path / "no" / "dir.csv")
    assert rc == 2 and "directory does not exist" in err
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[imu]\nstill_seconds = -1\n")
    if VTOL.exists():
        rc, _, err = _run(capsys, VTOL, "--config", cfg)
        assert rc == 2 and "config error" in err and "imu.still_seconds" in err


def test_cli_process_bad_input_no_traceback(tmp_path):
    """Through the installed command path (service.cli): exit code 2, one line, no traceback."""
    p = tmp_path / "junk.ulg"
    p.write_bytes(bytes(range(256)) * 8)
    r = subprocess.run([sys.executable, "-m", "service.cli", "replay", str(p)], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and r.stderr.startswith("azimuthd replay: ")
    assert r.stdout == ""
