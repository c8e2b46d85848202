"""Does any estimator of ArduPilot fuse our ODOMETRY placeholder position? ArduPlane SITL, on the ground.

    python bench/ardupilot_placeholder.py [--json PATH] [-I N] [--speedup X] [--cut-s S] [--end-s S]

ArduPilot hands every ODOMETRY that AP_VisualOdom consumes (VISO_TYPE 1) to EKF2 and EKF3
(docs/OUTPUTS.md 1.5). Four short runs of ArduPlane SITL (../shared/tools/ardupilot-sitl, fresh
eeprom each), each with a ground station on SERIAL0 that records the FC's STATUSTEXT and what
ArduPilot forwards from our component 191, and cuts GNSS (SIM_GPS1_ENABLE 0) at ``--cut-s`` of FC time:

* ``hazard``        EKF2 as shipped (EK2_ENABLE 1), VISO_TYPE 1, EK3_SRC1_YAW 1; this script sends
                    ODOMETRY at 10 Hz encoded exactly as the daemon's ardupilot profile (placeholder
                    0, 0, 0, 1e6 m^2), its yaw copied from the FC's own ATTITUDE (a plausible value;
                    the question is the position);
* ``fix``           the same with EK2_ENABLE 0, AHRS_EKF_TYPE 3;
* ``daemon_stock``  the daemon (azimuthd run, example config, site and URL set) against EKF2 as
                    shipped, VISO_TYPE 1, EK3_SRC1_YAW 6: it must send no ODOMETRY;
* ``daemon_fixed``  the daemon against EK2_ENABLE 0, VISO_TYPE 1, EK3_SRC1_YAW 1 (compass: the daemon
                    has a heading to send on the ground from the trusted FC).

"Fused" is the FC's own word: STATUSTEXT "EKFn IMUm is using external nav data". SIM_MAG_RND 3 gives
SITL's compass some noise (a noiseless one is rejected as frozen by the daemon's input checks).
Prints a table and writes JSON (default bench/results/ardupilot_placeholder.json).
"""
from __future__ import annotations

import argparse
import ast
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pymavlink import mavutil  # noqa: E402

SITL_DIR = Path(os.environ.get("AZIMUTHD_ARDUPILOT_SITL", ROOT.parent / "shared" / "tools" / "ardupilot-sitl"))
HOME = (-35.363261, 149.165230, 584.0)
EXTNAV = re.compile(r"^(EKF[23]) IMU\d+ is using external nav data")
RUNS = {
    "hazard": ("script", {"VISO_TYPE": 1, "EK3_SRC1_YAW": 1}),
    "fix": ("script", {"VISO_TYPE": 1, "EK3_SRC1_YAW": 1, "EK2_ENABLE": 0, "AHRS_EKF_TYPE": 3}),
    "daemon_stock": ("daemon", {"VISO_TYPE": 1, "EK3_SRC1_YAW": 6}),
    "daemon_fixed": ("daemon", {"VISO_TYPE": 1, "EK3_SRC1_YAW": 1, "EK2_ENABLE": 0, "AHRS_EKF_TYPE": 3}),
}
COMMON = {"ARMING_CHECK": 0, "SIM_MAG_RND": 3}


class Sitl:
    def __init__(self, rundir: Path, inst: int, speedup: float, params: dict):
        self.rundir = rundir
        parm = rundir / "bench.parm"
        rundir.mkdir(parents=True, exist_ok=True)
        parm.write_text("".join(f"{k} {v}\n" for k, v in {**COMMON, **params}.items()))
        subprocess.run([str(SITL_DIR / "start.sh"), str(rundir), "-I", str(inst), "--speedup", str(speedup),
                        "--wipe", "--defaults", str(parm)], check=True, stdout=subprocess.DEVNULL)

    def stop(self) -> None:
        try:
            pid = int((self.rundir / "sitl.pid").read_text())
            os.killpg(pid, 15)
        except (OSError, ValueError):
            pass


def ground_station(port: int, cut_s: float, end_s: float, rec: dict) -> None:
    """SERIAL0: STATUSTEXT, component 191's forwarded messages, the GNSS cut at cut_s FC time."""
    m = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190,
                                   dialect="ardupilotmega")
    m.wait_heartbeat(timeout=60)
    m.mav.command_long_send(1, 1, 511, 0, 30, 1e6 / 5, 0, 0, 0, 0, 0)  # ATTITUDE: the FC clock
    t_fc, cut = 0.0, False
    while t_fc < end_s:
        x = m.recv_match(blocking=True, timeout=1.0)
        if x is None:
            continue
        if x.get_srcComponent() == 191:
            rec["forwarded"][x.get_type()] = rec["forwarded"].get(x.get_type(), 0) + 1
            continue
        if hasattr(x, "time_boot_ms"):
            t_fc = x.time_boot_ms / 1e3
        if x.get_type() == "STATUSTEXT":
            rec["statustext"].append((round(t_fc, 1), x.text))
        if not cut and t_fc >= cut_s:
            cut = True
            m.mav.param_set_send(1, 1, b"SIM_GPS1_ENABLE", 0, 2)
            rec["statustext"].append((round(t_fc, 1), "## GNSS cut (SIM_GPS1_ENABLE 0)"))
    m.close()


def odometry_sender(port: int, end_s: float, rec: dict) -> None:
    """SERIAL1 as component 191: ODOMETRY at 10 Hz in the daemon's ardupilot encoding."""
    import numpy as np
    from estimators.rotations import quat_from_euler
    from mavlink_io import outputs
    from mavlink_io.navsolution import NavSolution
    m = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=1, source_component=191,
                                   dialect="ardupilotmega")
    m.wait_heartbeat(timeout=60)
    m.mav.command_long_send(1, 1, 511, 0, 30, 1e6 / 20, 0, 0, 0, 0, 0)
    prof, last, t_fc = outputs.ODOMETRY_PROFILES["ardupilot"], -1.0, 0.0
    while t_fc < end_s:
        x = m.recv_match(type="ATTITUDE", blocking=True, timeout=1.0)
        if x is None:
            continue
        t_fc = x.time_boot_ms / 1e3
        if t_fc - last >= 0.1:
            last = t_fc
            sol = NavSolution(t_fc, time.monotonic(), "in-flight", quat_from_euler(x.roll, x.pitch, x.yaw), x.roll,
                              x.pitch, np.zeros(3), math.radians(0.5), math.radians(0.5), x.yaw % (2 * math.pi),
                              math.radians(2.0), "fc", True)
            m.mav.send(outputs.encode_odometry(sol, prof, 0))
            rec["odometry_sent"] += 1
    m.close()


def run_daemon(port: int, rundir: Path, wall_s: float, rec: dict) -> None:
    cfg = rundir / "azimuthd.toml"
    cfg.write_text(f'[site]\nlat_deg = {HOME[0]}\nlon_deg = {HOME[1]}\nalt_m = {HOME[2]}\n'
                   f'[mavlink]\nurl = "tcp:127.0.0.1:{port}"\n[zenoh]\nenabled = false\n'
                   f'[service]\nstate_dir = "{rundir / "state"}"\n')
    with open(rundir / "daemon.log", "w") as log:
        p = subprocess.Popen([sys.executable, "-m", "service.cli", "run", "--config", str(cfg)], cwd=ROOT,
                             stdout=log, stderr=subprocess.STDOUT)
        try:
            p.wait(timeout=wall_s)
        except subprocess.TimeoutExpired:
            p.terminate()
            p.wait(timeout=30)
    text = (rundir / "daemon.log").read_text()
    m = re.search(r"sent=\"(\{[^\"]*\})\"", text)
    sent = ast.literal_eval(m.group(1)) if m else {}  # the daemon's own {'ODOMETRY': n, ...} from its stop line
    rec["odometry_sent"] = int(sent.get("ODOMETRY", 0))
    rec["daemon_lines"] = [ln.split("msg=", 1)[1][:220] for ln in text.splitlines()
                           if "event=fc_yaw_feed" in ln or "event=fc_yaw_loop" in ln or "event=placeholder_fused" in ln]


def one(name: str, inst: int, speedup: float, cut_s: float, end_s: float, base: Path) -> dict:
    kind, params = RUNS[name]
    rundir = base / name
    rec = {"params": params, "statustext": [], "forwarded": {}, "odometry_sent": 0}
    sitl = Sitl(rundir, inst, speedup, params)
    try:
        gcs = threading.Thread(target=ground_station, args=(5760 + 10 * inst, cut_s, end_s, rec), daemon=True)
        gcs.start()
        time.sleep(3.0)
        if kind == "script":
            odometry_sender(5762 + 10 * inst, end_s, rec)
        else:
            run_daemon(5762 + 10 * inst, rundir, end_s / speedup + 10.0, rec)
        gcs.join(timeout=end_s / speedup + 30.0)
    finally:
        sitl.stop()
    hits = [(t, s) for t, s in rec["statustext"] if EXTNAV.match(s)]
    rec["ekf2_fused_placeholder"] = any(s.startswith("EKF2") for _, s in hits)
    rec["ekf3_used_extnav"] = any(s.startswith("EKF3") for _, s in hits)
    rec["extnav_lines"] = hits
    rec["first_extnav_fc_s"] = hits[0][0] if hits else None
    rec["odometry_forwarded_count"] = rec["forwarded"].get("ODOMETRY", 0)
    rec["odometry_sent_count"] = rec.pop("odometry_sent")
    return rec


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-I", "--instance", type=int, default=2)
    ap.add_argument("--speedup", type=float, default=3.0)
    ap.add_argument("--cut-s", type=float, default=60.0, help="GNSS cut, FC time s")
    ap.add_argument("--end-s", type=float, default=120.0, help="end of each run, FC time s")
    ap.add_argument("--runs", default=",".join(RUNS), help="comma-separated subset of " + ", ".join(RUNS))
    ap.add_argument("--keep", type=Path, default=None, help="keep the run directories (logs) under this directory")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "ardupilot_placeholder.json")
    a = ap.parse_args()
    if not (SITL_DIR / "arduplane").exists():
        print(f"ArduPlane SITL not found in {SITL_DIR} (set AZIMUTHD_ARDUPILOT_SITL)")
        return 2
    out = {"cut_fc_s": a.cut_s, "end_fc_s": a.end_s, "speedup": a.speedup, "runs": {}}
    with tempfile.TemporaryDirectory(prefix="azimuthd-placeholder-") as tmp:
        base = a.keep if a.keep is not None else Path(tmp)
        for name in a.runs.split(","):
            r = one(name, a.instance, a.speedup, a.cut_s, a.end_s, base)
            out["runs"][name] = r
            print(f"{name:13s} ODOMETRY sent {r['odometry_sent_count']:4d} (forwarded to the GCS "
                  f"{r['odometry_forwarded_count']:4d})  EKF2 used it: {r['ekf2_fused_placeholder']!s:5s}  "
                  f"EKF3 used it: {r['ekf3_used_extnav']!s:5s}  first at FC {r['first_extnav_fc_s']} s")
            for ln in r.get("daemon_lines", []):
                print(f"{'':13s} daemon: {ln}")
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(out, indent=1))
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
