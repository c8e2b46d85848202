"""Levelling and take-off of the vehicles people fly, through the daemon's own Pipeline.

    python bench/takeoff_phases.py [--seeds N] [--json PATH]   (default bench/results/takeoff_phases.json)

Per shipped take-off scenario (sim/scenarios: multicopter_takeoff, vtol_takeoff, hand_launch,
runway_takeoff) at the rate an FC streams it (50 Hz; the VTOL at 25 Hz as well) and per seed:
the decoded samples (IMU, pressure, the FC's ATTITUDE, an armed HEARTBEAT at 1 Hz) go through a
Pipeline with ``[launch] vehicle`` set (case "aligned", "inclined" for the hand launch). The truth
(sim.offline's launch time) only scores.

Figures per case (JSON keys carry units):
  levelled_before_takeoff_fraction   runs whose levelling came before the detected take-off
  takeoff_error_abs_max_s            max |detected take-off - true take-off| over the seeds
  takeoff_error_mean_s               mean signed error (negative: early)
  started_in_flight_runs             runs wrongly taken for a start in flight (want 0)
  azimuth_running_fraction           runs where method A runs (not "not run"/"failed"/"disabled")
  azimuth_status                     method A's one-line status of the first seed at the end
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_takeoff_vehicles import fly  # noqa: E402  (the same feeding as the tests)

CASES = (  # scenario, IMU rate (Hz), vehicle, method A case, seconds fed after the true take-off
    ("multicopter_takeoff", 50.0, "multicopter", "aligned", 3.0),
    ("vtol_takeoff", 50.0, "vtol", "aligned", 3.0),
    ("vtol_takeoff", 25.0, "vtol", "aligned", 3.0),
    ("hand_launch", 50.0, "hand", "inclined", 1.0),
    ("runway_takeoff", 50.0, "runway", "aligned", 3.0),
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "takeoff_phases.json")
    a = ap.parse_args()
    out = {"seeds": a.seeds, "cases": {}}
    for scenario, rate, vehicle, case, after_s in CASES:
        from sim.scenario import load_scenario
        rest = load_scenario(scenario)["launcher"]["rest_s"]
        errs, before, sif, running, status = [], 0, 0, 0, ""
        for seed in range(a.seeds):
            run, p, events = fly(scenario, rate, vehicle, case=case, duration_s=rest + after_s, seed=seed)
            t_true = run.truth.launch_time_s
            t_lev = next((t for t, k, _d in events if k == "levelled"), None)
            t_det = p.phase.launch_time_s
            if t_det is not None:
                errs.append(t_det - t_true)
            before += int(t_lev is not None and t_lev <= t_true)  # levelled on data from before the take-off
            sif += int(p.phase.started_in_flight)
            st = p.azimuth_status()
            running += int(not st.startswith(("not run", "failed", "disabled")))
            status = status or st
        key = f"{scenario}@{rate:g}Hz"
        r = {"levelled_before_takeoff_fraction": before / a.seeds,
             "takeoff_detected_fraction": len(errs) / a.seeds,
             "takeoff_error_abs_max_s": float(np.max(np.abs(errs))) if errs else math.nan,
             "takeoff_error_mean_s": float(np.mean(errs)) if errs else math.nan,
             "started_in_flight_runs": sif, "azimuth_running_fraction": running / a.seeds,
             "azimuth_status": status}
        out["cases"][key] = r
        print(f"{key:28s} levelled first {r['levelled_before_takeoff_fraction']:.2f}  detected "
              f"{r['takeoff_detected_fraction']:.2f}  |err| max {r['takeoff_error_abs_max_s']:.2f} s  mean "
              f"{r['takeoff_error_mean_s']:+.2f} s  started-in-flight {sif}  A running "
              f"{r['azimuth_running_fraction']:.2f}  ({status[:70]})", flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        clean = json.loads(json.dumps(out), parse_constant=lambda _c: None)  # NaN -> null
        a.json.write_text(json.dumps(clean, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
