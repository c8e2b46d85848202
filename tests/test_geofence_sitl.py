"""Geofence end to end with the REAL daemon and its own heading: `azimuthd sim` and `azimuthd run`
as two processes over UDP (bench/geofence.py run_daemon). The daemon gets the operator's config
(site, launcher, [geofence]) and MAVLink only; the simulator's truth log only scores.

GIVEN the bench's fence and an outbound flight (seed 1, launch azimuth 194 deg), GNSS lost 25 s
      after the launch
WHEN the daemon dead-reckons on its own heading and predicts the breach
THEN it sends MAV_CMD_NAV_RETURN_TO_LAUNCH and the TRUE track never leaves the fence (the offline
     Pipeline run of this flight latches 25 s before the true crossing:
     tests/test_geofence_offline.py); the RAW_IMU the daemon was sent and the samples it
     processed are both counted (the bench reports the difference as lost).

What was lost and why, never timing: when the simulator itself fell behind real time on a
loaded machine (a real FC never does; the daemon then sees FC-clock lags), the flight measures
the harness, and the test says so and stops there. 20 + 20 flights, idle and busy:
bench/geofence.py --mode daemon.
"""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import geofence as bench  # noqa: E402

RTL = 20  # MAV_CMD_NAV_RETURN_TO_LAUNCH


@pytest.mark.timeout(900)
def test_daemon_diverts_on_its_own_heading_and_the_true_track_stays_inside():
    r = bench.run_daemon("outbound", 1, speed=2.0, flight_s=150.0)
    assert r["daemon_stopped_cleanly"], f"no 'stopped' line from the daemon; see {r['workdir']}"
    assert r["flight_complete"], r
    if not r["valid"]:
        pytest.skip(f"the simulator fell {r['sim_behind_real_time_max_s']:.1f} s behind real time "
                    f"(load {r['loadavg_1min_start']:.1f}): this run measures the machine, not the daemon")
    assert RTL in r["commands"], r
    assert r["min_true_clearance_m"] >= 0.0, r
    assert r["imu_samples_lost"] is not None and r["imu_samples_lost"] >= 0, r
