"""The daemon's CPU per second of flight, and how often its loop wakes, against the bundled simulator.

    python bench/daemon_cpu.py [--imu-hz 50] [--window-s 40] [--port 47100] [--json PATH] [--quick]
                               [--fixed-wait-s 0.005] [--idle] [--imu-batch] [--sched unit|inherit]
                               [--link-scan core|python]

``azimuthd sim`` (inclined_rail with its rest shortened to 6 s, real time) and ``azimuthd run`` (the
example config with the scenario's site, zenoh off, no extra outputs) as two processes over loopback
UDP on ``--port``, exactly as a user runs them. The simulator starts once the daemon has logged
``started``; after ``--warmup-s`` more (take-off included) the daemon's psutil counters are read over
``--window-s`` of flight:

- ``daemon_cpu_pct``: (user + system CPU time) / wall time, percent of one core (``daemon_user_pct``,
  ``daemon_system_pct``: the two apart; system is the kernel's work for the daemon: select, recv, send);
- ``daemon_cpu_ms_per_imu_nominal``: that CPU time / (window x the requested RAW_IMU rate);
- ``daemon_cpu_ms_per_processed_imu``: the daemon's CPU from its ``started`` log line to the end
  / the IMU samples it processed in that time (its ``stopped`` record): the cost per unit of work,
  which stays meaningful when the daemon is starved of CPU and behind its input (the figures per
  second then only say what share the scheduler gave it); ``daemon_wakeups_per_processed_imu``
  likewise;
- ``daemon_wakeups_per_s``: voluntary context switches per second: how often the loop went to sleep
  (in select) and woke; the loop's own timer cost scales with it;
- ``sim_cpu_pct``: the simulator's share, apart.
``--idle``: no simulator: the daemon waits for an FC that never talks, and what it costs is its
loop alone (timers, periodic work, waking up). On a crowded machine this is the figure that can
be measured: a daemon starved of CPU never sleeps and falls behind its input, and its CPU share
is then the share the scheduler gave it, not what the work needs (``daemon_stopped`` shows how
many IMU samples it processed in the whole run).

What the daemon lost is reported beside it (its ``stopped`` log record: IMU messages seen and
processed, kernel drops, sequence gaps), so a lower CPU that came from dropping input shows. ``--fixed-wait-s 0.005`` runs the daemon with the loop it had before
it blocked until input or a timer (``Daemon.loop_wait_s`` replaced by that constant wait): a
before/after in one tree. One run per call: the machine is shared; run it before and after a
change in the same conditions and compare. ``--imu-batch``: the daemon with the batch path (a
read's RAW_IMU as one ImuBatch, [mavlink] imu_batch on) instead of its default message path, likewise.
``--link-scan python``: the link's frame scan in Python (mavlink_io.frame_scan) instead of the compiled
core's (service/link_core.py), the rest unchanged: an A/B of the scan in one tree.

Scheduling (``--sched unit``, the default): the daemon starts in a session of its own whose CPU
group (kernel autogroup) gets the systemd unit's ``Nice=`` (bench/sitl.py ``unit_nice``: the stand-in
for the unit's cgroup CPUWeight), the simulator (the FC) one of its own at nice -15, as
bench/geofence.py runs them (needs root; ``--sched inherit``: both inherit this process's). The
1-min load is printed beside every figure.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


def _stopped_fields(log_path: Path) -> dict:
    """The fields of the daemon's last ``stopped`` log record (logfmt: key=value ...)."""
    fields: dict = {}
    for line in log_path.read_text(errors="replace").splitlines():
        if "msg=stopped " in line:
            fields = {}
            for tok in shlex.split(line.split("msg=stopped ", 1)[1]):
                k, _, v = tok.partition("=")
                try:
                    fields[k] = int(v)
                except ValueError:
                    fields[k] = v
    return fields


FC_GROUP_NICE = -15
"""The simulator's CPU group nice with --sched unit (bench/geofence.py's FC and wire)."""


def measure(imu_hz: float, window_s: float, warmup_s: float, port: int, fixed_wait_s: float | None = None,
            idle: bool = False, imu_batch: bool = False, sched: str = "unit", link_scan: str = "core") -> dict:
    import psutil

    from bench.sitl import _set_nice, scenario_site, unit_nice, write_config

    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-cpu-"))
    scen = workdir / "inclined_rail_short_rest.toml"
    scen.write_text((ROOT / "sim" / "scenarios" / "inclined_rail.toml").read_text()
                    .replace("rest_s = 60.0", "rest_s = 6.0"))
    overrides = {"mavlink": {"url": f"udpin:127.0.0.1:{port}", "imu_rate_hz": float(imu_hz)},
                 "outputs": {"extra_mavlink_urls": [], "status_interval_s": 0.0},
                 "service": {"state_dir": str(workdir / "state")}, "zenoh": {"enabled": False}}
    for section, keys in scenario_site(str(scen)).items():
        overrides.setdefault(section, {}).update(keys)
    cfg = write_config(workdir / "azimuthd.toml", overrides)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    dlog, slog = open(workdir / "daemon.log", "w"), open(workdir / "sim.log", "w")
    run = ["-m", "service.cli"]
    patches = []
    if fixed_wait_s is not None:  # the old loop: step(constant) whatever the timers say
        patches.append(f"Daemon.loop_wait_s = lambda self: {float(fixed_wait_s)!r}")
    # the batch path or the link's message path (one ImuSample per RAW_IMU), whatever [mavlink] imu_batch says
    patches.append("_init = Daemon.__init__; Daemon.__init__ = lambda self, *a, **k: (_init(self, *a, **k), "
                   f"setattr(self, 'link_cfg', dataclasses.replace(self.link_cfg, imu_batch={bool(imu_batch)!r})))[0]")
    if link_scan == "python":   # the link's frame scan in Python (mavlink_io.frame_scan), the rest as the daemon's
        patches.append("import service.link_core as _lc; _lc.frame_scan = lambda environ=None: None")
    if patches:
        run = ["-c", "import dataclasses, sys; from service.daemon import Daemon; from service.cli import main; "
                     + "; ".join(patches) + "; sys.exit(main(sys.argv[1:]))"]
    own = sched == "unit"
    daemon = subprocess.Popen([sys.executable, *run, "run", "--config", str(cfg)], cwd=ROOT,
                              env=env, stdout=dlog, stderr=subprocess.STDOUT, start_new_session=own,
                              preexec_fn=_set_nice(None, unit_nice()) if own else None)
    t_wait = time.monotonic() + 180.0  # the daemon listens before the simulator pushes (imports take
    while "msg=started " not in (workdir / "daemon.log").read_text(errors="replace"):  # long when busy)
        if daemon.poll() is not None or time.monotonic() > t_wait:
            _stop(daemon)
            raise RuntimeError(f"the daemon did not start; see {workdir}")
        time.sleep(0.2)
    dp = psutil.Process(daemon.pid)
    d_started, c_started = dp.cpu_times(), dp.num_ctx_switches()
    sim_cmd = [sys.executable, "-m", "service.cli", "sim", "--scenario", str(scen), "--mavlink",
               f"udpout:127.0.0.1:{port}", "--speed", "1", "--seed", "1"]
    if idle:  # no FC: a process that only sleeps stands in for the simulator's slot
        sim_cmd = [sys.executable, "-c", "import time; time.sleep(3600)"]
    sim = subprocess.Popen(sim_cmd, cwd=ROOT, env=env, stdout=slog, stderr=subprocess.STDOUT, start_new_session=own,
                           preexec_fn=_set_nice(None, FC_GROUP_NICE) if own else None)
    out = {"imu_hz": imu_hz, "window_s": window_s, "warmup_s": warmup_s, "workdir": str(workdir),
           "loop": "blocking (Daemon.loop_wait_s)" if fixed_wait_s is None else f"fixed wait {fixed_wait_s:g} s",
           "imu_path": "batch (ImuBatch)" if imu_batch else "message (ImuSample)", "link_scan": link_scan,
           "sched": (f"daemon CPU group nice {unit_nice()} (the unit's Nice=), simulator group nice {FC_GROUP_NICE}"
                     if own else "inherited"),
           "azimuthd_core": os.environ.get("AZIMUTHD_CORE", "core"), "idle_no_fc": idle}
    try:
        time.sleep(warmup_s)
        if daemon.poll() is not None or sim.poll() is not None:
            raise RuntimeError(f"a process ended during the warm-up; see {workdir}")
        sp = psutil.Process(sim.pid)
        d0, s0, c0, w0 = dp.cpu_times(), sp.cpu_times(), dp.num_ctx_switches(), time.monotonic()
        time.sleep(window_s)
        d1, s1, c1, w1 = dp.cpu_times(), sp.cpu_times(), dp.num_ctx_switches(), time.monotonic()
        if daemon.poll() is not None:
            raise RuntimeError(f"the daemon ended during the window (exit {daemon.returncode}); see {workdir}")
        _stop(sim)  # the FC goes quiet; the daemon's CPU since it started, then its count at stop
        d_end, c_end = dp.cpu_times(), dp.num_ctx_switches()
    finally:
        _stop(sim)
        _stop(daemon)
        dlog.close()
        slog.close()
    wall = w1 - w0
    d_cpu_s = (d1.user - d0.user) + (d1.system - d0.system)
    out.update(daemon_cpu_pct=100.0 * d_cpu_s / wall,
               daemon_cpu_ms_per_s=1e3 * d_cpu_s / wall,
               daemon_user_pct=100.0 * (d1.user - d0.user) / wall,
               daemon_system_pct=100.0 * (d1.system - d0.system) / wall,
               daemon_cpu_ms_per_imu_nominal=1e3 * d_cpu_s / (wall * imu_hz),
               daemon_wakeups_per_s=(c1.voluntary - c0.voluntary) / wall,
               daemon_involuntary_per_s=(c1.involuntary - c0.involuntary) / wall,
               sim_cpu_pct=100.0 * ((s1.user - s0.user) + (s1.system - s0.system)) / wall,
               load_avg_1min=os.getloadavg()[0])
    out["daemon_stopped"] = stopped = _stopped_fields(workdir / "daemon.log")
    n = stopped.get("imu_samples", 0)
    if n:  # per unit of work, valid even when the daemon was starved and fell behind
        cpu_run_s = (d_end.user - d_started.user) + (d_end.system - d_started.system)
        out["daemon_cpu_ms_per_processed_imu"] = 1e3 * cpu_run_s / n
        out["daemon_wakeups_per_processed_imu"] = (c_end.voluntary - c_started.voluntary) / n
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--imu-hz", type=float, default=50.0)
    ap.add_argument("--window-s", type=float, default=40.0)
    ap.add_argument("--warmup-s", type=float, default=15.0)
    ap.add_argument("--port", type=int, default=47100)
    ap.add_argument("--quick", action="store_true", help="a 20 s window")
    ap.add_argument("--fixed-wait-s", type=float, default=None, help="the old loop: step(this) every time")
    ap.add_argument("--idle", action="store_true", help="no simulator: the loop's own cost")
    ap.add_argument("--imu-batch", action="store_true",
                    help="the daemon with [mavlink] imu_batch on (a read's RAW_IMU as one batch; default off, "
                         "as the daemon's default: one ImuSample per RAW_IMU)")
    ap.add_argument("--sched", choices=("unit", "inherit"), default="unit",
                    help="unit: the daemon's CPU group at the unit's Nice=, the simulator's at -15 (root)")
    ap.add_argument("--link-scan", choices=("core", "python"), default="core",
                    help="the link's frame scan: the compiled core's (the daemon's when built) or mavlink_io's Python")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    window = 20.0 if a.quick else a.window_s
    r = measure(a.imu_hz, window, a.warmup_s, a.port, a.fixed_wait_s, a.idle, a.imu_batch, a.sched, a.link_scan)
    what = "idle, no FC" if r["idle_no_fc"] else f"RAW_IMU {r['imu_hz']:g} Hz"
    print(f"scheduling: {r['sched']}; IMU path: {r['imu_path']}; link frame scan: {r['link_scan']}")
    print(f"daemon ({r['loop']}) {what}, over {r['window_s']:.0f} s (load {r['load_avg_1min']:.1f}): "
          f"{r['daemon_cpu_pct']:.1f} % of a core (user {r['daemon_user_pct']:.1f} + system {r['daemon_system_pct']:.1f}; "
          f"{r['daemon_cpu_ms_per_s']:.0f} ms CPU per s, "
          f"{r['daemon_cpu_ms_per_imu_nominal']:.2f} ms per nominal IMU sample), loop wakeups "
          f"{r['daemon_wakeups_per_s']:.0f} /s; simulator {r['sim_cpu_pct']:.1f} %")
    if "daemon_cpu_ms_per_processed_imu" in r:
        print(f"per processed IMU sample (whole run): {r['daemon_cpu_ms_per_processed_imu']:.2f} ms CPU, "
              f"{r['daemon_wakeups_per_processed_imu']:.2f} wakeups")
    print(f"daemon at stop: {r['daemon_stopped']}")
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
