"""Method C's filter step with its magnetometer chain as one core call (core/filter_chain.hpp) against
the Python chain (service/pipeline.py Pipeline._filter_chain_python, each step a call of its own),
passes interleaved in one process (on, off, on, off ...) so that the machine's load moves both alike:

- the whole stack per IMU sample, bench/speed.py's ``case_pipeline_batch1`` (the daemon: one RAW_IMU
  per batch) and ``case_pipeline_step`` (step_imu), beside imufusion in the same run;
- the chain itself per filter step: wall time around Pipeline._filter_chain (median, p10, mean).

    python bench/filter_chain_ab.py [--rounds 4]

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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=4)
    a = ap.parse_args(argv)
    import bench.speed as sp
    import service.pipeline as P
    from bench.sitl import pipeline_inputs
    from estimators import core
    if not core.FILTER_CHAIN_AVAILABLE:
        print("compiled core without the filter chain: nothing to compare")
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
            core.FILTER_CHAIN_AVAILABLE = on   # read when a Pipeline is built
            for name, fac in cases.items():
                key = f"{name}_chain_{'on' if on else 'off'}"
                us = sp.time_case(fac, run, items, n_imu, 0.0)["us_per_imu_sample"]
                best[key] = min(best.get(key, float("inf")), us)
        fusion = min(fusion, sp.time_case(sp.case_imufusion, run, items, n_imu, 0.0)["us_per_imu_sample"])
    # the chain alone: wall time around each Pipeline._filter_chain call
    chain = P.Pipeline._filter_chain
    per: dict[str, list] = {"on": [], "off": []}

    def timed(self, *args):
        t0 = time.perf_counter()
        out = chain(self, *args)
        per["on" if self.filter_chain_core else "off"].append(time.perf_counter() - t0)
        return out
    P.Pipeline._filter_chain = timed
    try:
        for _ in range(2):
            for on in (True, False):
                core.FILTER_CHAIN_AVAILABLE = on
                sp._pipeline_batch_pass(run, items, 1)()
    finally:
        P.Pipeline._filter_chain = chain
        core.FILTER_CHAIN_AVAILABLE = True
    print(f"load {load0:.2f} -> {os.getloadavg()[0]:.2f}; imufusion {fusion:.2f} us per IMU sample")
    for k, v in best.items():
        print(f"{k:20s} {v:7.2f} us per IMU sample  {v / fusion:5.1f}x imufusion")
    for k, v in per.items():
        v = sorted(v)
        print(f"chain {k:3s}: {len(v)} filter steps, median {1e6 * statistics.median(v):.1f} us, p10 "
              f"{1e6 * v[len(v) // 10]:.1f} us, mean {1e6 * sum(v) / len(v):.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
