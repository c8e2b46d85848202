"""Method B per event: the compiled core (estimators.core, state held in C++) against the Python
reference (estimators.synthetic_ahrs), in one run on one stream (bench/speed.py's stream and
timing: process CPU time, best of up to 5 passes, fresh state each pass).

    python bench/core_ahrs_speed.py [--quick] [--json PATH]

The events are those bench/speed.py's synthetic_ahrs case builds (IMU with magnetometer,
SCALED_PRESSURE, the FC's ATTITUDE, in time order), the output asked for on every IMU sample as the
Pipeline asks. Figures are per IMU sample (the other events' cost included). Before timing, the two
are checked to give the same final output (1e-9 relative). JSON: ``python_us_per_imu_sample``,
``core_us_per_imu_sample``, ``speedup_x`` (python / core), ``imu_samples``, ``load_avg_1min``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from speed import b_events  # noqa: E402  (one conversion of link items to B's events)


def one_pass(step, init, events, params, imu_cls):
    st, last = init(params), None
    for ev in events:
        st, out = step(st, ev, params, type(ev) is imu_cls)
        if out is not None:
            last = out
    return last


def best_cpu_s(fn, passes: int, budget_s: float) -> tuple[float, int]:
    best, n, t_start = math.inf, 0, time.perf_counter()
    while n < passes:
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
        n += 1
        if time.perf_counter() - t_start > budget_s:
            break
    return best, n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="bench/speed.py's quick stream (30 s at 400 Hz)")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "core_ahrs_speed.json"))
    args = ap.parse_args(argv)
    from bench.sitl import pipeline_inputs
    from bench.speed import RATE_HZ, make_stream
    from estimators import core
    from estimators import synthetic_ahrs as ref
    from estimators.synthetic_ahrs import ImuEvent, synthetic_ahrs_params_for_site
    if not core.AVAILABLE:
        print(f"compiled core not available: {core.IMPORT_ERROR}")
        return 1
    run = make_stream(args.quick)
    events = b_events(pipeline_inputs(run))
    s = run.site
    params = synthetic_ahrs_params_for_site(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"])
    n_imu = sum(1 for e in events if type(e) is ImuEvent)
    print(f"stream: sim inclined_rail, {n_imu} IMU samples at {RATE_HZ:.0f} Hz, {len(events)} B events")
    a = one_pass(ref.synthetic_ahrs_step, ref.synthetic_ahrs_init, events, params, ImuEvent)
    b = one_pass(core.synthetic_ahrs_step, ref.synthetic_ahrs_init, events, params, ImuEvent)
    att_a = np.array([a.roll_rad, a.pitch_rad, a.heading_rad])
    att_b = np.array([b.roll_rad, b.pitch_rad, b.heading_rad])
    same = bool(np.max(np.abs(att_a - att_b)) <= 1e-9 * np.max(np.abs(att_a)) and a.mag_fused == b.mag_fused
                and a.ref_fused == b.ref_fused and a.reference_reason == b.reference_reason)
    print(f"final outputs agree to 1e-9: {same}")
    budget = 20.0 if args.quick else 60.0
    py_s, py_n = best_cpu_s(lambda: one_pass(ref.synthetic_ahrs_step, ref.synthetic_ahrs_init, events, params,
                                             ImuEvent), 3, budget)
    c_s, c_n = best_cpu_s(lambda: one_pass(core.synthetic_ahrs_step, ref.synthetic_ahrs_init, events, params,
                                           ImuEvent), 5, budget)
    res = {"imu_samples": n_imu, "events": len(events), "outputs_agree": same,
           "python_us_per_imu_sample": 1e6 * py_s / n_imu, "python_passes": py_n,
           "core_us_per_imu_sample": 1e6 * c_s / n_imu, "core_passes": c_n,
           "speedup_x": py_s / c_s if c_s > 0 else math.nan, "load_avg_1min": os.getloadavg()[0],
           "cpu_count": os.cpu_count()}
    print(f"method B per IMU sample: Python reference {res['python_us_per_imu_sample']:.1f} us, "
          f"core {res['core_us_per_imu_sample']:.2f} us: {res['speedup_x']:.0f}x (load {res['load_avg_1min']:.1f})")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {args.json}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
