"""Load (issue 10): RAW_IMU at 1 kHz for 2 minutes, simulator and daemon as processes, real time.

GIVEN the simulator streaming RAW_IMU at 1 kHz (requested by the daemon with
SET_MESSAGE_INTERVAL) WHEN the daemon runs for 2 minutes THEN no sample is lost inside the daemon
(every IMU message its link accepted reached the Pipeline: processed or rejected with a reason,
from its own "stopped" counters), the received rate is near 1 kHz, and its RSS grows by less than
5 MB. The 30-minute figure (flat once method A's buffer is full): bench/reliability_load.py --load.
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from reliability_load import run_load  # noqa: E402

DURATION_S = 120.0


def test_1khz_for_2_minutes_nothing_lost_inside_memory_flat():
    r = run_load(DURATION_S, 1000.0)
    print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()})
    assert r["imu_messages"] > 0.85 * 1000.0 * DURATION_S
    assert r["imu_lost_inside_daemon"] == 0
    assert r["imu_rejected"] == 0  # clean data: nothing for the input checks to reject
    # bounded: the only store that grows in flight is method A's fit buffer (max_fit_samples 1500
    # magnetometer records, full after 150 s of flight); measured +2.6 MB over these 2 minutes
    assert r["rss_end_mb"] - r["rss_start_mb"] < 5.0
