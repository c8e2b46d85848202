"""Is the log's own FC heading a reference at all? Its yaw against the log's own gyros.

    python bench/fc_reference_yaw.py [--json PATH] [--window-s S] [--limit-deg D] [FOLDER_OR_LOG ...]

bench/real_logs.py scores our heading against the FC's attitude in the log (not truth). Where the
FC had no GNSS its heading rests on its own magnetometer and may jump: an estimator correction, not
a rotation. The log's gyros say which: over every window of ``--window-s`` seconds the FC's yaw
change is compared with the yaw change its gyros give (the Euler yaw rate (q sin(phi) + r cos(phi))
/ cos(theta) integrated with the FC's own roll/pitch; no bias removed: 0.1 deg/s of gyro bias is
0.5 deg in 5 s). A window where they differ by more than ``--limit-deg`` is a reference step the
vehicle did not make; rows after it are scored against a reference that moved on its own.
Everything here comes from the log (its gyros and its FC attitude); nothing reaches an estimator.
Logs whose IMU is slower than 20 Hz are skipped (their gyros cannot be integrated; ArduPilot logs
its IMU samples at ~25 Hz: integrated as they are, a control of the method on a GNSS-aided FC).

JSON (bench/results/fc_reference_yaw.json): per log ``logs.<file>.max_unsupported_yaw_deg`` (the
largest |FC yaw change - gyro yaw change| over a window), ``at_s`` (its window's start, FC time),
``windows_over_limit_fraction``, ``fc_yaw_change_deg`` and ``gyro_yaw_change_deg`` of that window,
``imu_rate_hz``; or ``skipped`` with the reason.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
MIN_IMU_RATE_HZ = 20.0


def yaw_against_gyros(path: pathlib.Path, window_s: float, limit_deg: float) -> dict:
    from mavlink_io.samples import FcAttitude, ImuSample
    from service.logreaders import LogError, open_log
    try:
        reader = open_log(path)
        imu, att = [], []
        for it in reader.items():
            if isinstance(it, ImuSample):
                imu.append((it.time_fc_s, *it.gyro_rad_s))
            elif isinstance(it, FcAttitude):
                att.append((it.time_fc_s, it.roll_rad, it.pitch_rad, it.yaw_rad))
    except LogError as exc:
        return {"skipped": f"unreadable: {exc}"}
    if len(imu) < 100 or len(att) < 10:
        return {"skipped": f"{len(imu)} IMU samples, {len(att)} FC attitudes"}
    g, a = np.array(imu), np.array(att)
    g = g[np.argsort(g[:, 0], kind="stable")]
    dt = np.diff(g[:, 0])
    rate = 1.0 / float(np.median(dt[dt > 0])) if np.any(dt > 0) else 0.0
    if rate < MIN_IMU_RATE_HZ:
        return {"skipped": f"IMU at {rate:.1f} Hz (< {MIN_IMU_RATE_HZ:.0f} Hz): its gyros cannot be integrated",
                "imu_rate_hz": rate}
    a = a[np.argsort(a[:, 0], kind="stable")]
    # the FC's roll/pitch at each IMU sample; the Euler yaw rate; its integral (gaps > 0.1 s not bridged)
    phi = np.interp(g[:, 0], a[:, 0], np.unwrap(a[:, 1]))
    th = np.interp(g[:, 0], a[:, 0], a[:, 2])
    psi_dot = (g[:, 2] * np.sin(phi) + g[:, 3] * np.cos(phi)) / np.maximum(np.cos(th), 0.1)
    step = np.where((dt > 0) & (dt <= 0.1), psi_dot[:-1] * dt, 0.0)
    gyro_yaw = np.concatenate([[0.0], np.cumsum(step)])
    fc_yaw = np.unwrap(a[:, 3])
    t0, t1 = max(g[0, 0], a[0, 0]), min(g[-1, 0], a[-1, 0])
    starts = np.arange(t0, t1 - window_s, 0.5)
    if not len(starts):
        return {"skipped": f"shorter than the {window_s} s window", "imu_rate_hz": rate}
    ends = starts + window_s
    d_fc = np.interp(ends, a[:, 0], fc_yaw) - np.interp(starts, a[:, 0], fc_yaw)
    d_gy = np.interp(ends, g[:, 0], gyro_yaw) - np.interp(starts, g[:, 0], gyro_yaw)
    diff = np.degrees(np.abs(d_fc - d_gy))
    k = int(np.argmax(diff))
    return {"imu_rate_hz": rate, "windows": int(len(starts)), "max_unsupported_yaw_deg": float(diff[k]),
            "at_s": float(starts[k]), "fc_yaw_change_deg": float(np.degrees(d_fc[k])),
            "gyro_yaw_change_deg": float(np.degrees(d_gy[k])),
            "windows_over_limit_fraction": float(np.mean(diff > limit_deg))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="*", type=pathlib.Path)
    ap.add_argument("--json", type=pathlib.Path, default=ROOT / "bench" / "results" / "fc_reference_yaw.json")
    ap.add_argument("--window-s", type=float, default=5.0)
    ap.add_argument("--limit-deg", type=float, default=5.0)
    ap.add_argument("--quick", action="store_true", help="same logs (they are short); kept for the bench contract")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.window_s) and args.window_s > 0 and math.isfinite(args.limit_deg) and args.limit_deg > 0):
        ap.error("--window-s and --limit-deg must be finite and > 0")
    from bench.real_logs import find_logs
    logs = find_logs(args.paths or [DATA])
    if not logs:
        ap.error(f"no .tlog/.bin/.ulg under {', '.join(map(str, args.paths or [DATA]))}")
    res = {"window_s": args.window_s, "limit_deg": args.limit_deg, "logs": {}}
    for log in logs:
        r = yaw_against_gyros(log, args.window_s, args.limit_deg)
        res["logs"][log.name] = r
        if "skipped" in r:
            print(f"{log.name:32s} skipped: {r['skipped']}")
        else:
            print(f"{log.name:32s} IMU {r['imu_rate_hz']:.0f} Hz: largest FC yaw change the gyros do not make "
                  f"{r['max_unsupported_yaw_deg']:.1f} deg in the {args.window_s:g} s from {r['at_s']:.1f} s "
                  f"(FC {r['fc_yaw_change_deg']:+.1f}, gyros {r['gyro_yaw_change_deg']:+.1f} deg); "
                  f"{100 * r['windows_over_limit_fraction']:.1f} % of windows over {args.limit_deg:g} deg")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=1))
    print(f"json: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
