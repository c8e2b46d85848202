"""bench/geofence.py's daemon-mode scoring: what a flight is counted as (no flights flown here).

GIVEN per-flight results as run_daemon returns them: one where the simulator kept real time and
      the daemon kept up, one where the simulator kept real time but the daemon fell behind, one
      where the simulator fell behind, one that failed to run
WHEN the bench summarises them
THEN the late daemon's flight is valid but counted apart (flights_valid_daemon_behind), its exit
     is in the valid_* figures and not in the valid_daemon_kept_up_* ones; the invalid and failed
     flights are counted and kept out of both; each flight's line says which it was.
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import geofence as bench  # noqa: E402


def flight(kind, seed, clearance_m, diverts, valid=True, kept_up=True, lost=0, p99_ms=400.0):
    return {"kind": kind, "seed": seed, "diverts_sent": diverts, "commands": [20] if diverts else [],
            "min_true_clearance_m": clearance_m, "raw_imu_forwarded": 10201, "imu_samples_processed": 10201 - lost,
            "imu_samples_lost": lost, "kernel_rx_drops": 0, "link_seq_lost": 0,
            "attitude_latency_p50_ms": p99_ms / 2, "attitude_latency_p99_ms": p99_ms,
            "attitude_latency_max_ms": p99_ms, "daemon_declared_fc_reboots": 0, "sim_flown_s": 205.0,
            "sim_speed_achieved": 1.0 if valid else 0.3, "sim_behind_real_time_max_s": 0.0 if valid else 40.0,
            "valid": valid, "daemon_kept_up": kept_up, "daemon_backlog_drained": kept_up,
            "loadavg_1min_start": 1.0, "loadavg_1min_end": 2.0, "daemon_cpu_s": 30.0, "launch_azimuth_deg": 0.0}


def test_a_late_daemon_is_valid_but_counted_apart_and_failures_are_counted():
    res = [flight("outbound", 0, 600.0, 1),
           flight("outbound", 1, -900.0, 1, kept_up=False, lost=5000, p99_ms=140e3),
           flight("inside", 0, 2000.0, 1, valid=False, kept_up=False),
           {"kind": "inside", "seed": 1, "error": "RuntimeError: daemon exited with 1", "valid": False}]
    s = bench._closed_loop_summary(res, 50.0, "d.")
    assert s["d.flights_failed"] == 1
    assert s["d.flights_valid"] == 2 and s["d.flights_sim_behind_real_time"] == 1
    assert s["d.flights_valid_daemon_behind"] == 1
    assert s["d.valid_fence_exits"] == 1 and s["d.valid_min_true_clearance_m"] == -900.0
    assert s["d.valid_daemon_kept_up_outbound_runs"] == 1 and s["d.valid_daemon_kept_up_fence_exits"] == 0
    assert s["d.valid_daemon_kept_up_min_true_clearance_m"] == 600.0
    assert s["d.valid_daemon_kept_up_imu_samples_lost"] == 0 and s["d.valid_imu_samples_lost"] == 5000
    assert s["d.valid_inside_false_diverts"] == 0  # the only inside flight that ran was invalid
    assert s["d.daemon_cpu_s_per_flight_s_median"] == 30.0 / 205.0
    lines = [bench._line("daemon", r) for r in res]
    assert "DAEMON BEHIND" not in lines[0] and "DAEMON BEHIND" in lines[1]
    assert "INVALID (sim behind)" in lines[2] and lines[3].startswith("FAILED: RuntimeError")
