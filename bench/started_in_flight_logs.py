"""Roll/pitch of runs that start in flight, replayed from logs, scored after the first seconds of flight.

    python bench/started_in_flight_logs.py [--after-s 30] [--window-s 15] [--json PATH] LOG [LOG ...]

An ArduPilot DataFlash log starts at arming (an ArduPlane take-off run is already accelerating) and a
daemon restarted by systemd starts wherever the flight is: the replay then finds the run "started in
flight" (service/phases.py) and method C's attitude filter starts from the trusted FC attitude
(service/pipeline.py ``_start_in_flight``) with no rest to measure its gyro bias. Each LOG is replayed
as `azimuthd replay` does (service/replay.py: the config built from the log, the FC's yaw excluded
where the log says it came from our own ODOMETRY) and scored:

- against the FC's attitude (the log's ATT / ATTITUDE: the FC's GNSS-aided estimate, a reference);
- against the simulator's truth where the log carries it (ArduPilot SITL's SIM record: score only,
  never fed to the Pipeline).

Per log: whether the run started in flight and when; the flight's start (the log's own take-off,
else the first output row); roll / pitch RMS and max |error| from ``--after-s`` seconds after that
start to the end, and the mean error per ``--window-s`` window from the first row (what shows a
tilt error that settles or one that stays); the share of rows whose error is within 3 published
sigmas after ``--after-s``.

JSON (default bench/results/started_in_flight_logs.json): ``logs.<name>`` with unit-suffixed keys.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.logreaders import LogError, open_log  # noqa: E402
from service.replay import ReplayError, build_config, json_safe, run_replay  # noqa: E402


def _sim_truth(path: Path) -> np.ndarray | None:
    """(time s, roll deg, pitch deg) rows of ArduPilot SITL's SIM record, None when the log has none.
    Read for scoring only: nothing here reaches the Pipeline."""
    if path.suffix.lower() != ".bin":
        return None
    from pymavlink import mavutil
    m = mavutil.mavlink_connection(str(path))
    rows = []
    while True:
        msg = m.recv_match(type=["SIM"])
        if msg is None:
            break
        d = msg.to_dict()
        rows.append((d["TimeUS"] * 1e-6, d["Roll"], d["Pitch"]))
    return np.array(rows) if rows else None


def _wrap_deg(x: np.ndarray) -> np.ndarray:
    return (x + 180.0) % 360.0 - 180.0


def _scores(t, err_roll, err_pitch, sig_roll, sig_pitch, start_s, after_s, window_s) -> dict:
    ok = np.isfinite(err_roll) & np.isfinite(err_pitch)
    out: dict = {}
    m = ok & (t >= start_s + after_s)
    if m.any():
        out.update(roll_rms_deg=float(np.sqrt(np.mean(err_roll[m] ** 2))),
                   pitch_rms_deg=float(np.sqrt(np.mean(err_pitch[m] ** 2))),
                   roll_max_abs_deg=float(np.max(np.abs(err_roll[m]))),
                   pitch_max_abs_deg=float(np.max(np.abs(err_pitch[m]))),
                   within_3_sigma_pct=float(100.0 * np.mean((np.abs(err_roll[m]) <= 3.0 * sig_roll[m])
                                                            & (np.abs(err_pitch[m]) <= 3.0 * sig_pitch[m]))),
                   rows_scored=int(m.sum()))
    else:
        out.update(roll_rms_deg=math.nan, pitch_rms_deg=math.nan, rows_scored=0)
    windows = []
    if ok.any():
        t0 = float(t[ok][0])
        for a in np.arange(t0, float(t[ok][-1]), window_s):
            w = ok & (t >= a) & (t < a + window_s)
            if w.any():
                windows.append({"from_s": float(a), "roll_mean_deg": float(np.mean(err_roll[w])),
                                "pitch_mean_deg": float(np.mean(err_pitch[w]))})
    out["windows"] = windows
    return out


def replay_one(path: Path, after_s: float, window_s: float) -> dict:
    reader = open_log(str(path))
    cfg, notes = build_config(types.SimpleNamespace(config=None, site=None, exclude_fc_yaw=False), reader)
    if hasattr(reader, "imu_gap_s"):
        reader.imu_gap_s = cfg["mavlink"]["imu_gap_s"]
    w0 = time.perf_counter()
    res = run_replay(reader, cfg, None)
    wall = time.perf_counter() - w0
    t = np.array(res.time_s, float)
    roll = np.array(res.cols["roll_deg"], float)
    pitch = np.array(res.cols["pitch_deg"], float)
    sr = np.array(res.roll_sigma_deg, float)
    sp = np.array(res.pitch_sigma_deg, float)
    sif = [e for e in res.events if len(e) >= 3 and e[1] == "started_in_flight"]
    try:
        takeoffs = reader.takeoff_times_s()
    except LogError:
        takeoffs = []
    first = float(t[np.isfinite(roll)][0]) if np.isfinite(roll).any() else math.nan
    start = float(takeoffs[0]) if takeoffs and takeoffs[0] <= t[-1] else first
    out = {"imu_rate_hz": res.imu_samples / max(t[-1] - t[0], 1e-9) if len(t) > 1 else math.nan,
           "started_in_flight_s": float(sif[0][0]) if sif else None,
           "started_in_flight_evidence": sif[0][2] if sif else None,
           "flight_start_s": start, "flight_start_from": "log take-off" if takeoffs else "first row",
           "after_s": after_s, "replay_wall_s": wall,
           "attitude_events": [e[2] for e in res.events if len(e) >= 3 and e[1] == "attitude"][:5],
           "config_notes": notes}
    ref_r = np.array(res.cols["ref_roll_deg"], float)
    ref_p = np.array(res.cols["ref_pitch_deg"], float)
    out["vs_fc"] = _scores(t, _wrap_deg(roll - ref_r), pitch - ref_p, sr, sp, start, after_s, window_s)
    truth = _sim_truth(path)
    if truth is not None:
        tr = np.interp(t, truth[:, 0], truth[:, 1], left=np.nan, right=np.nan)
        tp = np.interp(t, truth[:, 0], truth[:, 2], left=np.nan, right=np.nan)
        # a roll near +-180 deg would interpolate across the wrap: SITL's flights here stay far from it
        out["vs_sim_truth"] = _scores(t, _wrap_deg(roll - tr), pitch - tp, sr, sp, start, after_s, window_s)
        out["fc_vs_sim_truth"] = _scores(t, _wrap_deg(ref_r - tr), ref_p - tp, np.full_like(t, np.inf),
                                         np.full_like(t, np.inf), start, after_s, window_s)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", metavar="LOG")
    ap.add_argument("--after-s", type=float, default=30.0, help="score from this long after the flight's start (s)")
    ap.add_argument("--window-s", type=float, default=15.0, help="mean error per window of this length (s)")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "started_in_flight_logs.json"))
    a = ap.parse_args(argv)
    if not (a.after_s >= 0.0 and a.window_s > 0.0):
        ap.error("--after-s must be >= 0 and --window-s > 0")
    out = {"after_s": a.after_s, "window_s": a.window_s, "logs": {}}
    for name in a.logs:
        p = Path(name)
        try:
            r = replay_one(p, a.after_s, a.window_s)
        except (LogError, ReplayError, OSError) as exc:
            print(f"{p}: not replayed: {exc}")
            out["logs"][str(p)] = {"error": str(exc)}
            continue
        out["logs"][str(p)] = r
        f = r["vs_fc"]
        print(f"{p}  ({r['imu_rate_hz']:.0f} Hz IMU, replayed in {r['replay_wall_s']:.0f} s)")
        print(f"  started in flight: {'at %.1f s (%s)' % (r['started_in_flight_s'], r['started_in_flight_evidence']) if r['started_in_flight_s'] is not None else 'no'}")
        print(f"  flight from {r['flight_start_s']:.1f} s ({r['flight_start_from']}); scored from {a.after_s:g} s after it")
        for key, label in (("vs_fc", "vs the FC"), ("vs_sim_truth", "vs SITL truth"), ("fc_vs_sim_truth", "the FC vs SITL truth")):
            s = r.get(key)
            if s is None:
                continue
            line = f"  {label:22s} roll / pitch RMS {s['roll_rms_deg']:.2f} / {s['pitch_rms_deg']:.2f} deg"
            if s.get("rows_scored"):
                line += f", max {s['roll_max_abs_deg']:.1f} / {s['pitch_max_abs_deg']:.1f} deg"
                if key != "fc_vs_sim_truth":
                    line += f", within 3 sigma {s['within_3_sigma_pct']:.0f} %"
            print(line)
        print("  mean roll/pitch error vs the FC per %g s: " % a.window_s
              + " ".join(f"{w['roll_mean_deg']:+.1f}/{w['pitch_mean_deg']:+.1f}" for w in f["windows"]))
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(json_safe(out), indent=2) + "\n")
    print(f"json: {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
