"""Where the microseconds of one IMU sample go in the Pipeline, by part (issue 19 item 1's
profile), with the compiled core on (the default) or the Python reference (AZIMUTHD_CORE=python).

    python bench/core_speed.py [--quick] [--backend core|python] [--json PATH]

bench/speed.py's 400 Hz stream (sim ``inclined_rail``, rest then launch and flight) is fed to one
Pipeline as the daemon feeds it (bench/sitl.feed_pipeline). Each part below is wrapped by a timer
(time.thread_time, this thread's CPU time, around the call; nested parts are taken out of their parent, so each row is
that part's own time and the rows add up to the whole). The figure per part is its time over
the pass / IMU samples in the stream, in microseconds; "untimed" is the Pipeline's own code
between the parts (and the feed loop). The timers cost ~0.3-0.5 us per wrapped call (measured
as the difference between the timed and an untimed pass, printed as ``timer_overhead``).

JSON: ``parts`` (name -> ``us_per_imu_sample``, ``calls``), ``total_us_per_imu_sample`` (timed
pass), ``untimed_pass_us_per_imu_sample`` (process CPU, same stream, no timers), ``backend``,
``imu_samples``, ``load_avg_1min``.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# (owner, attribute, part name): module-level functions as service.pipeline calls them, and
# Pipeline methods; a name may appear under several owners (one part)
MODULE_PARTS = [
    ("phase_step", "phases (phase_step)"),
    ("azimuth_step", "A: azimuth_step (in flight)"),
    ("azimuth_prelaunch_step", "A: azimuth_prelaunch_step"),
    ("azimuth_launch", "A: azimuth_launch"),
    ("azimuth_apply_solve", "A: apply solve"),
    ("rest_accumulate", "E: rest_accumulate"),
    ("polar_attitude_step", "C: polar_attitude_step"),
    ("polar_attitude_estimate", "C: polar_attitude_estimate"),
    ("polar_heading_step", "C: polar_heading_step"),
    ("polar_heading_estimate", "C: polar_heading_estimate"),
    ("polar_heading_attitude", "C: polar_heading_attitude"),
    ("mag_disturbance_step", "mag_disturbance_step"),
    ("mag_usability_step", "mag_usability_step"),
    ("mag_usability_stale", "mag_usability_step"),
    ("output_step", "output propagation (output_step)"),
    ("output_reset", "output propagation (output_step)"),
    ("arbitrate", "arbitration (arbitrate)"),
    ("deviation_step", "D: deviation_step"),
    ("corrected_mag", "D: corrected_mag"),
]
METHOD_PARTS = [
    ("_flight_evidence", "Pipeline: _flight_evidence"),
    ("_step_ahrs", "B: _step_ahrs (core or reference)"),
    ("_readings", "Pipeline: _readings (heading sources)"),
    ("_deviation_record", "Pipeline: _readings (heading sources)"),
    ("_heading_tilt", "Pipeline: tilt, platform, residual"),
    ("_heading_platform", "Pipeline: tilt, platform, residual"),
    ("_mag_hard_iron_residual", "Pipeline: tilt, platform, residual"),
    ("_solution", "Pipeline: _solution (rest of)"),
    ("_step_azimuth", "Pipeline: _step_azimuth (rest of)"),
    ("_mag_disturbance", "Pipeline: _mag_disturbance (rest of)"),
    ("_mag_usable", "Pipeline: _mag_usable (rest of)"),
    ("_deviation_corrected", "Pipeline: _deviation_corrected"),
    ("on_pressure", "Pipeline: on_pressure (rest of)"),
    ("on_fc_attitude", "Pipeline: on_fc_attitude (rest of)"),
    ("drain_events", "Pipeline: drain_events"),
]


class Timers:
    """Own time per part: a stack of running parts; a part's elapsed time is taken off its parent."""

    def __init__(self):
        self.own: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._child = [0.0]

    def wrap(self, name: str, fn):
        clock = time.thread_time  # CPU time of this thread: other users of a shared machine do not count

        @functools.wraps(fn)
        def timed(*a, **k):
            self._child.append(0.0)
            t0 = clock()
            try:
                return fn(*a, **k)
            finally:
                dt = clock() - t0
                kids = self._child.pop()
                self._child[-1] += dt
                self.own[name] = self.own.get(name, 0.0) + dt - kids
                self.calls[name] = self.calls.get(name, 0) + 1
        return timed


def instrument(pipeline, timers: Timers) -> None:
    import service.pipeline as sp
    for attr, name in MODULE_PARTS:
        if hasattr(sp, attr) and not hasattr(getattr(sp, attr), "__wrapped__"):
            setattr(sp, attr, timers.wrap(name, getattr(sp, attr)))
    for attr, name in METHOD_PARTS:
        setattr(pipeline, attr, timers.wrap(name, getattr(pipeline, attr)))
    pipeline.input_checks.check = timers.wrap("input checks (ImuInputChecks.check)", pipeline.input_checks.check)
    c = pipeline.core  # the parts the Pipeline calls through its backend (service/core_backend.py)
    for attr, name in (("strapdown_step", "Pipeline strapdown (core.strapdown_step)"),
                       ("mag_usability_step", "mag_usability_step"), ("mag_usability_stale", "mag_usability_step"),
                       ("azimuth_propagate", "A: azimuth_propagate (in azimuth_step)"),
                       ("mag_disturbance_step", "mag_disturbance_step"),
                       ("polar_attitude_step", "C: polar_attitude_step"),
                       ("polar_attitude_estimate", "C: polar_attitude_estimate"),
                       ("attitude_zero_rate_update", "C: attitude_zero_rate_update (at rest)"),
                       ("polar_heading_step", "C: polar_heading_step"),
                       ("polar_heading_estimate", "C: polar_heading_estimate"),
                       ("polar_heading_attitude", "C: polar_heading_attitude"),
                       ("heading_zero_rate_update", "C: heading_zero_rate_update (at rest)")):
        if hasattr(c, attr):
            object.__setattr__(c, attr, timers.wrap(name, getattr(c, attr)))
    pipeline.solver.submit = timers.wrap("A: solve (H8's solver, inline)", pipeline.solver.submit)
    pipeline.solver.poll = timers.wrap("A: apply solve", pipeline.solver.poll)
    pipeline.on_imu = timers.wrap("Pipeline: on_imu (own code)", pipeline.on_imu)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="bench/speed.py's quick stream (30 s at 400 Hz)")
    ap.add_argument("--backend", choices=("core", "python"), default="core")
    ap.add_argument("--json", default=None, help="default bench/results/core_speed_<backend>.json")
    args = ap.parse_args(argv)
    os.environ["AZIMUTHD_CORE"] = args.backend
    from bench.sitl import feed_pipeline, pipeline_inputs
    from bench.speed import RATE_HZ, make_stream, site_config
    from service.pipeline import Pipeline
    run = make_stream(args.quick)
    items = pipeline_inputs(run)
    cfg = site_config(run)
    n = len(run.time_s)
    print(f"stream: sim inclined_rail, {n} IMU samples at {RATE_HZ:.0f} Hz; backend {args.backend}")

    def one_pass(timers: Timers | None) -> float:
        p = Pipeline(cfg)
        if p.core.name != args.backend:
            raise SystemExit(f"asked for {args.backend}, got {p.core.name}: {p.core.why}")
        if timers is not None:
            instrument(p, timers)
        t0 = time.process_time()
        for _ in feed_pipeline(p, items):
            pass
        return time.process_time() - t0

    plain = min(one_pass(None) for _ in range(2))
    timers = Timers()
    w0 = time.thread_time()
    one_pass(timers)
    total = time.thread_time() - w0
    import service.pipeline as sp  # undo the module-level wrappers (a later Pipeline in this process)
    for attr, _ in MODULE_PARTS:
        f = getattr(sp, attr, None)
        if f is not None and hasattr(f, "__wrapped__"):
            setattr(sp, attr, f.__wrapped__)
    parts = {k: {"us_per_imu_sample": 1e6 * v / n, "calls": timers.calls[k]} for k, v in timers.own.items()}
    parts["untimed (feed loop)"] = {"us_per_imu_sample": 1e6 * (total - sum(timers.own.values())) / n, "calls": 0}
    res = {"backend": args.backend, "imu_samples": n, "total_us_per_imu_sample": 1e6 * total / n,
           "untimed_pass_us_per_imu_sample": 1e6 * plain / n,
           "timer_overhead_us_per_imu_sample": 1e6 * (total - plain) / n,
           "parts": dict(sorted(parts.items(), key=lambda kv: -kv[1]["us_per_imu_sample"])),
           "load_avg_1min": os.getloadavg()[0], "cpu_count": os.cpu_count()}
    print(f"{'part':<48} {'us/IMU sample':>14} {'calls':>7} {'share':>6}")
    for k, v in res["parts"].items():
        print(f"{k:<48} {v['us_per_imu_sample']:14.1f} {v['calls']:7d} {100 * v['us_per_imu_sample'] * n / 1e6 / total:5.0f}%")
    print(f"timed pass {res['total_us_per_imu_sample']:.1f} us/sample (thread CPU); untimed pass "
          f"{res['untimed_pass_us_per_imu_sample']:.1f} us/sample (process CPU); load {res['load_avg_1min']:.1f}")
    path = Path(args.json or ROOT / "bench" / "results" / f"core_speed_{args.backend}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2) + "\n")
    print(f"json: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
