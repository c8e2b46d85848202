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
import _fc_status as fc_status  # noqa: E402
import _truth_guard as guard  # noqa: E402
import azimuth_accuracy as az_bench  # noqa: E402
import deviation_declination as dev_bench  # noqa: E402
import geofence as fence_bench  # noqa: E402
import heading_consistency as hc_bench  # noqa: E402
import polar_accuracy as polar_bench  # noqa: E402
import synthetic_ahrs_accuracy as b_bench  # noqa: E402

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


def test_heading_consistency_decision_path_reads_no_truth():
    """GIVEN a rail flight (10 s on the rail, 35 s flown) with a 10 s link outage, sealed
    WHEN the fused-heading bench's decision half runs the Pipeline on it
    THEN every solution has its heading and inputs recorded, most with a published heading, and
    the FC's is_flying comes from its own airspeed: ACTIVE from 0-3 s after the true launch
    (scored here, in the test), never before."""
    case = dict(name="t", scenario="inclined_rail", duration_s=45.0, feed_from_s=0.0, gap_start_s=30.0,
                overrides={"launcher": {"rest_s": 10.0}})
    run = simulate(case["scenario"], seed=3, imu_grade="consumer", imu_rate_hz=hc_bench.IMU_HZ,
                   duration_s=case["duration_s"], overrides=case["overrides"])
    rec = hc_bench.decide(guard.sealed(run), case)
    n = len(rec["t"])
    assert n >= 0.45 * (run.time_s.size - hc_bench.GAP_S * hc_bench.IMU_HZ)
    assert all(len(v) == n for v in rec.values())
    assert np.isfinite(rec["h"]).sum() > 0.5 * n
    active = [it.time_rx_s for it in fc_status.fc_status_items(guard.sealed(run), 0.0)
              if type(it).__name__ == "FcHeartbeat" and it.system_status == fc_status.MAV_STATE_ACTIVE]
    launch = run.truth.launch_time_s
    assert active and 0.0 <= active[0] - launch <= 3.0, (active[:3], launch)


def test_polar_decision_paths_read_no_truth():
    """Method C's bench, both halves on a sealed 45 N run (35 s on the rail): the Pipeline and C
    alone give roll/pitch throughout, and C's heading from the magnetometer (no heading prior: it
    was the true launcher azimuth before)."""
    run = polar_bench.simulate_flight(45.0, 0, "consumer", 35.0)
    for rows in (polar_bench.pipeline_decide(guard.sealed(run)), polar_bench.per_method_decide(guard.sealed(run), "consumer")):
        r = np.array(rows, float)
        assert len(r) > 250 and np.all(np.isfinite(r[:, 1:5]))
        assert np.isfinite(r[:, 5]).mean() > 0.9


def test_synthetic_ahrs_decision_paths_read_no_truth(tmp_path):
    """Method B's bench on a sealed runway flight (10 s at rest, GNSS lost 10 s after the start,
    30 s): the Pipeline (KF1 through the daemon's calibration keeper, saved at the end) and B alone
    both run past the loss."""
    from service.calibration_keeper import CalibrationKeeper
    run = simulate("runway_gnss_denied", seed=2, imu_grade="consumer", imu_rate_hz=b_bench.IMU_HZ, duration_s=30.0,
                   overrides={"launcher": {"rest_s": 10.0}, "gnss": {"lost_at_s": 20.0}})
    keeper = CalibrationKeeper(tmp_path, clock=lambda: 1.0e9)
    d = b_bench.pipeline_decide(guard.sealed(run), keeper)
    assert len(d["rows"]) > 300 and (tmp_path / "synthetic_ahrs_calibration.json").exists()
    from estimators.geomag import earth_field_ned_gauss
    s = run.site
    params = b_bench.SyntheticAhrsParams(variant="b2", C_body_from_sensor=s["C_body_from_sensor"],
                                         field_nav_gauss=tuple(earth_field_ned_gauss(s["lat_deg"], s["lon_deg"],
                                                                                    s["alt_m"], s["decimal_year"])))
    st, est, sig, base, trusted, k0 = b_bench.run_flight(guard.sealed(run), params, None, None, True)
    assert run.time_s[k0] >= 20.0 and np.isfinite(est[k0:, 2]).any()


def test_azimuth_decision_paths_read_no_truth():
    """Method A's bench on a sealed inclined-rail flight: the Pipeline (operator's config: site,
    mount, launch case; no launcher azimuth) and A alone both reach a solution."""
    rng = np.random.default_rng(10_000 + 1)
    scenario, ov = az_bench.flight_overrides("inclined", rng)
    run = simulate(scenario, seed=1, imu_grade="consumer", imu_rate_hz=50.0,
                   duration_s=az_bench.REST_S + 25.0, overrides=ov)
    cfg = az_bench.operator_config("inclined", ov, run.site, "full12", 50.0)
    rows = az_bench.pipeline_decide(guard.sealed(run), cfg)
    assert any(np.isfinite(r[1]) for r in rows), {r[5] for r in rows}
    p = az_bench.estimator_params("inclined", run.site, "full12")
    rows, launch, _ = az_bench.per_method_decide(guard.sealed(run), p)
    assert launch is not None and any(np.isfinite(r[1]) for r in rows), {r[5] for r in rows}


DECISION_CALLS = {
    "geofence.py": ("pipeline_decide",),
    "deviation_declination.py": ("deviation_decide",),
    "heading_consistency.py": ("decide",),
    "polar_accuracy.py": ("pipeline_decide", "per_method_decide"),
    "synthetic_ahrs_accuracy.py": ("pipeline_decide", "run_flight"),
    "azimuth_accuracy.py": ("pipeline_decide", "per_method_decide"),
}
"""Each headline bench's decision functions: every call of them passes a sealed run."""


def test_benches_in_the_guard_decide_on_sealed_runs():
    """The headline paths call the sealed run: a bench that passes the unsealed run to its decision
    half (or reads truth before) is caught by the source, not only by luck of the data."""
    for name, decides in DECISION_CALLS.items():
        path = ROOT / "bench" / name
        tree = ast.parse(path.read_text())
        for decide in decides:
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
