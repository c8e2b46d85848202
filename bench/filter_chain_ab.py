"""A compiled-core switch on against off, passes interleaved in one process (on, off, on, off ...) so
that the machine's load moves both alike. ``--switch chain`` (the default): method C's filter step with
its magnetometer chain as one core call (core/filter_chain.hpp) against the Python chain
(service/pipeline.py Pipeline._filter_chain_python, each step a call of its own); ``--switch solution``:
the filter step's solution numbers in one core call (core/solution.hpp) against the reference's reads
(Pipeline._solution_attitude):

- the whole stack per IMU sample, bench/speed.py's ``case_pipeline_batch1`` (the daemon: one RAW_IMU
  per batch) and ``case_pipeline_step`` (step_imu), beside imufusion in the same run;
- the switched part per filter step: wall time around Pipeline._filter_chain / Pipeline._solution
  (median, p10, mean).

    python bench/filter_chain_ab.py [--rounds 4] [--switch chain|solution]

The stream: bench/speed.py's quick stream (sim inclined_rail, 400 Hz, 30 s, launch at 8 s). Best
pass of each, process CPU time; the 1-min load before and after.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


SWITCHES = {"chain": ("FILTER_CHAIN_AVAILABLE", "_filter_chain", "filter_chain_core"),
            "solution": ("SOLUTION_AVAILABLE", "_solution", "solution_core")}
"""--switch -> (estimators.core's flag read when a Pipeline is built, the Pipeline method timed, the
Pipeline's attribute that says the switch is on)."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--switch", choices=tuple(SWITCHES), default="chain")
    a = ap.parse_args(argv)
    flag, method, held = SWITCHES[a.switch]
    import bench.speed as sp
    import service.pipeline as P
    from bench.sitl import pipeline_inputs
    from estimators import core
    if not getattr(core, flag):
        print(f"compiled core without {flag}: nothing to compare")
        return 1
    run = sp.make_stream(True)
    items = pipeline_inputs(run)
    n_imu = len(run.gyro_rad_s)
    load0 = os.getloadavg()[0]
    cases = {"batch1": sp.case_pipeline_batch1, "step_imu": sp.case_pipeline_step}
    best: dict[str, float] = {}
    fusion = sp.time_case(sp.case_imufusion, run, items, n_imu, 0.0)["us_per_imu_sample"]
    for _ in range(a.rounds):
        for on in (True, False):
            setattr(core, flag, on)   # read when a Pipeline is built
            for name, fac in cases.items():
                key = f"{name}_{a.switch}_{'on' if on else 'off'}"
                us = sp.time_case(fac, run, items, n_imu, 0.0)["us_per_imu_sample"]
                best[key] = min(best.get(key, float("inf")), us)
        fusion = min(fusion, sp.time_case(sp.case_imufusion, run, items, n_imu, 0.0)["us_per_imu_sample"])
    # the switched part alone: wall time around each call of the Pipeline's method
    part = getattr(P.Pipeline, method)
    per: dict[str, list] = {"on": [], "off": []}

    def timed(self, *args):
        t0 = time.perf_counter()
        out = part(self, *args)
        per["on" if getattr(self, held) else "off"].append(time.perf_counter() - t0)
        return out
    setattr(P.Pipeline, method, timed)
    try:
        for _ in range(2):
            for on in (True, False):
                setattr(core, flag, on)
                sp._pipeline_batch_pass(run, items, 1)()
    finally:
        setattr(P.Pipeline, method, part)
        setattr(core, flag, True)
    print(f"load {load0:.2f} -> {os.getloadavg()[0]:.2f}; imufusion {fusion:.2f} us per IMU sample")
    for k, v in best.items():
        print(f"{k:20s} {v:7.2f} us per IMU sample  {v / fusion:5.1f}x imufusion")
    for k, v in per.items():
        v = sorted(v)
        print(f"{method} {k:3s}: {len(v)} filter steps, median {1e6 * statistics.median(v):.1f} us, p10 "
              f"{1e6 * v[len(v) // 10]:.1f} us, mean {1e6 * sum(v) / len(v):.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
