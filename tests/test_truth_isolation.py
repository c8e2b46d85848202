"""Truth only scores (DESIGN.md "Tests and measurements"): the decision half of the headline benches
runs on a SimRun whose truth is sealed (bench/_truth_guard.py), and still produces its figures;
the daemon cannot see the truth on the wire. A bench or estimator path that reads the truth
stream, the scenario's true launcher azimuth or its phase labels fails here."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
import _truth_guard as guard  # noqa: E402
import deviation_declination as dev_bench  # noqa: E402
import geofence as fence_bench  # noqa: E402

from sim.offline import simulate  # noqa: E402


@pytest.fixture(scope="module")
def outbound_run():
    """The geofence bench's outbound flight (seed 1), cut at 50 s after the launch: 25 s of it on
    dead reckoning after the GNSS loss."""
    sc = fence_bench.scenario("outbound", 1)
    sc["scenario"]["duration_s"] = fence_bench.REST_S + 50.0
    return simulate(sc, seed=1, imu_rate_hz=fence_bench.PIPELINE_IMU_HZ)


def test_a_sealed_run_refuses_every_truth_read(outbound_run):
    s = guard.sealed(outbound_run)
    for read in (lambda: s.truth.euler_rad, lambda: s.truth.phase, lambda: s.truth.launch_time_s,
                 lambda: s.site["launcher_azimuth_deg"], lambda: s.site.get("launcher_azimuth_deg"),
                 lambda: s.scenario["launcher"], lambda: s.scenario.get):
        with pytest.raises(guard.TruthReadError, match="truth"):
            read()
    # what the operator configures and what the FC sends stay readable
    assert s.site["decimal_year"] == outbound_run.site["decimal_year"]
    assert s.gnss_lost_time_s == outbound_run.gnss_lost_time_s
    np.testing.assert_array_equal(s.gyro_rad_s, outbound_run.gyro_rad_s)


def test_geofence_headline_decision_path_reads_no_truth(outbound_run):
    """GIVEN the outbound flight sealed (only the FC's GNSS reports before its loss are handed over)
    WHEN the daemon's Pipeline and GeofenceMonitor decide on it
    THEN they run to the end on the daemon's own heading (FC / synthetic AHRS / A / C, no truth):
    a solution for every other IMU sample (the Pipeline publishes at 50 Hz), most with a heading.
    (bench/sitl.py's pipeline_inputs, which every Pipeline bench uses, runs on the sealed run too.)"""
    d = fence_bench.pipeline_decide(guard.sealed(outbound_run), fence_bench.fc_gnss_positions(outbound_run),
                                    fence_bench.fence_raw())
    n = sum(d["heading_sources"].values())
    assert n >= 0.45 * outbound_run.time_s.size
    assert n - d["heading_sources"].get("none", 0) > 0.9 * n, d["heading_sources"]


def test_deviation_decision_path_reads_no_truth():
    """Method D's bench: calibration window and reference heading from the Pipeline, not from the
    truth's phase labels or the launcher azimuth (a short flight: 20 s of the manoeuvre)."""
    run = simulate("inclined_rail", seed=0, imu_rate_hz=dev_bench.RATE_HZ, duration_s=55.0,
                   overrides={"legs": dev_bench.CAL_LEGS, "launcher": {"rest_s": 10.0}})
    d = dev_bench.deviation_decide(guard.sealed(run))
    assert d["t_launch"] is not None and abs(d["t_launch"] - 10.0) < 1.0  # the Pipeline's own detection
    assert d["dev"].n > 50 and len(d["rows"]) > 150


def test_benches_in_the_guard_decide_on_sealed_runs():
    """The headline paths call the sealed run: a bench that passes the unsealed run to its decision
    half (or reads truth before) is caught by the source, not only by luck of the data."""
    for path, decide in ((ROOT / "bench" / "geofence.py", "pipeline_decide"),
                         (ROOT / "bench" / "deviation_declination.py", "deviation_decide")):
        tree = ast.parse(path.read_text())
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == decide]
        assert calls, f"{path.name} never calls {decide}"
        for c in calls:
            arg = c.args[0]
            assert isinstance(arg, ast.Call) and getattr(arg.func, "id", "") == "sealed", \
                f"{path.name}: {decide} gets an unsealed run (line {c.lineno})"


def test_the_daemon_never_sees_the_truth_stream():
    """SIMSTATE is the simulator's truth on the wire: nothing in the daemon's packages reads it,
    no estimator, link or service module imports sim/ (service/cli.py only starts the `azimuthd
    sim` subcommand), and the daemon-mode bench switches it off."""
    for pkg in ("service", "mavlink_io", "estimators"):
        for f in (ROOT / pkg).rglob("*.py"):
            text = f.read_text()
            assert "SIMSTATE" not in text, f"{f} mentions SIMSTATE"
            if f == ROOT / "service" / "cli.py":
                continue
            for node in ast.walk(ast.parse(text)):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                assert not any(n == "sim" or n.startswith("sim.") for n in names), f"{f} imports sim"
    src = (ROOT / "bench" / "geofence.py").read_text()
    assert '"autopilot.simstate_rate_hz=0"' in src.split("def run_daemon")[1].split("\ndef ")[0]
