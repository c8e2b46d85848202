"""`make run`: the bundled simulator and the daemon as two processes on loopback.

The daemon prints its live status line (phase, roll/pitch/heading with sigma, link rates); at the
end this harness compares what the daemon SENT (its ATTITUDE, received on a ground-station port)
with the simulator's truth log, and prints a summary. The daemon never sees the truth.

    python bench/live_demo.py [--scenario NAME] [--speed X] [--duration S] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sitl import Sitl, angle_diff_rad  # noqa: E402


def compare_with_truth(attitude: list, truth: dict, launch_time_s: float | None) -> dict:
    """RMS/max of the daemon's ATTITUDE against the truth at the same FC time."""
    if not attitude:
        return {"attitude_messages": 0}
    a = np.array([row[:4] for row in attitude], dtype=float)
    t = a[:, 0]
    tt = truth["time_boot_s"]
    keep = (t >= tt[0]) & (t <= tt[-1])
    a, t = a[keep], t[keep]
    eul = np.column_stack([truth["roll_rad"], truth["pitch_rad"], truth["yaw_rad"]])
    idx = np.clip(np.searchsorted(tt, t), 0, len(tt) - 1)
    d_roll = np.degrees(angle_diff_rad(a[:, 1], eul[idx, 0]))
    d_pitch = np.degrees(angle_diff_rad(a[:, 2], eul[idx, 1]))
    out = {"attitude_messages": int(len(a)),
           "roll_rms_deg": float(np.sqrt(np.mean(d_roll ** 2))), "roll_max_abs_deg": float(np.max(np.abs(d_roll))),
           "pitch_rms_deg": float(np.sqrt(np.mean(d_pitch ** 2))), "pitch_max_abs_deg": float(np.max(np.abs(d_pitch)))}
    valid = np.isfinite(a[:, 3])
    out["heading_valid_fraction"] = float(np.mean(valid))
    if np.any(valid):
        d_yaw = np.degrees(angle_diff_rad(a[valid, 3], eul[idx[valid], 2]))
        out["heading_rms_deg"] = float(np.sqrt(np.mean(d_yaw ** 2)))
        out["heading_max_abs_deg"] = float(np.max(np.abs(d_yaw)))
        if launch_time_s is not None and math.isfinite(launch_time_s):
            # negative: a heading (magnetometer, FC) was valid on the launcher already
            out["first_heading_after_launch_s"] = float(t[valid][0] - launch_time_s)
    if launch_time_s is not None and math.isfinite(launch_time_s):
        first = (t >= launch_time_s) & (t <= launch_time_s + 60.0)
        if np.any(first):
            out["first_60s_after_launch_roll_pitch_max_abs_deg"] = float(
                max(np.max(np.abs(d_roll[first])), np.max(np.abs(d_pitch[first]))))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="inclined_rail")
    ap.add_argument("--speed", type=float, default=4.0, help="simulated seconds per wall second")
    ap.add_argument("--duration", type=float, default=300.0, help="simulated seconds to fly")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="a 120 s flight")
    ap.add_argument("--json", default=str(Path(__file__).resolve().parent / "results" / "live_demo.json"))
    args = ap.parse_args(argv)
    duration = 120.0 if args.quick else args.duration
    wall = duration / args.speed
    print(f"azimuthd demo: scenario {args.scenario}, {duration:.0f} s of flight at {args.speed:g}x "
          f"(~{wall:.0f} s); simulator and daemon run as two processes on loopback UDP.", flush=True)
    # Zenoh on, so `azimuthd watch` in another terminal shows the flight live
    sitl = Sitl(scenario=args.scenario, speed=args.speed, seed=args.seed, status_interval_s=1.0,
                sim_args=["--duration", str(duration)], config_overrides={"zenoh": {"enabled": True}})
    with sitl:
        print(f"  daemon: {' '.join(sitl.daemon_cmd[2:])}\n  sim:    {' '.join(sitl.sim_cmd[2:])}\n", flush=True)
        shown = 0
        t_end = time.monotonic() + wall + 20.0
        while time.monotonic() < t_end and sitl.sim.poll() is None:
            time.sleep(0.5)
            lines = [ln for ln in sitl.log("daemon").splitlines() if ln.startswith("phase=")]
            for ln in lines[shown:]:
                print("  " + ln, flush=True)
            shown = len(lines)
        time.sleep(0.5)
    truth = sitl.truth()
    launch = truth["launch_time_boot_s"]
    summary = {"scenario": args.scenario, "simulated_s": duration, "speed": args.speed,
               **compare_with_truth(sitl.listener.attitude, truth, launch),
               "daemon_heartbeats_seen": sitl.listener.heartbeats}
    print("\nSummary against the simulator's truth (what the daemon sent, not what it logged):")
    for k, v in summary.items():
        print(f"  {k:<48} {v:.3f}" if isinstance(v, float) else f"  {k:<48} {v}")
    errors = [ln for ln in sitl.log("daemon").splitlines() if "level=error" in ln]
    if errors:
        print(f"  daemon errors: {len(errors)} (first: {errors[0]})")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(summary, indent=2))
    print(f"  written to {args.json}; logs in {sitl.workdir}")
    return 0 if summary.get("attitude_messages", 0) > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
