"""CPU cost of one GROUND (pre-launch) IMU sample through the Pipeline (issue 19): the daemon's
largest per-sample item before take-off, and a replay's for a log with a long ground phase.

    python bench/ground_speed.py [--seconds 20] [--rate 400] [--passes 5] [--json PATH]

The stream: the bundled simulator's ``inclined_rail`` launcher at rest for the whole stream (the IMU
at ``--rate`` Hz, pressure and the FC's ATTITUDE as bench/sitl.pipeline_inputs gives them), fed to a
fresh Pipeline per pass on the path the daemon and the replay use:

- ``step_imu``: the daemon's message path (Pipeline.step_imu, one sample per call);
- ``batch1``: the daemon's batch path with one row per batch (Pipeline.on_imu_batch);
- ``batch``: the IMU samples between two other items as one batch (a replay, the batch path);
- ``on_imu``: Pipeline.on_imu per sample (the reference path of every sample, with the core);
- ``python``: on_imu with the Python reference (AZIMUTHD_CORE=python).

Per path: the process CPU time per IMU sample over a pass (the best of ``--passes``: the least
disturbed by the other processes on the machine), and for the per-sample paths the wall time of
each call split by what it did: a sample between filter steps (no solution) and a filter step (a
solution), their means and medians (best pass by mean). Runs the tree it is started in (the current
directory's checkout first on sys.path, as a frozen clone's own venv runs it); prints the load."""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path[:0] = [os.getcwd(), str(Path.cwd() / "bench")]


def make_items(seconds: float, rate_hz: float) -> tuple[list, dict]:
    from sitl import pipeline_inputs, scenario_site
    from service.config import validate
    from sim.offline import simulate
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=rate_hz, duration_s=seconds,
                   overrides={"launcher": {"rest_s": seconds + 60.0}})
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    cfg = validate({**site, "mavlink": {"imu_rate_hz": rate_hz}, "launch": {"case": "inclined", "vehicle": "launcher"}})
    return pipeline_inputs(run), cfg


def _pipeline(cfg, backend: str):
    from speed import pipeline_on
    return pipeline_on(cfg, backend)


def _handlers(p) -> dict:
    return {"PressureSample": p.on_pressure, "FcAttitude": p.on_fc_attitude, "FcHeartbeat": p.on_fc_heartbeat,
            "FcEkfStatus": p.on_fc_ekf_status, "FcFlightState": p.on_fc_flight_state}


def pass_per_sample(items, cfg, path: str) -> dict:
    """One pass of a per-sample path: CPU per sample, and each call's wall time by kind."""
    from mavlink_io.samples import ImuSample
    p = _pipeline(cfg, "python" if path == "python" else "core")
    step = p.step_imu if path == "step_imu" else p.on_imu
    others = _handlers(p)
    between, steps = [], []
    clock = time.perf_counter_ns
    n = 0
    cpu0 = time.process_time()
    for it in items:
        if type(it) is ImuSample:
            t0 = clock()
            sol = step(it)
            dt = clock() - t0
            if sol is None:
                between.append(dt)
                if path == "step_imu":
                    p.propagated_snapshot()   # what the daemon takes between filter steps
            else:
                steps.append(dt)
            p.drain_events()
            n += 1
        else:
            others[type(it).__name__](it)
    cpu = time.process_time() - cpu0
    assert p.phase.phase == "pre-launch", p.phase.phase
    return {"cpu_us_per_sample": cpu / n * 1e6, "samples": n,
            "between_mean_us": statistics.fmean(between) / 1e3, "between_median_us": statistics.median(between) / 1e3,
            "between_n": len(between),
            "filter_step_mean_us": statistics.fmean(steps) / 1e3, "filter_step_median_us": statistics.median(steps) / 1e3,
            "filter_step_n": len(steps)}


def pass_batches(items, cfg, max_rows: int | None) -> dict:
    """One pass of the batch path: CPU per sample (the batches made before the clock starts)."""
    from mavlink_io.samples import ImuSample
    from service.hot_path import batches_of
    plan = batches_of(items, max_rows)
    p = _pipeline(cfg, "core")
    others = _handlers(p)
    n = sum(type(it) is ImuSample for it in items)
    cpu0 = time.process_time()
    for it in plan:
        if type(it).__name__ == "ImuBatch":
            p.on_imu_batch(it)
            p.drain_events()
            p.propagated_snapshot()
        else:
            others[type(it).__name__](it)
    cpu = time.process_time() - cpu0
    assert p.phase.phase == "pre-launch", p.phase.phase
    return {"cpu_us_per_sample": cpu / n * 1e6, "samples": n}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=400.0)
    ap.add_argument("--passes", type=int, default=5)
    ap.add_argument("--paths", nargs="+", default=["step_imu", "batch1", "batch", "on_imu", "python"])
    ap.add_argument("--json", type=Path, default=Path("bench/results/ground_speed.json"))
    a = ap.parse_args(argv)
    import service
    items, cfg = make_items(a.seconds, a.rate)
    out = {"tree": str(Path(service.__file__).resolve().parents[1]), "load_before": os.getloadavg(),
           "seconds": a.seconds, "rate_hz": a.rate, "passes": a.passes, "paths": {}}
    print(f"tree {out['tree']}; {a.seconds:g} s at rest at {a.rate:g} Hz; load {os.getloadavg()[0]:.2f}", flush=True)
    for path in a.paths:
        runs = []
        for _ in range(a.passes):
            if path in ("batch1", "batch"):
                runs.append(pass_batches(items, cfg, 1 if path == "batch1" else None))
            else:
                runs.append(pass_per_sample(items, cfg, path))
        best = min(runs, key=lambda r: r["cpu_us_per_sample"])
        if "between_mean_us" in runs[0]:
            by_wall = min(runs, key=lambda r: r["between_mean_us"])
            best = {**best, **{k: by_wall[k] for k in by_wall if k.startswith(("between", "filter_step"))}}
        best["cpu_us_per_sample_all_passes"] = [r["cpu_us_per_sample"] for r in runs]
        out["paths"][path] = best
        line = f"  {path:9s} CPU {best['cpu_us_per_sample']:7.1f} us/sample (best of {a.passes})"
        if "between_mean_us" in best:
            line += (f"; between filter steps {best['between_mean_us']:6.1f} us mean, {best['between_median_us']:6.1f} "
                     f"median; filter step {best['filter_step_mean_us']:6.1f} mean, "
                     f"{best['filter_step_median_us']:6.1f} median (wall)")
        print(line, flush=True)
    out["load_after"] = os.getloadavg()
    print(f"load {out['load_before'][0]:.2f} -> {out['load_after'][0]:.2f}")
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(out, indent=1))
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
