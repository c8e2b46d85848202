"""Geofence end to end with the REAL daemon and its own heading: `azimuthd sim` and `azimuthd run`
as two processes over UDP (bench/geofence.py daemon_flights / run_daemon). The daemon gets the
operator's config (site, launcher, RAW_IMU at 50 Hz as a stock ArduPilot streams it, [geofence])
and MAVLink only; the simulator's truth log only scores.

GIVEN the bench's fence and an outbound flight (seed 1, launch azimuth 194 deg), GNSS lost 25 s
      after the launch; the simulator and the tap (the FC and its wire) in a CPU group of their
      own at nice -5 when run as root, the daemon in its own session at nice 0 as its systemd unit
      runs it
WHEN the daemon dead-reckons on its own heading and predicts the breach
THEN every RAW_IMU it did not process is one it counted (kernel drop, sequence gap); it sends
     MAV_CMD_NAV_RETURN_TO_LAUNCH; and the TRUE track stays >= 300 m inside the fence (measured
     605 m with a 200 Hz RAW_IMU at load 4-8, session 3; a daemon that kept up at 50 Hz on this
     machine has not been measured yet: bench/geofence.py --mode daemon on a quiet machine).

What was lost and why, never timing: when the simulator fell behind real time (a real FC never
does), or the daemon did (its ATTITUDE more than 5 s behind its RAW_IMU, or a backlog left 30 s
after the flight: the CPU it got on a crowded machine), the flight does not show the daemon's
own divert geometry, and the test says which and stops there. 20 + 20 flights, idle and busy:
bench/geofence.py --mode daemon.
"""
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import geofence as bench  # noqa: E402

RTL = 20  # MAV_CMD_NAV_RETURN_TO_LAUNCH
ROOT_USER = os.geteuid() == 0
FLIGHT_S = 110.0
"""Seconds flown after the launch (real time). Outbound seed 1 (truth, four daemon flights of
2026-12-02): without a divert the track crosses the fence 101-103 s after the launch; the daemon
diverted at 76 s and the true track came closest, 527-534 m inside, at 81.5 s, then flew away
from the fence (776 m at 100 s). A divert too late for 300 m (after ~85 s) comes closest before
110 s, a divert after it is no RTL, and a crossing is inside the flight: the 150 s flown before
this asserted nothing more."""


@pytest.mark.timeout(900)
def test_daemon_diverts_on_its_own_heading_and_the_true_track_stays_inside():
    opts = {"raw": bench.fence_raw(), "speed": 1.0, "flight_s": FLIGHT_S, "imu_rate_hz": 50.0,
            "fc_group_nice": -5 if ROOT_USER else None, "daemon_nice": 0 if ROOT_USER else None}
    (r,) = list(bench.daemon_flights([("outbound", 1)], opts, 1))
    assert "error" not in r, r
    assert r["daemon_stopped_cleanly"], f"no 'stopped' line from the daemon; see {r['workdir']}"
    if not r["valid"]:
        pytest.skip(f"the simulator fell {r['sim_behind_real_time_max_s']:.1f} s behind real time "
                    f"(load {r['loadavg_1min_start']:.1f}): this run measures the machine, not the daemon")
    assert r["flight_complete"], r
    lost = r["imu_samples_lost"]
    assert lost is not None and lost >= 0, r
    if not r["daemon_kept_up"]:
        p99 = r["attitude_latency_p99_ms"]
        pytest.skip(f"the daemon fell behind on this machine (load {r['loadavg_1min_end']:.1f}): ATTITUDE "
                    f"latency p99 {'-' if p99 is None else f'{p99 / 1e3:.1f} s'}, backlog drained "
                    f"{r['daemon_backlog_drained']}, "
                    f"{lost} of {r['raw_imu_forwarded']} RAW_IMU unprocessed; the divert geometry is not its own")
    # what was lost and why: the daemon worked off its backlog, so every RAW_IMU the tap forwarded
    # and the daemon did not process is one it counted as a kernel drop or a sequence gap
    assert lost <= r["kernel_rx_drops"] + r["link_seq_lost"], r
    assert RTL in r["commands"], r
    # 605 m measured (200 Hz, session 3); bound with 305 m of margin
    assert r["min_true_clearance_m"] >= 300.0, r
