"""Load (issue 10): RAW_IMU at 1 kHz for 2 minutes, simulator and daemon as processes, real time.

GIVEN the simulator streaming RAW_IMU at 1 kHz (requested by the daemon with
SET_MESSAGE_INTERVAL) WHEN the daemon runs for 2 minutes THEN no sample is lost inside the daemon
(every IMU message its link accepted reached the Pipeline: processed or rejected with a reason,
from its own "stopped" counters), the simulator sent 1 kHz of its own clock and what it sent
reached the daemon's link or was dropped by the kernel as counted (a busy machine may slow the
simulator and make the kernel drop: both are accounted, neither is a failure; only the shutdown
tail, sent after the daemon stopped reading, is unaccounted), and its RSS grows by less than
5 MB. The 30-minute figure (flat once method A's buffer is full): bench/reliability_load.py --load.
"""
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import pytest  # noqa: E402
from reliability_load import run_load  # noqa: E402

DURATION_S = 120.0


def test_1khz_for_2_minutes_nothing_lost_inside_memory_flat():
    r = run_load(DURATION_S, 1000.0)
    print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()})
    own = re.search(r"sim stopped: simulated_s=([\d.]+) .* sent=(\{.*\})",
                    (Path(r["workdir"]) / "sim.log").read_text())
    assert own, "no 'sim stopped' line in the simulator's log"
    simulated_s, sent_by_type = float(own.group(1)), json.loads(own.group(2))
    # 1 kHz of its clock from the daemon's request (within its first 2 s) to the end
    assert 1000.0 * (simulated_s - 2.0) <= sent_by_type["RAW_IMU"] <= 1000.0 * simulated_s + 1
    sent = sum(sent_by_type.get(k, 0) for k in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU"))  # as imu_messages counts
    kernel = re.search(r"msg=stopped .*kernel_rx_drops=(\d+)", (Path(r["workdir"]) / "daemon.log").read_text())
    assert kernel, "no kernel_rx_drops in the daemon's stopped line"
    assert r["imu_messages"] <= sent and 0.85 * sent <= r["imu_messages"] + int(kernel.group(1))
    assert r["imu_lost_inside_daemon"] == 0
    assert r["imu_rejected"] == 0  # clean data: nothing for the input checks to reject
    # bounded: the only store that grows in flight is method A's fit buffer (max_fit_samples 1500
    # magnetometer records, full after 150 s of flight); measured +2.6 MB over these 2 minutes
    assert r["rss_end_mb"] - r["rss_start_mb"] < 5.0
