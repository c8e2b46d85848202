"""Real flight logs through `azimuthd replay`, as a user runs it, scored against the log's own FC.

    python bench/real_logs.py [--quick] [--json PATH] [--site-for NAME=LAT,LON ...] [FOLDER_OR_LOG ...]

Every .tlog / .bin / .ulg under ../shared/data (and every folder or log given) is replayed by the
real command line (`azimuthd replay LOG --output CSV --json J`, a subprocess: a traceback is a
failure, counted), twice:

- ``fc_allowed``: the daemon's defaults (the FC's yaw is a heading source while it is trusted);
- ``fc_excluded``: `--exclude-fc-yaw` (the FC's yaw is no source and no reference: our own heading).

Per log and mode: replay OK or the one-line reason; wall time vs flight time; the coverage of a
valid heading (share of output rows with one); roll / pitch / heading RMS against the log's own
attitude (the FC's GNSS-aided estimate where it had GNSS: a reference, not truth); the share of
rows whose heading error is within 2 published sigmas; whether method A produced a solution;
whether the magnetometer was usable (the replay names a rejection). Per log: the detected take-off
(our phases: the first ``launch``; none when they found the run started in flight, whose time is
``started_in_flight_s``) against the log's own take-off (the FC's landed -> in-air
transition from the reader's ``takeoff_times_s()`` where the log has a land detector or arming
records), the error in seconds.

A log without a GNSS position needs a site to replay at all: ``--site-for NAME=LAT,LON``
(defaults below for the shared logs, labelled "assumed" in the output). Its heading comparison
then carries the declination error of the assumed site, and its FC heading is no GNSS-aided
reference (the FC's own magnetometer heading), so the heading targets (RMS and the share within 2
sigma) apply only to logs with a GNSS position and a usable magnetometer; the others' figures are
printed as diagnostics. Each log replays with the ``[launch] vehicle`` its operator would configure
(``OPERATOR_VEHICLE``, ``--vehicle-for``).

JSON (bench/results/real_logs.json): ``replay_failures`` (logs that did not replay in either mode,
tracebacks included), ``tracebacks``, and per log ``logs.<file>.<mode>.*`` with unit-suffixed keys,
``logs.<file>.takeoff_error_s``, ``logs.<file>.magnetometer_usable``, ``logs.<file>.azimuth_solved``.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
LOG_SUFFIXES = (".tlog", ".bin", ".ulg")
MODES = {"fc_allowed": [], "fc_excluded": ["--exclude-fc-yaw"]}

# Logs of ../shared/data with no GNSS position: a site an operator would configure. Their README
# says where they flew is unknown; these are labelled as assumed in every output.
ASSUMED_SITES = {
    "px4-bench-sample.ulg": "47.397,8.546",      # PX4's default SITL home (Zurich): a bench log, no fix
    "px4-quad-no-gnss.ulg": "47.397,8.546",      # no fix at any time; location unknown
}
# How each shared log's vehicle takes off: what its operator would configure ([launch] vehicle and
# case; the logs' READMEs say what flew). Named as configuration in the output; never derived from
# anything the bench scores against.
OPERATOR_VEHICLE = {
    "arducopter-flight.tlog": "multicopter",
    "arducopter-rtl-midflight.bin": "multicopter",
    "px4-bench-sample.ulg": "multicopter",       # a flight controller moved by hand on a bench
    "px4-quad-no-gnss.ulg": "multicopter",
    "px4-vtol-airspeed-small.ulg": "vtol",
}
HEADING_TARGET_RMS_DEG = 3.0
WITHIN_2SIGMA_TARGET = 0.90
TAKEOFF_TARGET_S = 2.0


def find_logs(paths: list[pathlib.Path]) -> list[pathlib.Path]:
    out: list[pathlib.Path] = []
    for p in paths:
        if p.is_dir():
            out += sorted(q for q in p.rglob("*") if q.suffix.lower() in LOG_SUFFIXES and q.is_file())
        elif p.is_file():
            out.append(p)
    seen, uniq = set(), []
    for p in out:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            uniq.append(p)
    return uniq


def _f(v: str) -> float:
    try:
        return float(v) if v != "" else math.nan
    except ValueError:
        return math.nan


def _rms(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan


def read_csv(path: pathlib.Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    cols: dict[str, np.ndarray] = {}
    if not rows:
        return cols
    for k in rows[0]:
        if k in ("phase", "heading_source"):
            cols[k] = np.array([r[k] for r in rows], dtype=object)
        else:
            cols[k] = np.array([_f(r[k]) for r in rows])
    return cols


def score_rows(c: dict[str, np.ndarray]) -> dict:
    """Figures of one replay's CSV against the log's own FC attitude (the ref_ columns)."""
    if not c:
        return {"rows": 0}
    n = len(c["time_s"])
    hdg, sig, ref_h = c["heading_deg"], c["heading_sigma_deg"], c["ref_heading_deg"]
    err_h = (hdg - ref_h + 180.0) % 360.0 - 180.0
    valid = np.isfinite(hdg)
    both = valid & np.isfinite(ref_h)
    src = c["heading_source"]
    uses_fc = np.array(["fc" in str(s).split("+") for s in src], dtype=bool)
    own = both & ~uses_fc
    within = np.abs(err_h[both]) <= 2.0 * sig[both]
    out = {
        "rows": int(n),
        "heading_coverage_fraction": float(np.mean(valid)) if n else math.nan,
        "roll_rms_deg": _rms(c["roll_deg"] - c["ref_roll_deg"]),
        "pitch_rms_deg": _rms(c["pitch_deg"] - c["ref_pitch_deg"]),
        "heading_rms_deg": _rms(err_h[both]),
        "heading_rms_own_deg": _rms(err_h[own]),
        "heading_compared_rows": int(np.sum(both)),
        "heading_rows_using_fc_yaw": int(np.sum(both & uses_fc)),
        "within_2sigma_fraction": float(np.mean(within)) if within.size else math.nan,
        "heading_sigma_median_deg": float(np.median(sig[both])) if np.any(both) else math.nan,
        "azimuth_solved": bool(np.any(np.isfinite(c["azimuth_deg"]))),
    }
    # our take-off: the first output row in flight (launch or in-flight) after a pre-launch row, the
    # time the daemon acted on it (a launch phase shorter than a filter step has no row of its own);
    # a run that starts in flight (no pre-launch row before) detected no take-off
    t, ph = c["time_s"], list(c["phase"])
    out["detected_takeoff_s"] = None
    for k in range(1, len(ph)):
        if ph[k] in ("launch", "in-flight") and ph[k - 1] == "pre-launch":
            out["detected_takeoff_s"] = float(t[k])
            break
    return out


def log_takeoffs(path: pathlib.Path) -> tuple[list[float] | None, str]:
    """The log's own take-off times (FC time, s) and where they come from: the reader's land
    detector / arming records. For scoring only: nothing here reaches the replay."""
    try:
        from service.logreaders import open_log
        reader = open_log(str(path))
    except Exception as exc:  # noqa: BLE001 - a reader failure is the replay's to report
        return None, f"reader: {exc}"
    fn = getattr(reader, "takeoff_times_s", None)
    if fn is None:
        return None, "the reader gives no take-off reference"
    try:
        times = fn()
    except Exception as exc:  # noqa: BLE001
        return None, f"take-off reference failed: {exc}"
    if times is None:
        return None, "the log has no landed/flying state"
    return [float(x) for x in times], "the log's landed/flying state"


def mag_verdict(stdout: str, summary: dict) -> tuple[bool | None, str]:
    """Usable magnetometer or the replay's named rejection (its summary JSON, else its text)."""
    mag = summary.get("magnetometer") if isinstance(summary, dict) else None
    if isinstance(mag, dict) and "usable" in mag:  # the replay's timeline: its state at the end of the log
        spans = (f"usable {mag['usable_s']:.1f} s, rejected {mag['rejected_s']:.1f} s "
                 f"({mag['rejections']}x), {'usable' if mag['usable_at_end'] else 'rejected'} at the end")
        if mag["usable"]:
            return True, f"{spans}; first rejection: {mag['reason']}" if mag.get("rejections") else ""
        return False, f"{mag['reason']}; {spans}"
    for m in summary.get("missing_streams", []) if isinstance(summary, dict) else []:
        if m.startswith("magnetometer"):
            return False, m
    for line in stdout.splitlines():
        low = line.lower()
        if "magnetometer" in low and ("rejected" in low or "unusable" in low or "not usable" in low):
            return False, line.strip()
    return True, ""


def replay(log: pathlib.Path, mode_args: list[str], site: str | None, tmp: pathlib.Path,
           timeout_s: float, vehicle: str | None = None) -> dict:
    csv_path, json_path = tmp / f"{log.stem}.csv", tmp / f"{log.stem}.json"
    for p in (csv_path, json_path):
        p.unlink(missing_ok=True)
    cfg_args: list[str] = []
    if vehicle is not None:  # the operator's [launch] section, nothing else (the site stays the log's)
        cfg = tmp / f"{log.stem}.toml"
        cfg.write_text(f'[launch]\nvehicle = "{vehicle}"\ncase = "aligned"\n')
        cfg_args = ["--config", str(cfg)]
    cmd = [sys.executable, "-m", "service.cli", "replay", str(log), "--output", str(csv_path),
           "--json", str(json_path), "--no-progress"] + cfg_args + mode_args + (["--site", site] if site else [])
    t0 = time.perf_counter()
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    try:
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return {"ok": False, "reason": f"timed out after {timeout_s:.0f} s", "traceback": False}
    wall = time.perf_counter() - t0
    tb = "Traceback (most recent call last)" in p.stderr
    if p.returncode != 0 or not json_path.exists():
        lines = [ln for ln in p.stderr.strip().splitlines() if ln.strip()]
        return {"ok": False, "traceback": tb, "exit_code": p.returncode,
                "reason": (lines[-1] if lines else f"exit {p.returncode}")[:300]}
    summ = json.loads(json_path.read_text())
    out = {"ok": True, "traceback": tb, "wall_time_s": wall,
           "flight_time_s": summ.get("log_duration_s"), "imu_rate_hz": summ.get("imu_rate_hz")}
    ft = out["flight_time_s"]
    out["x_realtime"] = ft / wall if ft and wall > 0 else None
    out.update(score_rows(read_csv(csv_path)))
    # a run the phases found started in flight (no levelling, no launch) has no take-off of its own,
    # though its rows go from pre-launch to in-flight
    sif = next((e for e in summ.get("event_reasons", []) if e.get("kind") == "started_in_flight"), None)
    out["started_in_flight_s"] = sif.get("first_time_s") if sif else None
    if sif is not None:
        out["detected_takeoff_s"] = None
    usable, why = mag_verdict(p.stdout, summ)
    out["magnetometer_usable"], out["magnetometer_reason"] = usable, why
    out["warnings"] = summ.get("warnings", [])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="*", type=pathlib.Path, help="folders or logs (default ../shared/data)")
    ap.add_argument("--quick", action="store_true", help="same logs (they are short); kept for the bench contract")
    ap.add_argument("--json", type=pathlib.Path, default=ROOT / "bench" / "results" / "real_logs.json")
    ap.add_argument("--site-for", action="append", default=[], metavar="NAME=LAT,LON",
                    help="a site for a log without a GNSS position (file name = LAT,LON[,ALT])")
    ap.add_argument("--vehicle-for", action="append", default=[], metavar="NAME=VEHICLE",
                    help="[launch] vehicle an operator configures for a log (launcher, hand, runway, multicopter, vtol)")
    ap.add_argument("--timeout", type=float, default=900.0, help="per replay, s")
    args = ap.parse_args(argv)
    sites = _per_log(ap, ASSUMED_SITES, args.site_for, "--site-for", "LAT,LON")
    vehicles = _per_log(ap, OPERATOR_VEHICLE, args.vehicle_for, "--vehicle-for", "VEHICLE")
    logs = find_logs(args.paths or [DATA])
    if not logs:
        print(f"real_logs: no .tlog/.bin/.ulg under {', '.join(map(str, args.paths or [DATA]))}", file=sys.stderr)
        return 2
    res: dict = {"logs": {}, "targets": {"heading_rms_deg": HEADING_TARGET_RMS_DEG,
                                         "within_2sigma_fraction": WITHIN_2SIGMA_TARGET,
                                         "takeoff_error_s": TAKEOFF_TARGET_S}}
    with tempfile.TemporaryDirectory(prefix="real_logs_") as td:
        tmp = pathlib.Path(td)
        for log in logs:
            entry: dict = {"path": str(log)}
            site = sites.get(log.name)
            veh = vehicles.get(log.name)
            entry["operator_vehicle"] = veh
            for mode, extra in MODES.items():
                r = replay(log, extra, None, tmp, args.timeout, veh)
                if not r["ok"] and site is not None and "site" in r.get("reason", ""):
                    r = replay(log, extra, site, tmp, args.timeout, veh)
                    r["site"] = f"assumed {site} (the log has no GNSS position)"
                entry[mode] = r
            ex, al = entry["fc_excluded"], entry["fc_allowed"]
            entry["replayed"] = bool(ex["ok"] or al["ok"])
            entry["gnss_position"] = "site" not in ex and "site" not in al
            takeoffs, src = log_takeoffs(log)
            entry["log_takeoffs_s"], entry["log_takeoff_source"] = takeoffs, src
            ours = al.get("detected_takeoff_s") if al["ok"] else None
            if takeoffs:
                entry["takeoff_error_s"] = (min((ours - t for t in takeoffs), key=abs)
                                            if ours is not None else None)
            else:
                entry["takeoff_error_s"] = None
            entry["magnetometer_usable"] = ex.get("magnetometer_usable") if ex["ok"] else None
            entry["azimuth_solved"] = bool(al.get("azimuth_solved") or ex.get("azimuth_solved"))
            res["logs"][log.name] = entry
            print_row(log.name, entry)
    res["replay_failures"] = sum(not e["replayed"] for e in res["logs"].values())
    res["tracebacks"] = sum(bool(e[m].get("traceback")) for e in res["logs"].values() for m in MODES)
    res["checks"] = checks(res["logs"])
    print(f"\nreplay_failures {res['replay_failures']}  tracebacks {res['tracebacks']}")
    for name, ok in res["checks"].items():
        print(f"  {'PASS' if ok else 'FAIL'}  {name}")
    from service.replay import json_safe
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(json_safe(res), indent=2) + "\n")
    print(f"json: {args.json}")
    return 0


def _per_log(ap: argparse.ArgumentParser, defaults: dict, items: list[str], option: str, what: str) -> dict:
    """``defaults`` updated by the NAME=VALUE items of a per-log option (a usage error names it)."""
    out = dict(defaults)
    for item in items:
        name, _, val = item.partition("=")
        if not name or not val:
            ap.error(f"{option}: expected NAME={what}, got {item!r}")
        out[name] = val
    return out


def checks(logs: dict) -> dict:
    """The issue's targets, one line each, from the figures (nothing here decides a figure)."""
    out = {}
    for name, e in logs.items():
        ex = e["fc_excluded"]
        if not ex["ok"]:
            out[f"{name}: replays with the FC yaw excluded"] = False
            continue
        if e["magnetometer_usable"] and e["gnss_position"]:
            v = ex.get("heading_rms_deg")
            out[f"{name}: FC-excluded heading RMS <= {HEADING_TARGET_RMS_DEG:g} deg ({v:.2f})"
                if v == v else f"{name}: FC-excluded heading RMS (no heading)"] = bool(v == v and v <= HEADING_TARGET_RMS_DEG)
        elif e["magnetometer_usable"] is False:
            out[f"{name}: magnetometer rejected with a reason ({ex.get('magnetometer_reason', '')[:60]})"] = \
                bool(ex.get("magnetometer_reason"))
        w = ex.get("within_2sigma_fraction")
        if w is not None and w == w and e["gnss_position"]:
            out[f"{name}: FC-excluded within 2 sigma >= {WITHIN_2SIGMA_TARGET:.0%} ({w:.1%})"] = w >= WITHIN_2SIGMA_TARGET
        if e["log_takeoffs_s"]:
            te = e["takeoff_error_s"]
            out[f"{name}: take-off within {TAKEOFF_TARGET_S:g} s of the log's ({'none' if te is None else f'{te:+.1f} s'})"] = \
                te is not None and abs(te) <= TAKEOFF_TARGET_S
    return out


def _g(d: dict, k: str, fmt: str = ".2f") -> str:
    v = d.get(k)
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def print_row(name: str, e: dict) -> None:
    print(f"\n{name}" + (f"  (operator config: [launch] vehicle = {e['operator_vehicle']})"
                         if e.get("operator_vehicle") else ""))
    if "site" in e["fc_excluded"]:
        print(f"  site: {e['fc_excluded']['site']}")
    for mode in MODES:
        r = e[mode]
        if not r["ok"]:
            print(f"  {mode:11s} FAILED{' (traceback)' if r.get('traceback') else ''}: {r['reason']}")
            continue
        print(f"  {mode:11s} ok  {_g(r, 'wall_time_s', '.1f')} s wall for {_g(r, 'flight_time_s', '.1f')} s "
              f"({_g(r, 'x_realtime', '.1f')}x), IMU {_g(r, 'imu_rate_hz', '.0f')} Hz; heading coverage "
              f"{_g(r, 'heading_coverage_fraction', '.0%')}; RMS roll {_g(r, 'roll_rms_deg')} pitch "
              f"{_g(r, 'pitch_rms_deg')} heading {_g(r, 'heading_rms_deg')} deg (own {_g(r, 'heading_rms_own_deg')}); "
              f"within 2 sigma {_g(r, 'within_2sigma_fraction', '.0%')} (median sigma "
              f"{_g(r, 'heading_sigma_median_deg')}); method A {'solved' if r['azimuth_solved'] else 'no'}")
    te = e["takeoff_error_s"]
    sif = e["fc_allowed"].get("started_in_flight_s")
    ours = f"none (started in flight, said at {sif:.1f} s)" if sif is not None else \
        f"{_g(e['fc_allowed'], 'detected_takeoff_s', '.1f')} s"
    print(f"  take-off: ours {ours}, the log's "
          f"{e['log_takeoffs_s'] if e['log_takeoffs_s'] else '-'} ({e['log_takeoff_source']}); error "
          f"{'-' if te is None else f'{te:+.1f} s'}")
    mu = e["magnetometer_usable"]
    why = e["fc_excluded"].get("magnetometer_reason", "")
    print(f"  magnetometer: {'-' if mu is None else ('usable' + (': ' + why if why else '')) if mu else 'REJECTED: ' + why}")


if __name__ == "__main__":
    sys.exit(main())
