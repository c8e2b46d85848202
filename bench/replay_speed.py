"""``azimuthd replay`` speed in x real time: a 400 Hz telemetry log and the real logs (issue 19: >= 200x).

    python bench/replay_speed.py [--seconds 40] [--logs DIR] [--only NAME ...] [--json PATH] [--quick]

The 400 Hz log: the bundled simulator in this process (``inclined_rail``, rest shortened to 6 s so
that a launch and flight are in it), RAW_IMU 400 Hz, SCALED_PRESSURE and ATTITUDE 50 Hz, HEARTBEAT,
SYS_STATUS and EKF_STATUS_REPORT 2 Hz, written as a .tlog (8-byte receive time + frame) exactly as a
ground station records one. Then every log goes through ``azimuthd replay LOG --output CSV --json``
as its own process, as a user runs it. Per log:

- ``log_s``: the IMU's span in FC time (the log's duration where the estimators run);
- ``replay_x_realtime``: log_s / the process's wall time (load-dependent: the load is beside it);
- ``replay_x_realtime_cpu``: log_s / the process's CPU time (user + system: the work itself);
- ``pipeline_us_per_imu_sample`` and ``overhead_us_per_imu_sample``: the replay's own split of its
  loop's wall time per IMU sample: in the Pipeline, and the rest (reading and decoding the log,
  the CSV); start-up (imports, the log's pre-scan) is in the process's figures only;
- ``reader_cpu_us_per_imu_sample``: the log reader alone (``open_log(LOG).items(imu_batches=True)``
  iterated in this process, as the replay reads it, no Pipeline): CPU per IMU sample of reading and
  decoding the log, best of two;
- ``startup_s``: the process's wall time outside the replay's loop (interpreter, imports, opening
  and pre-scanning the log, the config; the summary and JSON at the end): paid once per log;
- ``replay_x_realtime_loop``: log_s / the loop's wall time: the x real time a log long enough to
  make ``startup_s`` negligible approaches (a flight log of 10-30 min, not this bench's 40 s).

The replay runs with Python's bytecode cache as an installed azimuthd has it (pip compiles it at
install): the environment's PYTHONDONTWRITEBYTECODE is dropped and the cache kept in the work
directory (PYTHONPYCACHEPREFIX), warmed by one ``replay --help`` first; ``--no-bytecode-cache``
measures a start that compiles every module (``bytecode_cached`` in the JSON says which).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
REAL_LOGS = ROOT.parent / "shared" / "data"
RATES_HZ = {27: 400.0, 29: 50.0, 30: 50.0, 1: 2.0, 193: 2.0}
"""RAW_IMU, SCALED_PRESSURE, ATTITUDE, SYS_STATUS, EKF_STATUS_REPORT (HEARTBEAT: the simulator's 1 Hz)."""
EPOCH_S = 1_767_225_600.0   # 2026-01-01 UTC: the log's receive clock
NO_FIX_SITES = {"px4-bench-sample.ulg": {"lat_deg": 47.397, "lon_deg": 8.546},
                "px4-quad-no-gnss.ulg": {"lat_deg": 47.397, "lon_deg": 8.546}}
"""Logs with no GNSS position: the site bench/real_logs.py assumes for them (speed does not depend on it)."""


class _TlogWriter:
    """The simulator's connection: every frame it sends becomes a tlog record."""

    def __init__(self, fh, sysid: int, compid: int):
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2
        self.fh, self.t = fh, 0.0
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)

    def write(self, buf) -> None:
        self.fh.write(struct.pack(">Q", int(round((EPOCH_S + self.t) * 1e6))) + bytes(buf))


def make_tlog_400hz(path: Path, seconds: float, seed: int = 1) -> dict:
    """The simulated 400 Hz flight as a .tlog; returns the site the replay is told."""
    from bench.sitl import scenario_site
    from sim.autopilot import Autopilot
    scen = path.with_suffix(".toml")
    scen.write_text((ROOT / "sim" / "scenarios" / "inclined_rail.toml").read_text()
                    .replace("rest_s = 60.0", "rest_s = 6.0"))
    ap = Autopilot(str(scen), "udpout:127.0.0.1:9", personality="ardupilot", seed=seed)
    with open(path, "wb") as fh:
        w = ap.conn = _TlogWriter(fh, ap.sysid, ap.compid)
        for mid, hz in RATES_HZ.items():
            ap.set_interval(mid, 1e6 / hz)
        while ap.t < seconds:
            ap.t = w.t = min(s.next_s for s in ap.streams.values())
            for mid, st in list(ap.streams.items()):
                if st.next_s <= ap.t + 1e-9 and ap.streams.get(mid) is st:
                    ap._send(ap._build(mid, st))
                    st.next_s += st.interval_s
    return scenario_site(str(scen))["site"]


def replay_env(workdir: Path, bytecode_cache: bool = True) -> dict:
    """The replay process's environment: with ``bytecode_cache``, Python's bytecode cache in
    ``workdir`` (PYTHONDONTWRITEBYTECODE dropped), warmed once, as an installed azimuthd starts."""
    env = dict(os.environ)
    if not bytecode_cache:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
        return env
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["PYTHONPYCACHEPREFIX"] = str(workdir / "pycache")
    subprocess.run([sys.executable, "-m", "service.cli", "replay", "--help"], cwd=ROOT, env=env,
                   capture_output=True, check=False)
    return env


def replay_one(log: Path, workdir: Path, site: dict | None = None, env: dict | None = None) -> dict:
    out_csv, out_json = workdir / (log.stem + ".csv"), workdir / (log.stem + ".json")
    cmd = [sys.executable, "-m", "service.cli", "replay", str(log), "--output", str(out_csv), "--json",
           str(out_json), "--no-progress"]
    if site is not None:
        cmd += ["--site", f"{site['lat_deg']},{site['lon_deg']},{site.get('alt_m', 0.0)}"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        return {"log": log.name, "error": (proc.stderr or proc.stdout).strip().splitlines()[-1:]}
    s = json.loads(out_json.read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    n = s["imu_samples"]
    log_s = float(s["log_duration_s"])
    pipe_us = s["pipeline_us_per_imu_sample"]
    return {"log": log.name, "imu_samples": n, "log_s": log_s, "imu_rate_hz": n / log_s if log_s > 0 else None,
            "wall_s": wall, "cpu_s": cpu, "replay_x_realtime": log_s / wall, "replay_x_realtime_cpu": log_s / cpu,
            "pipeline_us_per_imu_sample": pipe_us, "overhead_us_per_imu_sample": s["total_us_per_imu_sample"] - pipe_us,
            "in_process_wall_s": s["wall_time_s"], "startup_s": wall - s["wall_time_s"],
            "replay_x_realtime_loop": log_s / s["wall_time_s"],
            "bytecode_cached": env is not None and "PYTHONDONTWRITEBYTECODE" not in env,
            "load_avg_1min": os.getloadavg()[0]}


def reader_cpu_us(log: Path) -> float:
    """CPU per IMU sample of iterating the log reader alone (no Pipeline, no CSV), best of two."""
    from mavlink_io.imu_batch import ImuBatch
    from mavlink_io.samples import ImuSample
    from service.logreaders import open_log
    best = float("inf")
    for _ in range(2):
        reader = open_log(str(log))
        c0, n = time.process_time(), 0
        for item in reader.items(imu_batches=True):
            n += len(item) if isinstance(item, ImuBatch) else isinstance(item, ImuSample)
        best = min(best, (time.process_time() - c0) / max(n, 1) * 1e6)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=40.0, help="length of the simulated 400 Hz log")
    ap.add_argument("--logs", default=str(REAL_LOGS), help="directory of real logs (.tlog .bin .ulg)")
    ap.add_argument("--only", action="append", default=[], metavar="NAME", help="only these logs (file names; "
                    "'sim-400hz' for the simulated one)")
    ap.add_argument("--quick", action="store_true", help="a 15 s simulated log, no real logs")
    ap.add_argument("--no-bytecode-cache", action="store_true",
                    help="replay processes compile every module (PYTHONDONTWRITEBYTECODE=1) instead of "
                         "starting from a bytecode cache as an installed azimuthd does")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-replay-speed-"))
    env = replay_env(workdir, not a.no_bytecode_cache)
    rows = []
    if not a.only or "sim-400hz" in a.only:
        tlog = workdir / "sim-400hz.tlog"
        site = make_tlog_400hz(tlog, 15.0 if a.quick else a.seconds)
        rows.append(replay_one(tlog, workdir, site, env))
        rows[-1]["reader_cpu_us_per_imu_sample"] = reader_cpu_us(tlog)
    if not a.quick:
        for log in sorted(Path(a.logs).glob("*")):
            if log.suffix in (".tlog", ".bin", ".ulg") and (not a.only or log.name in a.only):
                site = NO_FIX_SITES.get(log.name)
                rows.append(replay_one(log, workdir, site, env))
                rows[-1]["reader_cpu_us_per_imu_sample"] = reader_cpu_us(log)
    for r in rows:
        if "error" in r:
            print(f"{r['log']:<32} error: {r['error']}")
            continue
        print(f"{r['log']:<32} {r['imu_samples']:7d} IMU ({r['imu_rate_hz']:5.0f} Hz, {r['log_s']:6.1f} s): "
              f"{r['replay_x_realtime']:6.1f}x real time wall, {r['replay_x_realtime_cpu']:6.1f}x per CPU second, "
              f"{r['replay_x_realtime_loop']:6.1f}x without the {r['startup_s']:.2f} s start; "
              f"Pipeline {r['pipeline_us_per_imu_sample']:6.0f} us + the rest {r['overhead_us_per_imu_sample']:5.0f} us wall "
              f"per IMU sample; the log reader alone {r['reader_cpu_us_per_imu_sample']:5.0f} us CPU "
              f"(load {r['load_avg_1min']:.1f})")
    if a.json:
        Path(a.json).write_text(json.dumps({"rows": rows, "workdir": str(workdir)}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
