"""The Pipeline's per-IMU-sample hot path (service/hot_path.py, core/hot_path.hpp): CPU per IMU sample
of the whole stack with the compiled core, three ways, passes interleaved in one process (ABCABC...)
so that the machine's load moves all three alike:

- ``batch_hot``: fed as the daemon's batch path (Pipeline.on_imu_batch, the IMU samples between two
  other items as one batch, made once and untimed), the quiet samples in the core's hot path;
- ``batch_no_hot``: the same batches, the hot path off (on_imu for every sample);
- ``per_sample``: on_imu per sample as the daemon's message path (bench/sitl.feed_pipeline).

    python bench/hot_path_ab.py [--passes 3] [--json PATH]

The stream: bench/speed.py's quick stream (sim inclined_rail, 400 Hz, 30 s, launch at 8 s). Best and
every pass, process CPU time, with the 1-min load.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import bench.speed as sp
    import service.pipeline as P
    from bench.sitl import feed_pipeline, pipeline_inputs
    from service import core_backend
    from service.hot_path import batches_of
    run = sp.make_stream(True)
    items = pipeline_inputs(run)
    cfg = sp.site_config(run)
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    if core.hot_run is None:
        print(f"no hot path in this core: {core.why}")
        return 1
    plan = batches_of(items)

    def pipeline(backend):
        P.select_core = lambda: backend
        try:
            return P.Pipeline(cfg)
        finally:
            P.select_core = core_backend.select

    def batches(backend) -> float:
        p = pipeline(backend)
        others = {"PressureSample": p.on_pressure, "FcAttitude": p.on_fc_attitude}
        t0 = time.process_time()
        for it in plan:
            if type(it).__name__ == "ImuBatch":
                p.on_imu_batch(it)
                p.drain_events()
                p.propagated_solution()
            else:
                others[type(it).__name__](it)
        return time.process_time() - t0

    def per_sample(backend) -> float:
        p = pipeline(backend)
        t0 = time.process_time()
        for _ in feed_pipeline(p, items):
            pass
        return time.process_time() - t0

    n = len(run.time_s)
    ways = {"batch_hot": lambda: batches(core),
            "batch_no_hot": lambda: batches(dataclasses.replace(core, hot_run=None)),
            "per_sample": lambda: per_sample(core)}
    us = {k: [] for k in ways}
    loads = []
    for _ in range(a.passes):
        for k, f in ways.items():
            us[k].append(1e6 * f() / n)
        loads.append(os.getloadavg()[0])
    print(f"stream: {n} IMU samples at 400 Hz, launch at {run.truth.launch_time_s:.0f} s; {a.passes} interleaved passes, "
          f"1-min load {min(loads):.1f}-{max(loads):.1f}")
    for k, v in us.items():
        print(f"  {k:<13} best {min(v):7.1f} us per IMU sample (CPU)   passes {', '.join(f'{x:.1f}' for x in v)}")
    best = {k: min(v) for k, v in us.items()}
    print(f"  batch_hot / per_sample: {best['batch_hot'] / best['per_sample']:.3f}")
    if a.json:
        Path(a.json).write_text(json.dumps({"imu_samples": n, "us_per_imu_sample": us, "best": best,
                                            "load_avg_1min": loads}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
