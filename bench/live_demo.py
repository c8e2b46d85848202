"""`make run`: the bundled simulator and the daemon as two processes on loopback.

The daemon prints its live status line (phase, roll/pitch/heading with sigma, link rates); at the
end this harness compares what the daemon SENT (its ATTITUDE, received on a ground-station port)
with the simulator's truth log, and prints a summary that tells what really happened: the
simulated time actually flown and the speed achieved (a busy machine runs the simulator slower
than asked), what the daemon lost (its own counters: kernel drops, sequence loss, IMU gaps), its
warnings, and a PASS/FAIL verdict against the thresholds in VERDICT (each failure says why).
The daemon never sees the truth.

    python bench/live_demo.py [--scenario NAME] [--speed X] [--duration S] [--quick] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sitl import Sitl, angle_diff_rad, unit_nice  # noqa: E402

README_DEMO_FIGURE = "README, Measured: 300 s at 2x, roll / pitch / heading RMS 0.49 / 0.27 / 0.93 deg"
VERDICT = {
    "flown_fraction_min": 0.95,        # of the requested simulated time
    "imu_lost_fraction_max": 0.01,     # IMU messages the simulator sent that the daemon never got
    "roll_rms_deg_max": 1.0,           # the project's attitude target (README: method B, <= 1 deg RMS)
    "pitch_rms_deg_max": 1.0,
    "heading_rms_deg_max": 2.0,        # the project's heading target (README: <= 2 deg RMS)
    "daemon_errors_max": 0,
    "attitude_rate_fraction_min": 0.5,  # of [outputs] attitude_hz, as received by the ground station
}
"""PASS needs every one; the accuracy thresholds are the README's targets, not its demo figure
(README_DEMO_FIGURE), which a healthy run is printed beside."""
WALL_LIMIT_FACTOR = 3.0
"""Wait for the simulator's end up to this many times the requested wall time (+ 60 s), then stop:
a machine too busy to keep up gives a FAIL that says so, not a summary of a flight never flown."""


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
    rx = np.array([row[4] for row in attitude], dtype=float)
    out = {"attitude_messages": int(len(a)),
           # wall-clock rate at the ground station while the daemon was sending
           "attitude_received_hz": float((len(rx) - 1) / (rx[-1] - rx[0])) if len(rx) > 1 and rx[-1] > rx[0] else 0.0,
           "roll_rms_deg": float(np.sqrt(np.mean(d_roll ** 2))), "roll_max_abs_deg": float(np.max(np.abs(d_roll))),
           "pitch_rms_deg": float(np.sqrt(np.mean(d_pitch ** 2))), "pitch_max_abs_deg": float(np.max(np.abs(d_pitch)))}
    valid = np.isfinite(a[:, 3])
    out["heading_valid_fraction"] = float(np.mean(valid))
    if np.any(valid):
        d_yaw = np.degrees(angle_diff_rad(a[valid, 3], eul[idx[valid], 2]))
        out["heading_rms_deg"] = float(np.sqrt(np.mean(d_yaw ** 2)))
        out["heading_max_abs_deg"] = float(np.max(np.abs(d_yaw)))
        out["first_valid_heading_time_boot_s"] = float(t[valid][0])
        if launch_time_s is not None and math.isfinite(launch_time_s):
            # < 0: a heading (the FC's own yaw, the magnetometer) was valid on the launcher already
            out["first_valid_heading_minus_launch_s"] = float(t[valid][0] - launch_time_s)
    if launch_time_s is not None and math.isfinite(launch_time_s):
        first = (t >= launch_time_s) & (t <= launch_time_s + 60.0)
        if np.any(first):
            out["first_60s_after_launch_roll_pitch_max_abs_deg"] = float(
                max(np.max(np.abs(d_roll[first])), np.max(np.abs(d_pitch[first]))))
    return out


def logfmt_fields(line: str) -> dict[str, str]:
    """key=value pairs of one logfmt line (service/logs.py), quotes removed."""
    import shlex
    out = {}
    try:
        parts = shlex.split(line)
    except ValueError:
        return out
    for part in parts:
        if "=" in part:
            k, v = part.split("=", 1)
            out[k] = v
    return out


def daemon_health(log: str) -> dict:
    """What the daemon itself counted (its 'stopped' line, IMU gap and warning events)."""
    out: dict = {}
    stopped = next((ln for ln in reversed(log.splitlines()) if "msg=stopped" in ln), None)
    if stopped:
        f = logfmt_fields(stopped)
        for key in ("imu_messages", "imu_samples", "imu_rejected", "link_seq_lost", "kernel_rx_drops",
                    "link_bad_data", "link_stale_drops", "link_losses", "fc_reboots"):
            if key in f and f[key].lstrip("-").isdigit():
                out[key] = int(f[key])
    gaps = [float(m.group(1)) for m in re.finditer(r"IMU gap of ([0-9.]+) s", log)]
    out["imu_gaps"] = len(gaps)
    out["imu_gap_max_s"] = max(gaps) if gaps else 0.0
    warnings: dict[str, list] = {}
    for ln in log.splitlines():
        if "level=warning" in ln or "level=error" in ln:
            f = logfmt_fields(ln)
            kind = f.get("event") or f.get("msg", "?")
            warnings.setdefault(kind, [0, f.get("msg", ""), f.get("level", "")])[0] += 1
    out["warnings"] = warnings
    out["errors"] = sum(v[0] for v in warnings.values() if v[2] == "error")
    return out


def sim_outcome(log: str) -> dict:
    """The simulator's own end-of-run line (sim/cli.py): simulated time, wall time, what it sent."""
    m = re.search(r"sim stopped: simulated_s=([0-9.]+) wall_s=([0-9.]+) achieved_speed=([0-9.naN]+) sent=(\{.*\})", log)
    if not m:
        return {}
    return {"simulated_s": float(m.group(1)), "wall_s": float(m.group(2)), "sent": json.loads(m.group(4))}


def configured_attitude_hz(config_path) -> float:
    import tomllib
    with open(config_path, "rb") as f:
        return float(tomllib.load(f).get("outputs", {}).get("attitude_hz", 50.0))


DRAIN_WAIT_S = 30.0


def stop_simulator_then_drain(sitl) -> None:
    """Stop the simulator first and let the daemon read what is still queued for it (it says
    link_lost once it has read everything and heard nothing for its link timeout), so that
    'sent - received' counts only what was really lost. Bounded by DRAIN_WAIT_S."""
    import signal
    import subprocess
    losses_before = sitl.log("daemon").count("event=link_lost")
    if sitl.sim.poll() is None:
        sitl.sim.send_signal(signal.SIGTERM)
    try:
        sitl.sim.wait(DRAIN_WAIT_S)
    except subprocess.TimeoutExpired:  # Sitl.stop kills it
        return
    t_end = time.monotonic() + DRAIN_WAIT_S
    while time.monotonic() < t_end and sitl.log("daemon").count("event=link_lost") <= losses_before \
            and sitl.daemon.poll() is None:
        time.sleep(0.2)


def last_line(text: str) -> str:
    """The daemon's last non-empty output line (for a crash: the exception), cut to 200 characters."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1][:200] if lines else ""


def verdict(summary: dict, requested_s: float, speed: float) -> list[str]:
    """The failed checks, each as one sentence with the measured value and the threshold."""
    v, why = VERDICT, []
    flown = summary.get("simulated_flown_s", 0.0)
    if flown < v["flown_fraction_min"] * requested_s:
        why.append(f"the simulator flew only {flown:.1f} s of the {requested_s:.0f} s asked (< "
                   f"{v['flown_fraction_min']:.0%}) at {summary.get('speed_achieved_x', 0):.2f}x instead of "
                   f"{speed:g}x: the machine is too busy for this speed; try --speed 1")
    lost = summary.get("imu_lost_fraction")
    if lost is None:
        why.append("the IMU loss could not be counted (no end-of-run line from the simulator or the daemon)")
    elif lost > v["imu_lost_fraction_max"]:
        why.append(f"the daemon lost {lost:.1%} of the IMU messages (> {v['imu_lost_fraction_max']:.0%})")
    for axis in ("roll", "pitch", "heading"):
        rms, lim = summary.get(f"{axis}_rms_deg"), v[f"{axis}_rms_deg_max"]
        if rms is None:
            why.append(f"no {axis} was received from the daemon")
        elif rms > lim:
            why.append(f"{axis} RMS {rms:.2f} deg > {lim:g} deg")
    got, asked = summary.get("attitude_received_hz"), summary.get("attitude_configured_hz")
    if got is not None and asked and got < v["attitude_rate_fraction_min"] * asked:
        why.append(f"ATTITUDE reached the ground station at {got:.1f} Hz, < {v['attitude_rate_fraction_min']:.0%} "
                   f"of the configured {asked:g} Hz")
    if summary.get("daemon_exited_early"):
        why.append(f"the daemon exited (code {summary.get('daemon_exit_code')}) before the harness stopped it: "
                   f"{summary.get('daemon_last_line') or 'no output'}")
    if summary.get("daemon_errors", 0) > v["daemon_errors_max"]:
        why.append(f"the daemon logged {summary['daemon_errors']} error(s)")
    return why


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="inclined_rail")
    # 2x: the daemon (pure Python estimators until issue 19's core) needs ~0.6 of a core for 200 Hz RAW_IMU
    # at 2x and more than a whole core at 4x (measured session 4: at 4x it lost 23 % of the IMU and the
    # verdict failed on any machine); a real FC runs at 1x
    ap.add_argument("--speed", type=float, default=2.0, help="simulated seconds per wall second (asked)")
    ap.add_argument("--duration", type=float, default=300.0, help="simulated seconds to fly")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="a 120 s flight")
    ap.add_argument("--json", default=str(Path(__file__).resolve().parent / "results" / "live_demo.json"))
    args = ap.parse_args(argv)
    duration = 120.0 if args.quick else args.duration
    wall = duration / args.speed
    limit_s = WALL_LIMIT_FACTOR * wall + 60.0
    print(f"azimuthd demo: scenario {args.scenario}, {duration:.0f} s of flight asked at {args.speed:g}x "
          f"(~{wall:.0f} s; stopped after {limit_s:.0f} s if the machine cannot keep up); simulator and daemon "
          "run as two processes on loopback UDP.", flush=True)
    # Zenoh on, so `azimuthd watch` in another terminal shows the flight live
    # the daemon as the systemd unit runs it: a session (CPU group) of its own at the unit's Nice=
    # (its CPUWeight's stand-in; a negative nice needs root, otherwise the group keeps nice 0)
    group_nice = unit_nice() if os.geteuid() == 0 else None
    print(f"  the daemon runs in its own CPU group at nice {group_nice if group_nice is not None else 0}"
          + (" (the unit's Nice=)" if group_nice is not None else " (not root: the unit's Nice= is not applied)"),
          flush=True)
    sitl = Sitl(scenario=args.scenario, speed=args.speed, seed=args.seed, status_interval_s=1.0,
                sim_args=["--duration", str(duration)], config_overrides={"zenoh": {"enabled": True}},
                daemon_own_session=True, daemon_group_nice=group_nice)
    with sitl:
        print(f"  daemon: {' '.join(sitl.daemon_cmd[2:])}\n  sim:    {' '.join(sitl.sim_cmd[2:])}\n", flush=True)
        shown = 0
        t0 = time.monotonic()
        t_end = t0 + limit_s
        while time.monotonic() < t_end and sitl.sim.poll() is None and sitl.daemon.poll() is None:
            time.sleep(0.5)
            lines = [ln for ln in sitl.log("daemon").splitlines() if ln.startswith("phase=")]
            for ln in lines[shown:]:
                print("  " + ln, flush=True)
            shown = len(lines)
        finished = sitl.sim.poll() is not None
        wall_s = time.monotonic() - t0
        stop_simulator_then_drain(sitl)
        # the daemon must outlive the flight: an exit before the harness stops it is a crash
        daemon_exit = sitl.daemon.poll()
    truth = sitl.truth()
    launch = truth["launch_time_boot_s"]
    sim = sim_outcome(sitl.log("sim"))
    health = daemon_health(sitl.log("daemon"))
    flown = sim.get("simulated_s", float(truth["time_s"][-1]) if len(truth["time_s"]) else 0.0)
    sim_wall = sim.get("wall_s", wall_s)
    imu_sent = sum(sim.get("sent", {}).get(k, 0) for k in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU")) or None
    imu_got = health.get("imu_messages")
    summary = {"scenario": args.scenario, "simulated_requested_s": duration, "simulated_flown_s": flown,
               "simulator_finished": finished, "speed_requested_x": args.speed, "daemon_group_nice": group_nice,
               "speed_achieved_x": flown / sim_wall if sim_wall > 0 else 0.0, "wall_s": wall_s,
               **compare_with_truth(sitl.listener.attitude, truth, launch),
               "attitude_configured_hz": configured_attitude_hz(sitl.config_path),
               "daemon_heartbeats_seen": sitl.listener.heartbeats,
               "imu_messages_sent_by_simulator": imu_sent, "imu_messages_received_by_daemon": imu_got,
               "imu_lost_fraction": (1.0 - imu_got / imu_sent) if imu_sent and imu_got is not None else None,
               **{f"daemon_{k}": v for k, v in health.items() if k != "warnings"},
               "daemon_exited_early": daemon_exit is not None, "daemon_exit_code": daemon_exit,
               "daemon_last_line": last_line(sitl.log("daemon")) if daemon_exit is not None else None}
    print("\nSummary against the simulator's truth (what the daemon sent, not what it logged):")
    for k, v in summary.items():
        print(f"  {k:<48} {v:.3f}" if isinstance(v, float) else f"  {k:<48} {v}")
    rel = summary.get("first_valid_heading_minus_launch_s")
    if rel is not None:
        when = f"{-rel:.1f} s before" if rel < 0 else f"{rel:.1f} s after"
        print(f"  (the first valid heading came {when} launch"
              + (": on the launcher, from the FC's own yaw or the magnetometer)" if rel < 0 else ")"))
    if health["warnings"]:
        print("  daemon warnings and errors (count, kind, first message):")
        for kind, (n, msg, level) in sorted(health["warnings"].items(), key=lambda kv: -kv[1][0]):
            print(f"    {n:5d} {level:<7} " + (f"{kind}: {msg[:110]}" if kind != msg else msg[:120]))
    failed = verdict(summary, duration, args.speed)
    summary["verdict"] = "FAIL" if failed else "PASS"
    summary["verdict_reasons"] = failed
    summary["verdict_thresholds"] = VERDICT
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(summary, indent=2))
    print(f"\n  thresholds: flown >= {VERDICT['flown_fraction_min']:.0%} of the asked time, IMU lost <= "
          f"{VERDICT['imu_lost_fraction_max']:.0%}, roll/pitch RMS <= {VERDICT['roll_rms_deg_max']:g} deg, heading "
          f"RMS <= {VERDICT['heading_rms_deg_max']:g} deg, ATTITUDE received at >= "
          f"{VERDICT['attitude_rate_fraction_min']:.0%} of its configured rate, no daemon error ({README_DEMO_FIGURE})")
    if failed:
        print("VERDICT: FAIL: " + "; ".join(failed))
    else:
        print(f"VERDICT: PASS (roll {summary['roll_rms_deg']:.2f}, pitch {summary['pitch_rms_deg']:.2f}, heading "
              f"{summary['heading_rms_deg']:.2f} deg RMS over {flown:.0f} s flown at {summary['speed_achieved_x']:.1f}x)")
    print(f"  written to {args.json}; logs in {sitl.workdir}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
