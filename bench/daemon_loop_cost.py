"""CPU of the daemon's own loop per RAW_IMU at 400 Hz, in this process, without the scheduler's noise.

    python bench/daemon_loop_cost.py [--flight-s 30] [--repeat 2] [--json PATH] [--split]
                                     [--link-scan core|python|ab]

The bundled simulator (inclined_rail, ArduPilot personality, rest shortened to 6 s) is run in memory
as fast as it computes, with the streams the daemon asks for at 400 Hz (RAW_IMU 400, SCALED_PRESSURE
and ATTITUDE 50, SYS_STATUS, EKF_STATUS_REPORT, EXTENDED_SYS_STATE 2, and its HEARTBEAT, SIMSTATE);
every frame is one datagram, as the simulator sends them (recorded first: the simulator does not
answer the daemon's requests here, which then retries them as a silent FC makes it). A Daemon (the default config: message path,
A's re-solves in the worker process, one extra MAVLink output) reads them from an in-memory
transport on a clock that follows the datagrams, one ``Daemon.step`` per datagram as its loop wakes
for each. Figures, in flight (from launch + 4 s to the end):

- ``us_per_imu``: the process CPU of the steps / RAW_IMU (best of ``--repeat``; A's worker apart);
- ``empty_wakeup_us``: one step with nothing to read (the loop's fixed cost per wake-up);
- call counts per RAW_IMU, which do not depend on the load: pymavlink parses (``MAVLink.parse_char``),
  NavSolutions built from propagated snapshots, ``OutputScheduler._fillable``, ``Pipeline.on_imu``.

``--split``: one more run with the parts of a step timed (thread CPU time around the outermost call of
each, in flight): ``split_us_per_imu`` per part, per RAW_IMU: where the loop's time goes (the link's
receive and decode, its timers, the Pipeline, the output slots and their sends, the daemon's periodic
work). A part's time includes the parts called inside it (Daemon._dispatch holds Pipeline.step_imu and
most of Daemon._publish_due); the timing adds ~1 us per wrapped call (a clock_gettime each side).

What it leaves out: the socket, select() and waking up (bench/speed.py measures the daemon as a
process). The 1-min load is printed beside every figure.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "bench")]
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

RATES_HZ = {27: 400.0, 29: 50.0, 30: 50.0, 1: 2.0, 193: 2.0, 245: 2.0}
"""RAW_IMU, SCALED_PRESSURE, ATTITUDE, SYS_STATUS, EKF_STATUS_REPORT, EXTENDED_SYS_STATE."""
REST_S = 6.0


class _Wire:
    """The simulator's connection: what it writes, with its time."""

    def __init__(self, sysid: int, compid: int):
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2
        self.frames: list[tuple[float, bytes]] = []
        self.t = 0.0
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)

    def write(self, buf):
        self.frames.append((self.t, bytes(buf)))


def record(flight_s: float) -> list[tuple[float, bytes]]:
    """(time s, datagram) of the simulator's frames over REST_S + flight_s."""
    from sim.autopilot import Autopilot
    ap = Autopilot("inclined_rail", "udpout:127.0.0.1:9", personality="ardupilot", seed=1,
                   overrides={"launcher": {"rest_s": REST_S}})
    wire = ap.conn = _Wire(ap.sysid, ap.compid)
    for mid, hz in RATES_HZ.items():
        ap.set_interval(mid, 1e6 / hz)
    while ap.t < REST_S + flight_s:
        ap.t = wire.t = min(s.next_s for s in ap.streams.values())
        for mid, st in list(ap.streams.items()):
            if st.next_s <= ap.t + 1e-9 and ap.streams.get(mid) is st:
                ap._send(ap._build(mid, st))
                st.next_s += st.interval_s
    return wire.frames


SPLIT_PARTS = (
    ("service.daemon", "Daemon", "step"),
    ("mavlink_io.link", "MavlinkLink", "poll"),
    ("mavlink_io.session", "Session", "read"),
    ("mavlink_io.framing", "FrameParser", "parse_chunk"),
    ("mavlink_io.link", "MavlinkLink", "_handle_imu_frame"),
    ("mavlink_io.link", "MavlinkLink", "_handle"),
    ("mavlink_io.link", "MavlinkLink", "_service_timers"),
    ("mavlink_io.link", "MavlinkLink", "_next_due_s"),
    ("service.daemon", "Daemon", "_dispatch"),
    ("service.pipeline", "Pipeline", "step_imu"),
    ("service.daemon", "Daemon", "_publish_due"),
    ("service.daemon", "Daemon", "_send"),
    ("service.daemon", "Daemon", "_periodic"),
    ("service.daemon", "Daemon", "loop_wait_s"),
)
"""(module, class, method) timed by --split."""


class _Split:
    """Thread CPU time around the outermost call of each SPLIT_PARTS method while ``on``."""

    def __init__(self):
        import importlib
        self.on, self.acc, self._saved = False, {}, []
        for mod, cls_name, meth in SPLIT_PARTS:
            cls = getattr(importlib.import_module(mod), cls_name)
            self._saved.append((cls, meth, cls.__dict__[meth]))
            setattr(cls, meth, self._wrap(f"{cls_name}.{meth}", cls.__dict__[meth]))

    def _wrap(self, key, f):
        acc, depth, pc = self.acc, [0], time.thread_time   # CPU time: the wall clock counts the waits for a core
        acc[key] = [0.0, 0]

        def timed(*a, **k):
            if depth[0] or not self.on:
                return f(*a, **k)
            depth[0] += 1
            t = pc()
            try:
                return f(*a, **k)
            finally:
                depth[0] -= 1
                r = acc[key]
                r[0] += pc() - t
                r[1] += 1
        return timed

    def restore(self) -> None:
        for cls, meth, f in self._saved:
            setattr(cls, meth, f)


class _Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


def run(frames, t0_s: float, counting: bool = False, split: bool = False, link_scan: str = "core") -> dict:
    """One daemon over the frames; CPU and wake-ups counted from t0_s on. ``link_scan``: "core" (the
    daemon's: the compiled frame scan, service/link_core.py, when built) or "python" (mavlink_io.frame_scan)."""
    import socket

    from pymavlink import mavutil

    from mavlink_io.link import MavlinkLink
    from mem_transport import MemTransport
    from service.config import validate
    from service import link_core
    from service.daemon import Daemon
    from sitl import scenario_site
    work = Path(tempfile.mkdtemp(prefix="azimuthd-loop-cost-"))
    over = {k: dict(v) for k, v in scenario_site("inclined_rail").items()}
    over.update({"zenoh": {"enabled": False}, "service": {"state_dir": str(work)},
                 "mavlink": {"imu_rate_hz": 400.0}, "outputs": {"status_interval_s": 0.0}})
    clock = _Clock()
    d = Daemon(validate(over), clock=clock)
    tr = MemTransport(datagram=True)
    d.link = MavlinkLink(d.link_cfg, clock=clock, transport=tr,
                         frame_scan=link_core.frame_scan() if link_scan == "core" else None)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)   # the ground station's port (never read)
    sink.bind(("127.0.0.1", 0))
    d.extra_ports.append(mavutil.mavlink_connection(f"udpout:127.0.0.1:{sink.getsockname()[1]}", source_system=1,
                                                    source_component=d.link_cfg.component_id, dialect="ardupilotmega"))
    counts = {}
    timer = _Split() if split else None
    if counting:
        import cProfile
        prof = cProfile.Profile()
    cpu, n_imu, n_dg = 0.0, 0, 0
    for t, f in frames:
        clock.t = 1000.0 + t
        tr.inbox.append(f)
        inside = t >= t0_s
        if inside:
            if timer is not None:
                timer.on = True
            if counting:
                prof.enable()
            c0 = time.process_time()
        d.step(d.loop_wait_s())
        if inside:
            cpu += time.process_time() - c0
            if counting:
                prof.disable()
            n_dg += 1
            n_imu += f[7] == 27 and f[8] == 0 and f[9] == 0
    if timer is not None:
        timer.on = False
        timer.restore()
    empty = None
    if not counting and not split:
        best = float("inf")
        for _ in range(3):
            c0 = time.process_time()
            for _k in range(2000):
                clock.t += 1e-4
                d.step(d.loop_wait_s())
            best = min(best, (time.process_time() - c0) / 2000)
        empty = best
    sent = dict(d.sent)
    d.close()
    sink.close()
    if counting:
        import pstats
        calls: dict[str, int] = {}
        for (file, _line, name), (_cc, nc, *_rest) in pstats.Stats(prof).stats.items():
            calls[f"{Path(file).name}:{name}"] = calls.get(f"{Path(file).name}:{name}", 0) + nc
        counts = {k: calls.get(k, 0) / n_imu for k in (
            "ardupilotmega.py:parse_char", "pipeline.py:solution_from_snapshot", "outputs.py:_fillable",
            "pipeline.py:on_imu", "daemon.py:step")}
    if timer is not None:
        counts = {k: {"us_per_imu": 1e6 * v[0] / n_imu, "calls_per_imu": v[1] / n_imu} for k, v in timer.acc.items()}
    return {"us_per_imu": 1e6 * cpu / n_imu, "imu": n_imu, "datagrams": n_dg, "sent": sent,
            "empty_wakeup_us": None if empty is None else 1e6 * empty, "calls_per_imu": counts,
            "load_avg_1min": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--flight-s", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "daemon_loop_cost.json"))
    ap.add_argument("--split", action="store_true", help="one more run with the parts of a step timed")
    ap.add_argument("--link-scan", choices=("core", "python", "ab"), default="core",
                    help="the link's frame scan: the compiled core's (the daemon's), mavlink_io's Python, or both "
                         "interleaved (ab: --repeat runs of each, alternating)")
    a = ap.parse_args(argv)
    if not a.flight_s > 5.0 or a.repeat < 1:
        ap.error("--flight-s must be > 5 and --repeat >= 1")
    import logging
    logging.getLogger("azimuthd").setLevel(logging.ERROR)   # the simulator here never answers the rate requests
    frames = record(a.flight_s)
    t0 = REST_S + 4.0
    if a.link_scan == "ab":
        ab = {"core": [], "python": []}
        for _ in range(a.repeat):
            for scan in ("python", "core"):
                ab[scan].append(run(frames, t0, link_scan=scan))
        for scan, rs in ab.items():
            print(f"link scan {scan:6s}: " + ", ".join(f"{r['us_per_imu']:.1f}" for r in rs) + " us CPU per RAW_IMU "
                  f"(best {min(r['us_per_imu'] for r in rs):.1f}; loads "
                  + ", ".join(f"{r['load_avg_1min']:.1f}" for r in rs) + ")")
        runs = ab["core"]
    else:
        runs = [run(frames, t0, link_scan=a.link_scan) for _ in range(a.repeat)]
    best = min(runs, key=lambda r: r["us_per_imu"])
    counted = run(frames, t0, counting=True)
    for r in runs:
        print(f"daemon loop: {r['us_per_imu']:.1f} us CPU per RAW_IMU in flight ({r['imu']} RAW_IMU, {r['datagrams']} "
              f"datagrams), empty wake-up {r['empty_wakeup_us']:.1f} us (load {r['load_avg_1min']:.1f}); sent {r['sent']}")
    print("calls per RAW_IMU: " + ", ".join(f"{k} {v:.3f}" for k, v in counted["calls_per_imu"].items()))
    out = {"best": best, "runs": runs, "link_scan": a.link_scan, "calls_per_imu": counted["calls_per_imu"], "flight_s": a.flight_s,
           "rates_hz": {str(k): v for k, v in RATES_HZ.items()}}
    if a.split:
        parts = run(frames, t0, split=True, link_scan="python" if a.link_scan == "python" else "core")
        out["split_us_per_imu"] = {k: v["us_per_imu"] for k, v in parts["calls_per_imu"].items()}
        print(f"split (us per RAW_IMU in flight, calls per RAW_IMU; load {parts['load_avg_1min']:.1f}; "
              f"the whole loop {parts['us_per_imu']:.1f} us with the timing):")
        for k, v in parts["calls_per_imu"].items():
            print(f"  {k:32s} {v['us_per_imu']:8.1f} us  {v['calls_per_imu']:6.3f} calls")
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(out, indent=2) + "\n")
    print(f"json: {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
