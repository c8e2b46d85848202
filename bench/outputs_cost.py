"""Cost of the outputs per NavSolution, and Zenoh delivery latency to another process.

    python bench/outputs_cost.py [--quick] [--json PATH]

Figures:
- encode_us_per_solution: OutputScheduler.messages + sending the due messages as the daemon does
  (mavlink_io/frame_pack) to a null file, mean over 200 Hz solutions with the default rates, best of
  3; ``encode_pymavlink_us_per_solution`` the same with pymavlink's MAVLink.send, alternated with it;
- zenoh_publish_us_per_solution: ZenohBus.publish_solution (default rates) with a subscriber;
- zenoh_latency_p50_ms / p99_ms: put -> callback in a subscriber process on loopback (the
  subscriber reports its receive time on the same monotonic clock, CLOCK_MONOTONIC is
  system-wide on Linux).
"""
from __future__ import annotations

import argparse
import json
import math
import socket
import subprocess
import sys
import time
from pathlib import Path

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.rotations import quat_from_euler  # noqa: E402
from mavlink_io import frame_pack, outputs  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402
from mavlink_io.navsolution import NavSolution  # noqa: E402
from service.zenoh_bus import ZenohBus  # noqa: E402

SUB = r"""
import json, sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"'); conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
s = zenoh.open(conf)
n = int(sys.argv[2]); got = []
def cb(x):
    got.append((json.loads(x.payload.to_string())["seq_count"], time.monotonic()))
sub = s.declare_subscriber("azimuthd/bench/events", cb)
print("ready", flush=True)
t_end = time.monotonic() + 60
while len(got) < n and time.monotonic() < t_end:
    time.sleep(0.01)
print(json.dumps(got), flush=True)
s.close()
"""


def solution(k: int) -> NavSolution:
    yaw = math.radians(100.0 + 0.01 * k)
    return NavSolution(time_fc_s=k * 0.005, time_rx_s=k * 0.005, phase="in-flight",
                       q_nav_from_body=quat_from_euler(0.1, 0.05, yaw), roll_rad=0.1,
                       pitch_rad=0.05, rates_body_rad_s=np.array([0.01, 0.0, 0.02]),
                       roll_sigma_rad=0.01, pitch_sigma_rad=0.01, heading_rad=yaw,
                       heading_sigma_rad=0.03, heading_source="azimuth", heading_valid=True,
                       azimuth_rad=yaw, azimuth_sigma_rad=0.02)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "outputs_cost.json"))
    args = ap.parse_args(argv)
    n = 2000 if args.quick else 20000
    sols = [solution(k) for k in range(n)]

    class _Null:
        def write(self, buf) -> None:
            pass

    def encode(send) -> float:
        """Mean us per solution: the due messages built and sent by ``send(mav, msg)`` to a null file."""
        sched = outputs.OutputScheduler(profile=outputs.ODOMETRY_PROFILES["ardupilot"])
        mav = mavlink2.MAVLink(_Null(), srcSystem=1, srcComponent=191)
        t0 = time.perf_counter()
        for k, sol in enumerate(sols):
            for msg in sched.messages(sol, k * 0.005):
                send(mav, msg)
        return (time.perf_counter() - t0) / n * 1e6

    # what the daemon sends with (frame_pack) and pymavlink's own send, alternated, best of 3 each
    fast, slow = [], []
    for _ in range(3):
        fast.append(encode(frame_pack.send))
        slow.append(encode(lambda mav, msg: mav.send(msg)))
    encode_us, encode_pymavlink_us = min(fast), min(slow)

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    n_lat = 200 if args.quick else 1000
    sub = subprocess.Popen([sys.executable, "-c", SUB, endpoint, str(n_lat)],
                           stdout=subprocess.PIPE, text=True)
    bus = ZenohBus("bench", "peer", [endpoint], [])
    assert sub.stdout.readline().strip() == "ready"
    time.sleep(1.5)  # let the subscriber connect (it retries about once a second)
    t0 = time.perf_counter()
    for k, sol in enumerate(sols):
        bus.publish_solution(sol, k * 0.005)
    publish_us = (time.perf_counter() - t0) / n * 1e6
    sent: dict[int, float] = {}
    for i in range(n_lat):
        sent[i] = time.monotonic()
        bus.publish("events", {"time_rx_s": sent[i], "kind": "bench", "severity": "debug",
                               "detail": "latency", "seq_count": i})
        time.sleep(0.002)
    got = json.loads(sub.stdout.readline())
    sub.wait(30)
    bus.close()
    lat_ms = np.array([(t - sent[i]) * 1e3 for i, t in got])
    res = {"encode_us_per_solution": round(encode_us, 2),
           "encode_pymavlink_us_per_solution": round(encode_pymavlink_us, 2),
           "load_avg_1min": round(os.getloadavg()[0], 2),
           "zenoh_publish_us_per_solution": round(publish_us, 2),
           "zenoh_latency_p50_ms": round(float(np.percentile(lat_ms, 50)), 3),
           "zenoh_latency_p99_ms": round(float(np.percentile(lat_ms, 99)), 3),
           "zenoh_delivered_count": int(len(lat_ms)), "zenoh_sent_count": n_lat}
    for k, v in res.items():
        print(f"{k:32s} {v}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
