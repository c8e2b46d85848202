"""Geofence open loop on simulated flights (sim.offline), GNSS lost 25 s after the launch.

GIVEN the bench's 5 km x 5 km fence and a straight leg toward it at a random angle, with the
heading the bench states (truth + 1.5 deg-sigma bias + 0.5 deg white, sigma told 1.6 deg; the
daemon's own heading is not integrated yet) and the wind estimated while GNSS was healthy
WHEN the monitor dead-reckons after the GNSS loss
THEN it latches the breach (and commands RTL) at least 15 s before the TRUE track crosses the fence,
     with a dead-reckoning error inside 2 of its own sigmas; and a flight that stays inside is never
     diverted. The 20 + 20-seed statistics are in bench/geofence.py.
"""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import geofence as bench  # noqa: E402


@pytest.mark.parametrize("seed", [1, 4])
def test_outbound_latches_before_the_true_crossing(seed):
    r = bench.run_offline("outbound", seed, flight_s=140.0)
    assert r["true_cross_time_s"] is not None, "the scenario must cross the fence without a divert"
    assert r["latch_time_s"] is not None and r["latch_time_s"] > r["gnss_lost_time_s"]  # on dead reckoning
    assert r["first_command"] == "rtl"
    assert r["lead_time_s"] >= 15.0
    assert r["dr_error_at_latch_m"] < 2.0 * r["dr_sigma_major_at_latch_m"]


def test_inside_flight_never_latches():
    r = bench.run_offline("inside", 0, flight_s=160.0)
    assert r["latch_time_s"] is None and r["first_command"] is None
