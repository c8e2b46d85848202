"""Geofence closed loop end to end: the simulator as its own process over MAVLink/UDP.

GIVEN the bench's fence and an outbound flight (GNSS lost 25 s after the launch)
WHEN the geofence loop (GeofenceMonitor + CommandProtocol on a MavlinkLink, as the daemon runs them)
     predicts the breach on dead reckoning
THEN it sends MAV_CMD_NAV_RETURN_TO_LAUNCH, the simulator ACKs it and turns back (mode RTL), and the
     TRUE track (the simulator's truth log) never leaves the fence, keeping at least the 50 m margin.

The first test runs the loop in this process (a stand-in for the daemon, bench/geofence.py
run_closed); the second runs the real daemon and is skipped until the daemon accepts [geofence]
(the lead wires it: docs/GEOFENCE.md "Wiring into the daemon"). 20 + 20 seeds: bench/geofence.py.
"""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import geofence as bench  # noqa: E402


@pytest.mark.timeout(120)
def test_closed_loop_divert_before_the_breach_true_track_stays_inside():
    r = bench.run_closed("outbound", 1, speed=25.0, flight_s=130.0)
    assert r["truth_rows"] > 1000, f"truth log too short; see {r['workdir']}"
    assert r["actions"][:1] == ["rtl"] and r["outcomes"][:1] == ["rtl:accepted"], r
    assert r["first_divert_time_fc_s"] > bench.REST_S + bench.GNSS_LOST_AFTER_LAUNCH_S  # on dead reckoning
    assert "RTL" in r["modes_seen"]
    assert r["min_true_clearance_m"] >= bench.fence_raw()["margin_m"], r


@pytest.mark.timeout(180)
def test_daemon_end_to_end_divert():
    ok, why = bench.daemon_supports_geofence()
    if not ok:
        pytest.skip(f"daemon not wired yet: {why}")
    r = bench.run_daemon("outbound", 1, speed=3.0, flight_s=150.0)  # a daemon that keeps up (see run_daemon)
    assert r["diverts_sent"] >= 1, r
    assert r["min_true_clearance_m"] >= 0.0, r
