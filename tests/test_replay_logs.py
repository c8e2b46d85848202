"""`azimuthd replay` on the real logs of shared/data: the CSV header, the reference columns equal to
the log's own attitude sample for sample, the streams reported missing, the site taken from the
log (or refused without one), the plot a valid PNG."""
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from service.aiding import WHY_NOT
from service.replay import CSV_COLUMNS, main

DATA = Path("/work/shared/data")
TLOG = DATA / "arducopter-flight.tlog"
BENCH = DATA / "px4-bench-sample.ulg"
VTOL = DATA / "px4-vtol-airspeed-small.ulg"
pytestmark = pytest.mark.skipif(not all(p.exists() for p in (TLOG, BENCH, VTOL)),
                                reason="shared real logs not available")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _replay(tmp_path_factory, log: Path, *extra: str):
    d = tmp_path_factory.mktemp(log.stem)
    out, js = d / "out.csv", d / "out.json"
    rc = main([str(log), "--output", str(out), "--json", str(js), "--no-progress", *extra])
    assert rc == 0
    with out.open() as f:
        rows = list(csv.reader(f))
    return rows, json.loads(js.read_text()), d


@pytest.fixture(scope="module")
def tlog_run(tmp_path_factory):
    return _replay(tmp_path_factory, TLOG)


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    return _replay(tmp_path_factory, BENCH, "--site", "47.3769,8.5417,410", "--plot",
                   str(tmp_path_factory.getbasetemp() / "bench.png"))


@pytest.fixture(scope="module")
def vtol_run(tmp_path_factory):
    return _replay(tmp_path_factory, VTOL)


def _f(s: str) -> float:
    return float(s) if s else math.nan


def _ulog_reference(path: Path):
    """(t_s, roll_deg, pitch_deg, heading_deg) of vehicle_attitude, from q by an independent formula."""
    from pyulog import ULog
    d = ULog(str(path), ["vehicle_attitude"]).get_dataset("vehicle_attitude").data
    w, x, y, z = (np.asarray(d[f"q[{i}]"], float) for i in range(4))
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    roll = np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    pitch = np.degrees(np.arcsin(np.clip(2 * (w * y - z * x), -1, 1)))
    yaw = np.degrees(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))) % 360.0
    return np.asarray(d["timestamp"], float) * 1e-6, roll, pitch, yaw


@pytest.mark.parametrize("which", ["tlog_run", "bench_run", "vtol_run"])
def test_csv_has_the_exact_header_and_a_row_per_output_sample(which, request):
    rows, s, _ = request.getfixturevalue(which)
    assert rows[0] == CSV_COLUMNS
    assert len(rows) - 1 == s["rows"]
    # one row per NavSolution: at heading.filter_rate_hz (50 Hz), or per IMU sample when slower
    t = np.array([float(r[0]) for r in rows[1:]])
    expected = min(s["imu_samples"] - s["imu_rejected"], (t[-1] - t[0]) * 50.0)
    assert 0.9 * expected <= s["rows"] <= s["imu_samples"] - s["imu_rejected"]
    assert np.all(np.isfinite(t))
    for r in rows[1:]:
        assert r[1] in ("boot", "pre-launch", "launch", "in-flight")
        for name, v in zip(rows[0][2:], r[2:]):
            if name.endswith("_why_not"):  # the aiding records' codes (service/aiding.py)
                assert v in WHY_NOT, (name, v)
            elif name.endswith("_fused"):  # empty: no arbitration yet (not levelled)
                assert v in ("0", "1", ""), (name, v)
            elif name != "heading_source":
                assert v == "" or math.isfinite(float(v)), (name, v)


@pytest.mark.parametrize("which,log", [("bench_run", BENCH), ("vtol_run", VTOL)])
def test_ulog_reference_columns_are_the_logs_attitude(which, log, request):
    rows, s, _ = request.getfixturevalue(which)
    t_att, roll, pitch, yaw = _ulog_reference(log)
    n_checked = 0
    for r in rows[1:]:
        t = float(r[0])
        j = np.searchsorted(t_att, t + 1e-9, side="right") - 1  # the last attitude at or before the sample
        if j < 0 or t - t_att[j] > 1.0:
            assert r[9] == r[10] == r[11] == ""
            continue
        assert _f(r[9]) == pytest.approx(roll[j], abs=1e-7)
        assert _f(r[10]) == pytest.approx(pitch[j], abs=1e-7)
        d = (_f(r[11]) - yaw[j] + 180.0) % 360.0 - 180.0
        assert abs(d) < 1e-7
        n_checked += 1
    assert n_checked >= 0.95 * (len(rows) - 1)
    assert s["fc_attitude_samples"] == len(t_att)


def test_tlog_reference_columns_are_the_logs_attitude(tlog_run):
    """Every row's ref_ is the last ATTITUDE received before its RAW_IMU (within 1 s of FC time),
    as decoded by the lead's replay_tlog; none across the FC reboot."""
    from mavlink_io.link import LinkEvent
    from mavlink_io.samples import FcAttitude, ImuSample
    from mavlink_io.tlog import replay_tlog
    rows, s, _ = tlog_run
    items, _ = replay_tlog(TLOG)
    expected = []
    att = None
    for it in items:
        if isinstance(it, FcAttitude):
            att = it
        elif isinstance(it, LinkEvent) and it.kind == "fc_reboot":
            att = None
        elif isinstance(it, ImuSample):
            ok = att is not None and abs(it.time_fc_s - att.time_fc_s) <= 1.0
            expected.append((it.time_fc_s, att if ok else None))
    assert len(expected) == len(rows) - 1 == 2856
    filled = 0
    for r, (t, a) in zip(rows[1:], expected):
        assert float(r[0]) == pytest.approx(t, abs=1e-6)
        if a is None:
            assert r[9] == r[10] == r[11] == ""
            continue
        filled += 1
        assert float(r[9]) == pytest.approx(math.degrees(a.roll_rad), abs=1e-8)
        assert float(r[10]) == pytest.approx(math.degrees(a.pitch_rad), abs=1e-8)
        assert float(r[11]) == pytest.approx(math.degrees(a.yaw_rad) % 360.0, abs=1e-8)
    assert filled > 2700


def test_tlog_site_date_and_honest_outcome(tlog_run):
    rows, s, _ = tlog_run
    notes = " ".join(s["config_notes"])
    assert "GPS_RAW_INT" in notes and "-35.36" in notes and "149.16" in notes
    assert "WMM-2015" in notes  # a 2015 log: the field of its own epoch, not today's
    assert s["imu_rate_hz"] < 5  # a telemetry-radio log: ~2.7 Hz per stream
    # at that rate the estimators cannot work as designed: said in the summary, whatever they output
    assert len(s["warnings"]) == 1 and "2.7 Hz" in s["warnings"][0] and "not an accuracy figure" in s["warnings"][0]
    # no 2-s still block ever holds the 200 samples levelling needs; the copter's take-off may
    # still be seen as a launch (service/phases.py: launch before a still block)
    phases = [p["phase"] for p in s["phases"]]
    assert phases[0] == "pre-launch" and set(phases) <= {"pre-launch", "launch", "in-flight"}
    assert any("radio link" in n or "bad CRC" in n for n in s["notes"])


def test_bench_log_missing_barometer_and_needs_site(bench_run, tmp_path, capsys):
    rows, s, _ = bench_run
    assert any(m.startswith("barometer: none") for m in s["missing_streams"])
    assert s["pressure_samples"] == 0 and s["imu_rate_hz"] == pytest.approx(248, rel=0.01)
    # the bench log levels before it is moved by hand: roll/pitch against the FC's EKF2
    assert s["roll_compared_rows"] > 3000  # of ~3300 rows at 50 Hz
    assert 0.0 < s["roll_rms_diff_deg"] < 10.0
    # without --site the log (no GNSS) cannot give the site: a clear error, exit code 2
    assert main([str(BENCH), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "no GNSS position" in err and "--site" in err


def test_bench_plot_is_a_png(bench_run, tmp_path_factory):
    png = tmp_path_factory.getbasetemp() / "bench.png"
    data = png.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 20_000
    w, h = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert w > 600 and h > 400


def test_vtol_log_streams_and_site(vtol_run):
    rows, s, _ = vtol_run
    assert s["missing_streams"] == [] and s["warnings"] == []
    assert sum(s["heading_sources"].values()) == s["rows"]
    assert sorted(s["heading_sources"]) == sorted({r[6] for r in rows[1:]})
    # rows whose heading uses the FC's own yaw are left out of the "own" heading figure
    if all("fc" in k.split("+") for k in s["heading_sources"] if k != "none"):
        assert s["heading_rms_diff_own_deg"] is None
    assert s["pressure_samples"] == 120 and s["fc_attitude_samples"] == 1298
    notes = " ".join(s["config_notes"] + s["notes"])
    assert "vehicle_gps_position" in notes and "63.41" in notes and "WMM-2020" in notes
    assert "airspeed" in notes  # differential pressure at 1 Hz only: taken from airspeed
    # on the ground, still: levelling agrees with the FC's EKF2 to a fraction of a degree
    assert s["roll_compared_rows"] > 200  # of ~260 rows at 50 Hz
    assert s["roll_rms_diff_deg"] < 0.3 and s["pitch_rms_diff_deg"] < 0.3
