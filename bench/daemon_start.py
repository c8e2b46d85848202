"""Daemon start to READY=1: wall time and CPU seconds, as systemd (Type=notify) sees it.

    python bench/daemon_start.py [--runs 3] [--json PATH] [--also-import MODULE ...] [--quick]

``azimuthd run`` (the example config, zenoh off, no FC) as its own process with a NOTIFY_SOCKET this
bench listens on, exactly as the unit starts it. Per run:

- ``start_to_ready_s``: wall time from the process's spawn to the READY=1 datagram (issue 19:
  <= 2 s); on a shared machine this is mostly the scheduler's, so the load is printed beside it;
- ``cpu_to_ready_s``: the daemon's own CPU (user + system) read when READY=1 arrives: the work the
  start needs, whatever the load (the process idles in select after READY, ~3 ms CPU per s);
- ``import_daemon_cpu_s``: ``import service.daemon`` alone in a fresh interpreter (process CPU).

Bytecode: an installed daemon starts from compiled bytecode (pip compiles it at install time; the
unit's ProtectSystem=strict forbids writing it later). This machine's environment sets
PYTHONDONTWRITEBYTECODE=1, so a daemon started from the tree compiles every project module at every
start (~1 s of CPU). The headline runs therefore use a private bytecode cache
(PYTHONPYCACHEPREFIX in the work directory, filled by one discarded warm-up start); the
``*_from_source`` figures are the same starts with the environment as it is.

``--also-import filterpy.kalman`` imports a module before the daemon starts: the start as it was
while KF1/KF2 imported filterpy (and through it scipy.stats), for a before/after in one tree.
The medians are the figures; every run is in the JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
HANG_S = 300.0   # a hang detector for a crowded machine, not a bound on the figure


def _daemon_cmd(cfg: Path, also_import: list[str]) -> list[str]:
    if not also_import:
        return [sys.executable, "-m", "service.cli", "run", "--config", str(cfg)]
    pre = "; ".join(f"import {m}" for m in also_import)
    return [sys.executable, "-c", f"import sys; {pre}; from service.cli import main; sys.exit(main(sys.argv[1:]))",
            "run", "--config", str(cfg)]


def _env(workdir: Path, bytecode: bool) -> dict:
    env = dict(os.environ)
    if bytecode:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(workdir / "pycache")
    return env


def one_start(workdir: Path, port: int, also_import: list[str], bytecode: bool) -> dict:
    import psutil

    from bench.sitl import write_config

    cfg = write_config(workdir / "azimuthd.toml", {
        "mavlink": {"url": f"udpin:127.0.0.1:{port}"}, "outputs": {"extra_mavlink_urls": []},
        "site": {"lat_deg": 47.0, "lon_deg": 8.0},
        "service": {"state_dir": str(workdir / "state")}, "zenoh": {"enabled": False}})
    sock_path = workdir / "notify.sock"
    sock_path.unlink(missing_ok=True)
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(sock_path))
        env = dict(_env(workdir, bytecode), NOTIFY_SOCKET=str(sock_path))
        with open(workdir / "daemon.log", "w") as out:
            t0 = time.monotonic()
            proc = subprocess.Popen(_daemon_cmd(cfg, also_import), cwd=ROOT, env=env,
                                    stdout=out, stderr=subprocess.STDOUT)
        try:
            p = psutil.Process(proc.pid)
            sock.settimeout(0.2)
            t_hang = t0 + HANG_S
            while True:
                try:
                    if "READY=1" in sock.recv(4096).decode():
                        break
                except TimeoutError:
                    if proc.poll() is not None or time.monotonic() > t_hang:
                        raise RuntimeError(f"the daemon did not start; see {workdir / 'daemon.log'}") from None
            t_ready = time.monotonic()
            cpu = p.cpu_times()
        finally:
            proc.terminate()
            try:
                proc.wait(30.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5.0)
    return {"start_to_ready_s": t_ready - t0, "cpu_to_ready_s": cpu.user + cpu.system,
            "load_avg_1min": os.getloadavg()[0]}


def import_cpu_s(workdir: Path, bytecode: bool, also_import: list[str] = ()) -> float:
    pre = "".join(f"import {m}; " for m in also_import)
    code = f"import time; {pre}import service.daemon; print(time.process_time())"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True,
                         env=_env(workdir, bytecode))
    return float(out.stdout.strip().splitlines()[-1])


def measure(runs: int, port: int, also_import: list[str]) -> dict:
    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-start-"))
    out = {"also_import": also_import, "azimuthd_core": os.environ.get("AZIMUTHD_CORE", "core")}
    one_start(workdir, port, also_import, bytecode=True)   # warm-up: writes the bytecode cache
    for bytecode, tail in ((True, ""), (False, "_from_source")):
        starts = [one_start(workdir, port, also_import, bytecode) for _ in range(runs)]
        imports = [import_cpu_s(workdir, bytecode, also_import) for _ in range(runs)]
        out.update({f"runs{tail}": starts,
                    f"start_to_ready{tail}_s": statistics.median(r["start_to_ready_s"] for r in starts),
                    f"cpu_to_ready{tail}_s": statistics.median(r["cpu_to_ready_s"] for r in starts),
                    f"import_daemon_cpu{tail}_s": statistics.median(imports),
                    f"import_daemon_cpu_runs{tail}_s": imports})
    out["load_avg_1min"] = os.getloadavg()[0]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--port", type=int, default=14950)
    ap.add_argument("--also-import", action="append", default=[], metavar="MODULE")
    ap.add_argument("--quick", action="store_true", help="one run")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    r = measure(1 if a.quick else a.runs, a.port, a.also_import)
    extra = f", with {', '.join(a.also_import)} imported first" if a.also_import else ""
    for tail, what in (("", "bytecode compiled"), ("_from_source", "from source")):
        runs = ", ".join(f"{x['start_to_ready_s']:.2f} s / {x['cpu_to_ready_s']:.2f} s CPU "
                         f"(load {x['load_avg_1min']:.1f})" for x in r[f"runs{tail}"])
        print(f"daemon start to READY=1 ({what}{extra}): median {r[f'start_to_ready{tail}_s']:.2f} s wall, "
              f"{r[f'cpu_to_ready{tail}_s']:.2f} s CPU; import service.daemon alone "
              f"{r[f'import_daemon_cpu{tail}_s']:.2f} s CPU; runs: {runs}")
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
