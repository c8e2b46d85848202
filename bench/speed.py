"""Speed: per-IMU-sample cost of our stack and of each estimator, against imufusion, VQF and ahrs;
end-to-end latency RAW_IMU -> ATTITUDE and the daemon's CPU, with the simulator and the daemon as
separate processes at 400 Hz.

    python bench/speed.py [--quick] [--json PATH] [--no-install] [--no-sitl] [--sitl-only] [--imu-batch]
                          [--no-replay] [--busy | --busy-only] [--busy-s 600] [--busy-competitors 2]
                          [--busy-daemon-group-nice N]

1. Compute cost. One synthetic 400 Hz stream (sim.offline, ``inclined_rail`` with a shortened rest
   so that pre-launch and flight are both in it): IMU + SCALED_PRESSURE + the FC's ATTITUDE, in
   time order. Each case runs over the whole stream in this process; the figure is wall time /
   IMU samples (best of up to 3 passes: the machine is shared). Cases: the daemon's Pipeline
   (every estimator it runs, fed exactly as the daemon feeds it), each estimator alone, and the
   references imufusion (x-io Fusion, C), vqf (C++), ahrs Madgwick and ahrs EKF (numpy). The
   references are benchmark-only: installed into this venv at bench start if missing (their
   versions are printed), never runtime dependencies.
   The compiled core (issue 19): the whole stack runs twice, with the ported parts in the core (the
   default) and with the Python reference (AZIMUTHD_CORE=python); each ported part runs as the
   Python reference, through the core per sample, and through the core's batch API (the whole
   stream's N x 3 arrays in one call). The daemon's batch path (Pipeline.on_imu_batch) runs twice:
   the IMU samples between two other items as one batch, and one row per batch (the daemon at
   400 Hz reads one RAW_IMU per wake-up); and the daemon's message path (Pipeline.step_imu per
   sample). The headline ``stack_us_per_imu_sample`` stays on_imu per sample (the reference path).
   JSON ``ported``: per-sample costs and speed-ups
   (``*_speedup_x`` = reference / core), all from the same run as imufusion and vqf.
2. Latency. ``bench.sitl.Sitl`` (simulator and daemon as two processes over loopback UDP) with a
   tap between them that timestamps, on one monotonic clock in one thread, every RAW_IMU it
   forwards to the daemon and every ATTITUDE the daemon sends back. The daemon stamps ATTITUDE
   with ``time_boot_ms = int(time_fc_s * 1000)`` of the IMU sample the solution is for, and
   RAW_IMU carries that sample's ``time_usec``: an ATTITUDE is matched to the one RAW_IMU (400 Hz:
   2.5 ms apart) whose time_usec is within 1 ms of time_boot_ms (truncated or rounded). Latency = tap
   receive time of the ATTITUDE - tap forward time of its RAW_IMU: the daemon's receive, decode,
   estimators and send, plus two loopback hops and the tap's own scheduling (an upper bound).
   The daemon sends ATTITUDE at ``outputs.attitude_hz`` (50 Hz, the default): each measured
   ATTITUDE is the solution of the sample that made it due.
   The harness floor (a datagram through a trivial Python echo process and back, at 400 Hz) is
   measured after the SITL on the same machine: what the SITL figure has above it is the daemon.
3. CPU. ``psutil`` cpu_times of the daemon process over a window (30 s; 12 s with --quick) in
   flight at 400 Hz: (user + system) / wall, in percent of one core. The simulator's share is
   reported apart. The daemon runs as the systemd unit schedules it: a session of its own whose CPU
   group (kernel autogroup) has the unit's ``Nice=`` (bench/sitl.py ``unit_nice``; needs root), the
   1-min load beside the figures; ``--imu-batch`` runs the batch path ([mavlink] imu_batch on: a
   read's RAW_IMU as one ImuBatch) instead of the daemon's default message path, for a before/after. ``--sitl-only`` skips
   part 1.
4. Busy (``--busy``; ``--busy-only`` alone, JSON default bench/results/speed_busy.json): issue 19's
   "the daemon at 400 Hz with two competing CPU-bound processes on the 2-core machine for 10 min:
   0 samples lost in the kernel or the daemon, ATTITUDE at the configured rate". The SITL of part 2
   (simulator, tap, daemon) plus ``--busy-competitors`` busy loops (:class:`Competitors`: each a
   process in a session, so a CPU group, of its own at nice 0, the same user: another service at
   the default weight), started before the daemon and running until it stopped; ``--busy-s`` of
   window once the daemon sends ATTITUDE. As root the daemon's group gets the unit's ``Nice=``
   (``--busy-daemon-group-nice 0``: none, a before/after) and the simulator and the tap, the FC
   and its wire, a group at nice -15 (a real FC has its own CPU; bench/geofence.py does the same).
   At the end the simulator stops first, the tap and the daemon read what is queued for them, then
   the daemon stops and logs its counters. JSON ``busy``: ``samples_lost`` with each part named
   (:func:`busy_accounting`: the tap's socket, dropped by the tap on purpose, the daemon's socket,
   read by the daemon but not processed) from independent observers that must agree (the
   simulator's send count, the tap, the kernel's socket tables read by the bench, the daemon's
   own counters and MAVLink sequence gaps), ``samples_sent``, ``attitude_rate_hz`` against
   ``attitude_rate_configured_hz``, the daemon's CPU, latency p50/p99 under load, the load
   average, the scheduling used (the groups as /proc shows them, the unit's keys), and a one-line
   ``verdict``: PASS, FAIL, or INVALID when the harness itself lost samples, the simulator fell
   behind real time or the observers disagree.

Targets (issue 9): whole stack <= 8 us per IMU sample, latency p99 <= 1 ms, CPU <= 5 % of a core.
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from service.replay import json_safe  # noqa: E402

RATE_HZ = 400.0
TARGET_STACK_US = 8.0
TARGET_P99_MS = 1.0
TARGET_CPU_PCT = 5.0
REFERENCE_PACKAGES = {"imufusion": "imufusion", "vqf": "vqf", "ahrs": "AHRS"}
"""import name -> distribution name, benchmark-only."""


# --- references: install for the benchmark only ----------------------------------------------

def ensure_references(install: bool) -> dict[str, str | None]:
    from importlib.metadata import PackageNotFoundError, version
    out = {}
    for mod, dist in REFERENCE_PACKAGES.items():
        try:
            importlib.import_module(mod)
        except ImportError:
            if install:
                print(f"installing {dist} into {sys.prefix} for this benchmark only ...", flush=True)
                subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", dist], check=False)
                importlib.invalidate_caches()
        try:
            importlib.import_module(mod)
            out[mod] = version(dist)
        except (ImportError, PackageNotFoundError):
            out[mod] = None
    return out


# --- the stream --------------------------------------------------------------------------------

def make_stream(quick: bool):
    from sim.offline import simulate
    rest_s, dur_s = (8.0, 30.0) if quick else (20.0, 120.0)
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ,
                   duration_s=dur_s, overrides={"launcher": {"rest_s": rest_s}})
    return run


def site_config(run) -> dict:
    from service.config import validate
    s = run.site
    return validate({"site": {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"],
                              "decimal_year": s["decimal_year"]},
                     "mavlink": {"imu_rate_hz": RATE_HZ},
                     # the operator's launch config for the inclined_rail stream (as bench/sitl.py
                     # scenario_site): with the default vehicle "auto" and no FC HEARTBEAT in this
                     # offline feed nothing would take off and the in-flight stack would go unmeasured
                     "launch": {"case": "inclined", "vehicle": "launcher"}})


# --- compute-cost cases ------------------------------------------------------------------------
# Each case: name -> factory(run, items) returning a zero-argument callable that runs one full pass
# over the stream (fresh state each pass). Factories that fail (an estimator's API moved) are
# reported as errors, not hidden.

def _pipeline_case(backend: str):
    """The whole stack with the ported parts in the compiled core or the Python reference
    (service/core_backend.py: AZIMUTHD_CORE, read when a Pipeline is built)."""
    def factory(run, items):
        from bench.sitl import feed_pipeline
        cfg = site_config(run)

        def one_pass():
            p = pipeline_on(cfg, backend)
            for _ in feed_pipeline(p, items):
                pass
        return one_pass
    return factory


case_pipeline = _pipeline_case("core")
case_pipeline_python = _pipeline_case("python")


def pipeline_on(cfg, backend: str):
    """A Pipeline on ``backend`` ("core": the compiled core, "python": the reference), the
    selection (AZIMUTHD_CORE) restored after; an error when that backend is not what it got."""
    from service.pipeline import Pipeline
    before = os.environ.get("AZIMUTHD_CORE")
    os.environ["AZIMUTHD_CORE"] = backend
    try:
        p = Pipeline(cfg)
    finally:
        os.environ.pop("AZIMUTHD_CORE") if before is None else os.environ.update(AZIMUTHD_CORE=before)
    if p.core.name != backend:
        raise RuntimeError(f"asked for {backend}, got {p.core.name}: {p.core.why}")
    return p


def _core_pipeline(cfg):
    """A Pipeline on the compiled core with its hot path."""
    p = pipeline_on(cfg, "core")
    if p.core.hot_run is None:
        raise RuntimeError(f"no hot path in this core: {p.core.why}")
    return p


def _pipeline_batch_case(max_rows: int | None):
    """The whole stack with the compiled core fed as the daemon's batch path feeds it
    (Pipeline.on_imu_batch: the quiet samples in the core's hot path, service/hot_path.py): the IMU
    samples between two other items as one batch (made once, untimed: the link decodes them), cut
    to ``max_rows`` rows (1: the daemon at 400 Hz, one RAW_IMU per datagram and per wake-up)."""
    def factory(run, items):
        return _pipeline_batch_pass(run, items, max_rows)
    return factory


def _pipeline_batch_pass(run, items, max_rows: int | None):
    from service.hot_path import batches_of
    cfg = site_config(run)
    plan = batches_of(items, max_rows)

    def one_pass():
        p = _core_pipeline(cfg)
        handlers = {}
        for it in plan:
            c = type(it)
            if c.__name__ == "ImuBatch":
                p.on_imu_batch(it)
                p.drain_events()
                p.propagated_snapshot()   # what the daemon takes after a batch (built for an output slot)
            else:
                fn = handlers.get(c)
                if fn is None:
                    fn = handlers[c] = {"PressureSample": p.on_pressure, "FcAttitude": p.on_fc_attitude,
                                        "FcHeartbeat": p.on_fc_heartbeat, "FcFlightState": p.on_fc_flight_state,
                                        "FcEkfStatus": p.on_fc_ekf_status}[c.__name__]
                fn(it)
    return one_pass


case_pipeline_batch = _pipeline_batch_case(None)
case_pipeline_batch1 = _pipeline_batch_case(1)


def case_pipeline_step(run, items):
    """The whole stack with the compiled core fed as the daemon's message path feeds it: each IMU
    sample through Pipeline.step_imu (a quiet one in the core's hot path, as a batch of one row),
    then the propagated snapshot the daemon takes between filter steps."""
    from mavlink_io.samples import ImuSample
    cfg = site_config(run)

    def one_pass():
        p = _core_pipeline(cfg)
        others = {}
        for it in items:
            c = type(it)
            if c is ImuSample:
                if p.step_imu(it) is None:
                    p.propagated_snapshot()
                p.drain_events()
            else:
                fn = others.get(c)
                if fn is None:
                    fn = others[c] = {"PressureSample": p.on_pressure, "FcAttitude": p.on_fc_attitude}[c.__name__]
                fn(it)
    return one_pass


def case_phases(run, items):
    from service.phases import PhaseParams, PhaseState, phase_step
    t, g, a = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2)
    params = PhaseParams()

    def one_pass():
        st = PhaseState()
        for k in range(len(t)):
            st, _ = phase_step(st, g[k], a[k], t[k], params)
    return one_pass


def case_phases_core(run, items):
    """The flight phases held in the core (service.phases_core.phase_step), the same samples and params."""
    from service import phases_core
    from service.phases import PhaseParams, PhaseState
    t, g, a = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2)
    params = PhaseParams()

    def one_pass():
        st = PhaseState()
        for k in range(len(t)):
            st, _ = phases_core.phase_step(st, g[k], a[k], t[k], params)
    return one_pass


def case_strapdown(run, items):
    from estimators.strapdown import StrapdownParams, strapdown_init, strapdown_step
    t, g = run.time_s.tolist(), list(run.gyro_rad_s)
    params = StrapdownParams()

    def one_pass():
        st = strapdown_init(np.array([1.0, 0.0, 0.0, 0.0]))
        for k in range(len(t)):
            st, _ = strapdown_step(st, g[k], t[k], params)
    return one_pass


def _in_flight_rates(run):
    """Bias-corrected rates as the Pipeline propagates them (the bias: the first 200 samples' mean)."""
    g = np.ascontiguousarray(run.gyro_rad_s - run.gyro_rad_s[:200].mean(axis=0))
    return run.time_s.copy(), g


def case_strapdown_core_held(run, items):
    """The Pipeline's hot path: the state held in the core, one call per sample."""
    from estimators.core import strapdown_step_held
    from estimators.strapdown import StrapdownParams, strapdown_init
    t, g = _in_flight_rates(run)
    t, g, params = t.tolist(), list(g), StrapdownParams()

    def one_pass():
        st = strapdown_init(np.array([1.0, 0.0, 0.0, 0.0]))
        for k in range(len(t)):
            st, _ = strapdown_step_held(st, g[k], t[k], params)
    return one_pass


def case_strapdown_core_batch(run, items):
    """The batch API: the whole stream's (N, 3) rates in one call."""
    from estimators.core import strapdown_propagate
    from estimators.strapdown import StrapdownParams, strapdown_init
    t, g = _in_flight_rates(run)

    def one_pass():
        strapdown_propagate(strapdown_init(np.array([1.0, 0.0, 0.0, 0.0])), g, t, StrapdownParams())
    return one_pass


def _levelling_per_sample(run, step):
    from estimators.levelling import LevellingState
    t, g, a = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2)

    def one_pass():
        st = LevellingState()
        for k in range(len(t)):
            st = step(st, g[k], a[k], t[k])
    return one_pass


def case_levelling(run, items):
    from estimators.levelling import levelling_step
    return _levelling_per_sample(run, levelling_step)


def case_levelling_core_step(run, items):
    """The per-sample drop-in (state packed and unpacked every call: why it is not wired)."""
    from estimators.core import levelling_step
    return _levelling_per_sample(run, levelling_step)


def case_levelling_core_batch(run, items):
    from estimators.core import levelling_accumulate
    from estimators.levelling import LevellingState
    t, g, a = run.time_s, np.ascontiguousarray(run.gyro_rad_s), np.ascontiguousarray(run.accel_m_s2)

    def one_pass():
        levelling_accumulate(LevellingState(), g, a, t)
    return one_pass


def _launch_index(run) -> int:
    """First IMU sample after launch as the daemon's phase detector sees it."""
    from service.phases import LAUNCH, PhaseParams, PhaseState, phase_step
    st = PhaseState()
    for k, (t, g, a) in enumerate(zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2)):
        st, _ = phase_step(st, g, a, t, PhaseParams())
        if st.phase == LAUNCH:
            return k, st.launch_time_s
    raise RuntimeError("no launch detected in the stream")


def case_azimuth(run, items):
    from estimators.azimuth import (AzimuthParams, azimuth_init, azimuth_launch, azimuth_prelaunch_step,
                                    azimuth_step)
    from estimators.geomag import earth_field_ned_gauss
    s = run.site
    e = earth_field_ned_gauss(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"])
    params = AzimuthParams(e_ned_gauss=e, launch_case="inclined",
                           launcher_elevation_rad=math.radians(s["launcher_elevation_deg"]))
    t, g, a, m = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2), list(run.mag_gauss)

    k_launch, t_launch = _launch_index(run)

    def one_pass():
        st = azimuth_init(params)
        for k in range(k_launch):
            st = azimuth_prelaunch_step(st, g[k], a[k], t[k])
        st, _ = azimuth_launch(st, t_launch)
        for k in range(k_launch, len(t)):
            st, _ = azimuth_step(st, g[k], a[k], m[k], t[k])
    return one_pass


_RESOLVES: dict = {}
"""What the re-solve cases timed: {"n": re-solves per pass, "n_imu": IMU samples of the stream}."""


def _recorded_resolves(run, items) -> list:
    """(state, time) of every re-solve the core Pipeline hands its solver on the stream (not timed)."""
    from service.solver import InlineSolver
    seen = []

    class Recording(InlineSolver):
        def submit(self, state, time_s, *kernels):
            seen.append((state, time_s))
            return super().submit(state, time_s, *kernels)

    from bench.sitl import feed_pipeline
    from service.pipeline import Pipeline
    for _ in feed_pipeline(Pipeline(site_config(run), solver=Recording()), items):
        pass
    _RESOLVES.update(n=len(seen), n_imu=len(run.time_s))
    return seen


def _resolve_case(fit_name: str):
    """Method A's re-solves (estimators.azimuth.azimuth_solve) of the states the Pipeline solved on this
    stream, with the reference's fit and diversity (estimators.azimuth_fit) or the core's (estimators.core);
    reported per IMU sample of the stream (the JSON also has ms per re-solve)."""
    def factory(run, items):
        from estimators import azimuth_fit, core
        from estimators.azimuth import azimuth_solve
        kernels = (core.fit_psi, core.orientation_diversity_rad) if fit_name == "core" else \
            (azimuth_fit.fit_psi, azimuth_fit.orientation_diversity_rad)
        if fit_name == "core" and not (core.FIT_AVAILABLE and core.DIVERSITY_AVAILABLE):
            raise RuntimeError("compiled core without method A's re-solve")
        states = _recorded_resolves(run, items)

        def one_pass():
            for st, t in states:
                azimuth_solve(st, t, *kernels)
        return one_pass
    return factory


case_resolve_python = _resolve_case("python")
case_resolve_core = _resolve_case("core")


def _deviation_case(backend: str):
    """Method D as the Pipeline calls it with D applied and learning: per IMU sample its coverage, the
    corrected field and the residual sigma; at 10 Hz an RLS step (heading, roll and pitch sweep)."""
    def factory(run, items):
        from estimators import core
        from estimators import mag_deviation as dv
        fns = (core.deviation_step, core.corrected_mag, core.residual_sigma_gauss, core.deviation_coverage) \
            if backend == "core" else (dv.deviation_step, dv.corrected_mag, dv.residual_sigma_gauss,
                                       dv.deviation_coverage)
        if backend == "core" and not core.DEVIATION_AVAILABLE:
            raise RuntimeError("compiled core without method D's RLS")
        step, corrected, sigma, coverage = fns
        params = dv.DeviationParams()
        field = np.array([0.21, 0.01, 0.43])
        m = list(run.mag_gauss)
        every = max(1, int(round(RATE_HZ / 10.0)))

        def one_pass():
            st = dv.deviation_init(params)
            for k, mk in enumerate(m):
                psi, roll, pitch = 0.01 * k % 6.283, 0.4 * math.sin(1e-3 * k), 0.3 * math.sin(7e-4 * k)
                if k % every == 0:
                    st, _ = step(st, mk, field, psi, roll, pitch, params)
                coverage(st, params)
                corrected(st, mk, psi, roll, pitch)
                sigma(st)
        return one_pass
    return factory


case_deviation_python = _deviation_case("python")
case_deviation_core = _deviation_case("core")


def b_events(items) -> list:
    """Method B's events from the link's items, as the Pipeline hands them over (IMU, air data, FC attitude)."""
    from estimators.synthetic_ahrs import AirEvent, FcAttitudeEvent, ImuEvent
    from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
    events = []
    for it in items:
        c = type(it)
        if c is ImuSample:
            events.append(ImuEvent(it.time_fc_s, it.gyro_rad_s, it.mag_gauss))
        elif c is PressureSample:
            events.append(AirEvent(it.time_fc_s, it.press_abs_pa, it.press_diff_pa, it.temperature_k))
        elif c is FcAttitude:
            events.append(FcAttitudeEvent(it.time_fc_s, np.array([it.roll_rad, it.pitch_rad, it.yaw_rad])))
    return events


def case_synthetic_ahrs(run, items):
    from estimators.synthetic_ahrs import SyntheticAhrs, synthetic_ahrs_params_for_site
    s = run.site
    params = synthetic_ahrs_params_for_site(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"])
    events = b_events(items)

    def one_pass():
        f = SyntheticAhrs(params)
        for ev in events:
            f.step(ev)
    return one_pass


def case_polar_attitude(run, items):
    from estimators.polar_attitude import polar_attitude_init, polar_attitude_step
    t, g, a = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2)

    def one_pass():
        st = polar_attitude_init()
        for k in range(len(t)):
            st, _ = polar_attitude_step(st, t[k], g[k], a[k])
    return one_pass


def case_polar_attitude_core(run, items):
    from estimators import core
    t, g, a = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2)

    def one_pass():
        st = core.polar_attitude_init()
        for k in range(len(t)):
            st, _ = core.polar_attitude_step(st, t[k], g[k], a[k])
    return one_pass


def _heading_inputs(run) -> list:
    """Method C's heading filter's inputs per IMU sample, as the Pipeline builds them (the platform
    formulation: the attitude filter's roll/pitch, covariance and attitude; the magnetometer with the
    site's declination, gated to mag_update_period_s by the filter): made once, not timed."""
    from estimators import core
    from estimators import polar_attitude as pa
    from estimators.geomag import earth_field_ned_gauss
    from estimators.polar_heading import HeadingInputs
    s = run.site
    e = earth_field_ned_gauss(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"])
    decl = math.atan2(e[1], e[0])
    m = core if core.POLAR_AVAILABLE else pa
    st = m.polar_attitude_init()
    out = []
    for t, g, a, mg in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss):
        st, _ = m.polar_attitude_step(st, t, g, a)
        att = m.polar_attitude_estimate(st)
        if att is None:
            continue
        out.append(HeadingInputs(t, g, att.roll_rad, att.pitch_rad, att.cov_roll_pitch_rad2, mg, decl, 0.01, None,
                                 att.q_P_from_body, st.P[0:3, 0:3], att.gyro_bias_rad_s, False))
    return out


def case_polar_heading(run, items):
    from estimators.polar_heading import polar_heading_init, polar_heading_step
    us = _heading_inputs(run)

    def one_pass():
        st = polar_heading_init()
        for u in us:
            st, _ = polar_heading_step(st, u)
    return one_pass


def case_polar_heading_core(run, items):
    from estimators import core
    us = _heading_inputs(run)

    def one_pass():
        st = core.polar_heading_init()
        for u in us:
            st, _ = core.polar_heading_step(st, u)
    return one_pass


def case_air_data(run, items):
    """Per pressure sample (50 Hz), reported per IMU sample of the same stream."""
    from estimators.air_data import air_data_init, air_data_step
    rows = list(zip(run.press_abs_pa.tolist(), run.press_diff_pa.tolist(), run.temperature_k.tolist(),
                    run.baro_time_s.tolist()))

    def one_pass():
        st = air_data_init()
        for p, d, k, t in rows:
            st, _ = air_data_step(st, p, d, k, t)
    return one_pass


def case_imufusion(run, items):
    import imufusion
    g = np.degrees(run.gyro_rad_s)
    a = run.accel_m_s2 / -9.80665  # Fusion: accelerometer in g, +1 g up at rest (= -f/g0 in FRD)
    m = run.mag_gauss * 100.0      # any unit: uT
    dt = 1.0 / RATE_HZ
    rows = [(g[k], a[k], m[k]) for k in range(len(g))]

    def one_pass():
        f = imufusion.Ahrs()
        if hasattr(f, "set_sample_period"):  # imufusion >= 1.3: period set once, update(g, a, m)
            f.set_sample_period(dt)
            for gk, ak, mk in rows:
                f.update(gk, ak, mk)
        else:
            for gk, ak, mk in rows:
                f.update(gk, ak, mk, dt)
    return one_pass


def case_vqf(run, items):
    from vqf import VQF
    g = np.ascontiguousarray(run.gyro_rad_s)
    a = np.ascontiguousarray(-run.accel_m_s2)
    m = np.ascontiguousarray(run.mag_gauss)
    rows = [(np.ascontiguousarray(g[k]), np.ascontiguousarray(a[k]), np.ascontiguousarray(m[k])) for k in range(len(g))]

    def one_pass():
        f = VQF(1.0 / RATE_HZ)
        for gk, ak, mk in rows:
            f.update(gk, ak, mk)
    return one_pass


def case_ahrs_madgwick(run, items):
    from ahrs.filters import Madgwick
    rows = [(run.gyro_rad_s[k], -run.accel_m_s2[k], run.mag_gauss[k] * 1e5) for k in range(len(run.time_s))]

    def one_pass():
        f = Madgwick(frequency=RATE_HZ)
        q = np.array([1.0, 0.0, 0.0, 0.0])
        for gk, ak, mk in rows:
            q = f.updateMARG(q, gk, ak, mk)
    return one_pass


def case_ahrs_ekf(run, items):
    from ahrs.filters import EKF
    rows = [(run.gyro_rad_s[k], -run.accel_m_s2[k], run.mag_gauss[k] * 1e5) for k in range(len(run.time_s))]

    g2, a2, m2 = (np.array([r[i] for r in rows[:2]]) for i in range(3))

    def one_pass():
        # built on two samples: that is how ahrs' EKF learns it runs with a magnetometer (MARG)
        f = EKF(gyr=g2, acc=a2, mag=m2, frequency=RATE_HZ, frame="NED", magnetic_ref=63.0)
        q = np.array([1.0, 0.0, 0.0, 0.0])
        for gk, ak, mk in rows:
            q = f.update(q, gk, ak, mk)
    return one_pass


CASES = [
    ("azimuthd whole stack (service.pipeline.Pipeline)", "ours", case_pipeline),
    ("whole stack, Python reference (AZIMUTHD_CORE=python)", "ours", case_pipeline_python),
    ("whole stack, core, batch path (on_imu_batch, hot path)", "ours", case_pipeline_batch),
    ("whole stack, core, batch path, 1 row per batch (the daemon)", "ours", case_pipeline_batch1),
    ("whole stack, core, message path (step_imu, the daemon's default)", "ours", case_pipeline_step),
    ("phases: levelling + launch detection", "ours", case_phases),
    ("phases, core, per sample (held state)", "ours", case_phases_core),
    ("strapdown (estimators.strapdown)", "ours", case_strapdown),
    ("strapdown, core, per sample (held state)", "ours", case_strapdown_core_held),
    ("strapdown, core, batch (N x 3 array)", "ours", case_strapdown_core_batch),
    ("rest accumulator (estimators.levelling)", "ours", case_levelling),
    ("rest accumulator, core, per-sample drop-in", "ours", case_levelling_core_step),
    ("rest accumulator, core, batch (N x 3 arrays)", "ours", case_levelling_core_batch),
    ("method A azimuth (estimators.azimuth)", "ours", case_azimuth),
    ("method A re-solves (estimators.azimuth_fit.fit_psi)", "ours", case_resolve_python),
    ("method A re-solves, core (estimators.core.fit_psi)", "ours", case_resolve_core),
    ("method D deviation (estimators.mag_deviation)", "ours", case_deviation_python),
    ("method D deviation, core (held state)", "ours", case_deviation_core),
    ("method B synthetic AHRS (estimators.synthetic_ahrs)", "ours", case_synthetic_ahrs),
    ("polar attitude (estimators.polar_attitude)", "ours", case_polar_attitude),
    ("polar attitude, core, per sample (held state)", "ours", case_polar_attitude_core),
    ("polar heading (estimators.polar_heading)", "ours", case_polar_heading),
    ("polar heading, core, per sample (held state)", "ours", case_polar_heading_core),
    ("air data, per IMU sample (estimators.air_data)", "ours", case_air_data),
    ("imufusion Ahrs (x-io Fusion, C)", "imufusion", case_imufusion),
    ("vqf VQF (C++)", "vqf", case_vqf),
    ("ahrs Madgwick MARG (numpy)", "ahrs", case_ahrs_madgwick),
    ("ahrs EKF (numpy)", "ahrs", case_ahrs_ekf),
]


def time_case(factory, run, items, n_imu: int, budget_s: float) -> dict:
    try:
        one_pass = factory(run, items)
    except Exception as exc:  # noqa: BLE001 - an estimator whose API moved: reported, not fatal
        return {"error": f"setup: {type(exc).__name__}: {exc}"}
    best = math.inf
    passes = 0
    t_start = time.perf_counter()
    while passes < 3:
        try:
            t0 = time.process_time()
            w0 = time.perf_counter()
            one_pass()
            cpu = time.process_time() - t0
            wall = time.perf_counter() - w0
        except Exception as exc:  # noqa: BLE001
            return {"error": f"run: {type(exc).__name__}: {exc}"}
        passes += 1
        # process CPU time: other users of this shared machine do not count against us
        best = min(best, cpu if cpu > 0 else wall)
        if time.perf_counter() - t_start > budget_s:
            break
    return {"us_per_imu_sample": 1e6 * best / n_imu, "passes": passes}


# --- latency and CPU through two processes -------------------------------------------------------

def match_latency_ms(imu_fwd, att_rx, per_message: bool = False) -> tuple[np.ndarray, int]:
    """RAW_IMU -> ATTITUDE latencies (ms) and the number of ATTITUDE left unmatched. ``imu_fwd``:
    (time_usec, tap forward monotonic s) of every RAW_IMU forwarded to the daemon; ``att_rx``:
    (time_boot_ms, tap receive monotonic s) of the daemon's ATTITUDE. An ATTITUDE is matched by FC
    time to the one RAW_IMU within 1 ms of its time_boot_ms. ``per_message``: one latency per
    ATTITUDE in ``att_rx``'s order, NaN where unmatched."""
    imu_us = np.array([u for u, _ in imu_fwd], dtype=np.int64)
    imu_t = np.array([t for _, t in imu_fwd], dtype=float)
    order = np.argsort(imu_us, kind="stable")
    imu_us, imu_t = imu_us[order], imu_t[order]
    lat = []
    unmatched = 0
    for ms, t_rx in att_rx:
        # time_boot_ms is the sample's FC time truncated or rounded to ms (int(3.24 * 1000) is
        # 3239): the sample is within 1 ms of it, and at 400 Hz (2.5 ms) only one sample can be
        lo = np.searchsorted(imu_us, ms * 1000 - 1000, side="left")
        hi = np.searchsorted(imu_us, ms * 1000 + 1000, side="right")
        if hi - lo != 1:
            unmatched += 1
            if per_message:
                lat.append(math.nan)
            continue
        lat.append(t_rx - imu_t[lo])
    return np.array(lat, dtype=float) * 1e3, unmatched


def sitl_latency_cpu(quick: bool, profile_out: str | None = None, raw: dict | None = None,
                     rt_priority: int = 0, imu_batch: bool = False) -> dict:
    import tempfile

    import psutil

    from bench.sitl import Sitl, unit_nice

    window_s = 12.0 if quick else 30.0
    rest_s = 6.0
    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-speed-"))
    scen_text = (ROOT / "sim" / "scenarios" / "inclined_rail.toml").read_text()
    scen_text = scen_text.replace("rest_s = 60.0", f"rest_s = {rest_s}")
    scenario = workdir / "inclined_rail_short_rest.toml"
    scenario.write_text(scen_text)
    # the tap timestamps every RAW_IMU it forwards to the daemon and every message the daemon sends
    # back, on one monotonic clock in one thread
    sitl = Sitl(scenario=str(scenario), speed=1.0, workdir=workdir,
                config_overrides={"mavlink": {"imu_rate_hz": RATE_HZ, "imu_batch": bool(imu_batch)}}, tap=True,
                tap_record_to_daemon=("RAW_IMU",), daemon_own_session=True,
                daemon_group_nice=unit_nice() if os.geteuid() == 0 else None)
    if profile_out:
        # the daemon under cProfile with a CPU-time clock (waiting in select and being preempted by
        # other processes on this shared machine do not count)
        i = sitl.daemon_cmd.index("-m")
        code = ("import cProfile, sys, time; from service.cli import main; "
                "p = cProfile.Profile(time.process_time); p.enable(); rc = main(sys.argv[1:]); "
                f"p.disable(); p.dump_stats({str(profile_out)!r}); sys.exit(rc)")
        sitl.daemon_cmd[i:i + 2] = ["-c", code]
    tap = sitl.tap
    out: dict = {"window_s": window_s, "rate_hz": RATE_HZ, "attitude_out_hz": 50.0,
                 "imu_path": "batch (ImuBatch)" if imu_batch else "message (ImuSample)",
                 "daemon_group_nice": sitl.daemon_group_nice}
    with sitl:
        if rt_priority > 0:
            # what a unit file can grant the daemon (CPUSchedulingPolicy=fifo): not preempted by
            # the other users of a shared machine; the tap (this process) too, so it timestamps
            # promptly. Both sleep in select() between packets.
            param = os.sched_param(rt_priority)
            for pid in (sitl.daemon.pid, os.getpid()):
                os.sched_setscheduler(pid, os.SCHED_FIFO, param)
            out["sched"] = f"SCHED_FIFO {rt_priority} (daemon and tap)"
        else:
            out["sched"] = "SCHED_OTHER (default)"
        if not sitl.wait_for(lambda: len(tap.sent_by_daemon("ATTITUDE")) > 20, 60.0):
            raise RuntimeError(f"the daemon sent no ATTITUDE within 60 s; see {workdir}")
        dproc, sproc = psutil.Process(sitl.daemon.pid), psutil.Process(sitl.sim.pid)
        d0, s0, w0 = dproc.cpu_times(), sproc.cpu_times(), time.monotonic()
        n_imu0 = len(tap.to_daemon)
        time.sleep(window_s)
        d1, s1, w1 = dproc.cpu_times(), sproc.cpu_times(), time.monotonic()
        n_imu1 = len(tap.to_daemon)
        out["load_avg_1min"] = os.getloadavg()[0]
        wall = w1 - w0
        out["daemon_cpu_pct"] = 100.0 * ((d1.user - d0.user) + (d1.system - d0.system)) / wall
        out["sim_cpu_pct"] = 100.0 * ((s1.user - s0.user) + (s1.system - s0.system)) / wall
        out["imu_rate_received_hz"] = (n_imu1 - n_imu0) / wall
    imu_fwd = [(m.time_usec, t) for t, m in tap.to_daemon]   # (time_usec, forward monotonic s)
    att_rx = [(m.time_boot_ms, t) for t, m in tap.from_daemon if m.get_type() == "ATTITUDE"]  # (.., receive s)
    lat_ms, unmatched = match_latency_ms(imu_fwd, att_rx)
    if raw is not None:
        raw.update(imu_fwd=imu_fwd, att_rx=att_rx, workdir=str(workdir))
    out.update({"attitude_matched": int(lat_ms.size), "attitude_unmatched": unmatched,
                "raw_imu_forwarded": len(imu_fwd)})
    if lat_ms.size:
        out.update({"latency_p50_ms": float(np.percentile(lat_ms, 50)),
                    "latency_p99_ms": float(np.percentile(lat_ms, 99)),
                    "latency_max_ms": float(lat_ms.max()),
                    "latency_min_ms": float(lat_ms.min())})
    return out


def harness_floor(seconds: float, rt_priority: int = 0) -> dict:
    """Latency floor of the measurement itself on this machine: a UDP datagram every 2.5 ms to a
    trivial Python echo process and back (two loopback hops + waking a Python process), timed by
    the same kind of thread as the tap. What is left of the SITL latency above this is the daemon."""
    import socket
    import threading
    code = ("import socket, sys; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); "
            "s.bind(('127.0.0.1', 0)); print(s.getsockname()[1], flush=True)\n"
            "while True:\n    d, a = s.recvfrom(2048)\n    s.sendto(d, a)")
    echo = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        port = int(echo.stdout.readline())
        if rt_priority > 0:
            os.sched_setscheduler(echo.pid, os.SCHED_FIFO, os.sched_param(rt_priority))
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sent: dict[int, float] = {}
        rtt: list[float] = []
        stop = threading.Event()

        def rx():
            sock.settimeout(0.2)
            while not stop.is_set():
                try:
                    d, _ = sock.recvfrom(2048)
                except (TimeoutError, socket.timeout):
                    continue
                now = time.monotonic()
                k = int.from_bytes(d[:4], "little")
                if k in sent:
                    rtt.append(now - sent.pop(k))
        th = threading.Thread(target=rx, daemon=True)
        th.start()
        payload = bytes(40)  # a RAW_IMU frame's size
        n = int(seconds * RATE_HZ)
        t_next = time.monotonic()
        for k in range(n):
            t_next += 1.0 / RATE_HZ
            sent[k] = time.monotonic()
            sock.sendto(k.to_bytes(4, "little") + payload, ("127.0.0.1", port))
            time.sleep(max(0.0, t_next - time.monotonic()))
        time.sleep(0.2)
        stop.set()
        th.join(1.0)
        sock.close()
    finally:
        echo.kill()
        echo.wait(5)
    r = np.array(rtt) * 1e3
    return {"echo_samples": int(r.size), "echo_lost": n - int(r.size),
            "floor_p50_ms": float(np.percentile(r, 50)) if r.size else math.nan,
            "floor_p99_ms": float(np.percentile(r, 99)) if r.size else math.nan}


def ported_figures(rows: list[dict]) -> dict:
    """The ported parts and the whole stack, core against the Python reference (issue 19 item 2):
    per-sample costs and speed-ups (x = reference / core), measured in the same run."""
    us = {r["case"]: r.get("us_per_imu_sample", math.nan) for r in rows}
    pick = {
        "strapdown_python_us_per_sample": "strapdown (estimators.strapdown)",
        "strapdown_core_held_us_per_sample": "strapdown, core, per sample (held state)",
        "strapdown_core_batch_us_per_sample": "strapdown, core, batch (N x 3 array)",
        "levelling_python_us_per_sample": "rest accumulator (estimators.levelling)",
        "levelling_core_step_us_per_sample": "rest accumulator, core, per-sample drop-in",
        "levelling_core_batch_us_per_sample": "rest accumulator, core, batch (N x 3 arrays)",
        "polar_attitude_python_us_per_sample": "polar attitude (estimators.polar_attitude)",
        "polar_attitude_core_held_us_per_sample": "polar attitude, core, per sample (held state)",
        "polar_heading_python_us_per_sample": "polar heading (estimators.polar_heading)",
        "polar_heading_core_held_us_per_sample": "polar heading, core, per sample (held state)",
        "phases_python_us_per_sample": "phases: levelling + launch detection",
        "phases_core_held_us_per_sample": "phases, core, per sample (held state)",
        "azimuth_fit_python_us_per_sample": "method A re-solves (estimators.azimuth_fit.fit_psi)",
        "azimuth_fit_core_held_us_per_sample": "method A re-solves, core (estimators.core.fit_psi)",
        "deviation_python_us_per_sample": "method D deviation (estimators.mag_deviation)",
        "deviation_core_held_us_per_sample": "method D deviation, core (held state)",
    }
    out = {k: us.get(v, math.nan) for k, v in pick.items()}
    if _RESOLVES.get("n"):   # per re-solve (ms): the cost a worker process or an inline solve pays at once
        for form in ("python", "core_held"):
            out[f"azimuth_fit_{form}_ms_per_resolve"] = \
                out[f"azimuth_fit_{form}_us_per_sample"] * _RESOLVES["n_imu"] / _RESOLVES["n"] / 1e3
        out["azimuth_fit_resolves"] = _RESOLVES["n"]
    for part in ("strapdown", "levelling", "polar_attitude", "polar_heading", "phases", "azimuth_fit", "deviation"):
        base = out[f"{part}_python_us_per_sample"]
        for form in ("core_held", "core_step", "core_batch"):
            k = f"{part}_{form}_us_per_sample"
            if k in out:
                out[f"{part}_{form}_speedup_x"] = base / out[k] if out[k] > 0 else math.nan
    stack_core = us.get("azimuthd whole stack (service.pipeline.Pipeline)", math.nan)
    stack_py = us.get("whole stack, Python reference (AZIMUTHD_CORE=python)", math.nan)
    out["stack_core_us_per_imu_sample"] = stack_core
    out["stack_python_reference_us_per_imu_sample"] = stack_py
    out["stack_core_speedup_x"] = stack_py / stack_core if stack_core > 0 else math.nan
    stack_batch = us.get("whole stack, core, batch path (on_imu_batch, hot path)", math.nan)
    out["stack_core_batch_us_per_imu_sample"] = stack_batch
    out["stack_core_batch_speedup_x"] = stack_py / stack_batch if stack_batch > 0 else math.nan
    stack_batch1 = us.get("whole stack, core, batch path, 1 row per batch (the daemon)", math.nan)
    out["stack_core_batch1_us_per_imu_sample"] = stack_batch1
    out["stack_core_batch1_speedup_x"] = stack_py / stack_batch1 if stack_batch1 > 0 else math.nan
    stack_step = us.get("whole stack, core, message path (step_imu, the daemon's default)", math.nan)
    out["stack_core_step_imu_us_per_imu_sample"] = stack_step
    out["stack_core_step_imu_speedup_x"] = stack_py / stack_step if stack_step > 0 else math.nan
    return {"ported": out, "stack_python_reference_us_per_imu_sample": stack_py}


# --- busy: the daemon beside competing CPU-bound processes (issue 19 item 5) -------------------

BUSY_COMPETITORS = 2
FC_GROUP_NICE = -15
"""CPU-group nice of the simulator and the tap (the FC and its wire) in the busy run, as
bench/geofence.py and bench/daemon_cpu.py run them: a real FC has a CPU of its own, so the
competitors' load must fall on the companion computer's side (the daemon), not on the FC's stand-in."""
BUSY_DRAIN_S = 120.0
"""After the simulator stopped, at most this long for the tap and the daemon to read what is queued
for them (what is still queued then is counted, as left in the socket)."""
BUSY_ATTITUDE_RATE_TOLERANCE = 0.01
"""'ATTITUDE at the configured rate': the rate received over the window within 1 % of
[outputs] attitude_hz (600 s at 50 Hz: at most 300 of 30,000 missing)."""
BUSY_IMU_TYPES = ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU")
"""The IMU messages the daemon's link counts as ``imu_messages`` (service/daemon.py close())."""
TAP_RCVBUF_BYTES = 4 * 1024 * 1024
"""The tap's receive buffer: as the daemon's (mavlink_io/transport.py), so the harness does not
overflow before the daemon would."""


class Competitors:
    """``n`` CPU-bound busy loops (``while True: pass``), each a process in a session of its own,
    at nice 0, the same user as the bench; killed on exit.

    Why this is the fair "other work" of a companion computer: there, video, mavlink-router or a
    mission computer run as other systemd services, each in a cgroup of its own at the default
    weight (CPUWeight=100, Nice=0). A session of its own is, with the kernel's autogroup
    scheduling, a CPU group of its own at nice 0: the same standing against the daemon's group
    as another service's cgroup against the unit's (CPUWeight=1000 / Nice=-10; the bench gives the
    daemon's group the unit's Nice=, bench/sitl.py unit_nice). Two of them on the 2-core machine
    want both cores all the time. Put in the daemon's own group they would be the daemon's own
    work, which no other service is; at a nice above 0 or as another user they would be weaker
    than the default service the unit must hold its own against."""

    def __init__(self, n: int):
        if n < 0:
            raise ValueError(f"competitors must be >= 0, got {n}")
        self.n, self.procs = n, []

    @staticmethod
    def _nice0() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, 0)  # from a bench run under `nice -n 10`: needs root
        except OSError:
            pass

    def __enter__(self) -> "Competitors":
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True,
                                       preexec_fn=self._nice0) for _ in range(self.n)]
        return self

    def cpu_s(self) -> list[float]:
        import psutil
        out = []
        for p in self.procs:
            c = psutil.Process(p.pid).cpu_times()
            out.append(c.user + c.system)
        return out

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait(10)


def _autogroup(pid: int) -> str | None:
    """/proc/PID/autogroup ("/autogroup-N nice X"): the CPU group a process is scheduled in."""
    try:
        return Path(f"/proc/{pid}/autogroup").read_text().strip()
    except OSError:
        return None


def _proc_tree_cpu_s(pid: int) -> dict[int, float]:
    """CPU seconds (user + system) of a process and its descendants (the daemon's solver worker), by pid."""
    import psutil
    out = {}
    try:
        root = psutil.Process(pid)
        for p in [root, *root.children(recursive=True)]:
            try:
                c = p.cpu_times()
                out[p.pid] = c.user + c.system
            except psutil.Error:
                pass
    except psutil.Error:
        pass
    return out


def _own_cpu_s() -> float:
    """CPU seconds of this process alone (the tap's and the listener's threads, the bench's loop)."""
    t = os.times()
    return t.user + t.system


def _take(lst: list) -> list:
    """Remove and return what a list holds now, while another thread appends to it (the tap):
    ``del lst[:n]`` removes only the first n, under the GIL each step is atomic."""
    n = len(lst)
    out = lst[:n]
    del lst[:n]
    return out


def stopped_counts(log_text: str) -> dict[str, int]:
    """The integer fields of the daemon's last "stopped" log line (service/daemon.py close())."""
    import re
    line = next((ln for ln in reversed(log_text.splitlines()) if "msg=stopped" in ln), None)
    if line is None:
        return {}
    return {k: int(v) for k, v in re.findall(r"\b([a-z_]+)=(-?\d+)\b", line)}


def sim_sent_counts(log_text: str) -> tuple[dict[str, int] | None, dict]:
    """What the simulator sent, by message type, and its achieved speed, from its "sim stopped" line
    (sim/cli.py): its own count, independent of the daemon's and the tap's."""
    import re
    m = re.search(r"sim stopped: simulated_s=([0-9.]+) wall_s=([0-9.]+) achieved_speed=([0-9.naN]+) sent=(\{.*\})",
                  log_text)
    if not m:
        return None, {}
    return json.loads(m.group(4)), {"simulated_s": float(m.group(1)), "wall_s": float(m.group(2)),
                                    "achieved_speed": float(m.group(3))}


def busy_accounting(sim_sent: dict, tap: dict, tap_socket_drops: int, daemon: dict,
                    daemon_socket_drops: int, daemon_socket_left_bytes: int = 0) -> dict:
    """Where IMU samples were lost between the simulator's send and the estimators, each part named,
    and whether the independent observers agree.

    Observers: the simulator's own send count by type (``sim_sent``); the tap between it and the
    daemon (``tap``: ``received_by_type``, ``forwarded_by_type``, ``dropped_on_purpose``,
    ``forwarded_before_heartbeat``, ``forwarded_datagrams``); the kernel, read by the bench from
    /proc/net/udp for the tap's and the daemon's sockets (``*_socket_drops``: datagrams dropped on a
    full receive buffer; ``daemon_socket_left_bytes``: still queued when the daemon was stopped); the
    daemon's own counters (``daemon``: its "stopped" line: imu_messages, imu_samples, imu_rejected,
    link_seq_lost, kernel_rx_drops, link_messages_received, link_foreign).

    IMU samples (RAW_IMU, HIGHRES_IMU, SCALED_IMU), counted from the FC's first HEARTBEAT on (before
    it the daemon does not know its FC and ignores everything as foreign, by design: reported as
    ``ignored_before_fc_heartbeat``, not as lost):
      tap_socket_kernel       sent by the simulator, never read by the tap (harness)
      tap_dropped_on_purpose  dropped by the tap because it was told to (harness)
      daemon_socket_kernel    forwarded to the daemon, never accepted by its link (its socket's
                              kernel drops, or left queued at its stop)
      daemon_read_not_processed  accepted by its link, not taken by its estimators
                              (pipeline_rejected: the input checks; link_dropped: stale FC time,
                              non-finite fields, or an input the daemon dropped on an internal
                              fault: its count over all inputs is given beside)
    ``samples_lost`` is their sum (= sent - ignored before the heartbeat - processed);
    ``daemon_samples_lost`` the daemon's two. Cross-checks over all messages (one per datagram):
    simulator sent == tap read + tap socket drops; tap forwarded == daemon read + daemon socket
    drops (with datagrams left queued at the daemon's stop: forwarded > that); the daemon's kernel counter == the bench's; the daemon's sequence gaps ==
    every datagram lost after the first HEARTBEAT; the daemon's foreign count == what the tap
    forwarded before the first HEARTBEAT. Where the daemon's sequence count is short of the datagrams
    lost and its socket overflowed, the check passes with a note (the 8-bit sequence cannot measure
    a run of 128 or more dropped at a full socket; the kernel counter is exact)."""
    def imu(d: dict | None) -> int:
        return sum(int((d or {}).get(k, 0)) for k in BUSY_IMU_TYPES)

    sent = imu(sim_sent)
    reached_tap = imu(tap["received_by_type"])
    on_purpose = imu(tap["dropped_on_purpose"])
    forwarded = imu(tap["forwarded_by_type"])
    before_hb = imu(tap["forwarded_before_heartbeat"])
    accepted = int(daemon.get("imu_messages", 0))
    processed = int(daemon.get("imu_samples", 0))
    rejected = int(daemon.get("imu_rejected", 0))
    parts = {"tap_socket_kernel": sent - reached_tap, "tap_dropped_on_purpose": on_purpose,
             "daemon_socket_kernel": forwarded - before_hb - accepted,
             "daemon_read_not_processed": accepted - processed}
    harness = parts["tap_socket_kernel"] + parts["tap_dropped_on_purpose"]
    in_daemon = parts["daemon_socket_kernel"] + parts["daemon_read_not_processed"]
    all_sent = sum(int(v) for v in sim_sent.values())
    all_read_by_tap = sum(int(v) for v in tap["received_by_type"].values())
    all_on_purpose = sum(int(v) for v in tap["dropped_on_purpose"].values())
    all_before_hb = sum(int(v) for v in (tap["forwarded_before_heartbeat"] or {}).values())
    checks = {
        "simulator_sent_vs_tap_read_plus_tap_kernel_drops": (all_sent, all_read_by_tap + tap_socket_drops),
        "tap_forwarded_vs_daemon_read_plus_daemon_kernel_drops": (
            int(tap["forwarded_datagrams"]),
            int(daemon.get("link_messages_received", -1)) + daemon_socket_drops),
        "daemon_kernel_counter_vs_bench": (int(daemon.get("kernel_rx_drops", -1)), daemon_socket_drops),
        "daemon_sequence_gaps_vs_datagrams_lost": (int(daemon.get("link_seq_lost", -1)),
                                                   all_on_purpose + tap_socket_drops + daemon_socket_drops),
        "daemon_foreign_vs_tap_before_heartbeat": (int(daemon.get("link_foreign", -1)), all_before_hb),
    }
    agree = {k: a == b for k, (a, b) in checks.items()}
    notes = {}
    fwd = "tap_forwarded_vs_daemon_read_plus_daemon_kernel_drops"
    if daemon_socket_left_bytes > 0:  # still queued when the daemon stopped: forwarded, neither read nor dropped
        agree[fwd] = checks[fwd][0] > checks[fwd][1]
        notes[fwd] = f"{daemon_socket_left_bytes} bytes still queued at the daemon's stop"
    seq = "daemon_sequence_gaps_vs_datagrams_lost"
    seq_a, seq_b = checks[seq]
    if 0 <= seq_a < seq_b and daemon_socket_drops > 0 and agree["daemon_kernel_counter_vs_bench"]:
        # a full socket drops runs of datagrams; the 8-bit MAVLink sequence cannot measure a run of
        # 128 or more (mavlink_io.framing.SeqTracker counts it as reordered, modulo 256), so its
        # count is a lower bound there; the kernel's counter, which both the daemon and the bench
        # read, is the exact one
        agree[seq] = True
        notes[seq] = (f"lower bound: runs of >= 128 datagrams dropped at a full socket are beyond the 8-bit "
                      f"sequence (the daemon's kernel counter, {daemon_socket_drops}, agrees with the bench's)")
    disagree = [k for k, ok in agree.items() if not ok]
    return {"samples_sent": sent - before_hb, "samples_sent_total": sent,
            "ignored_before_fc_heartbeat": before_hb, "samples_processed": processed,
            "samples_lost": harness + in_daemon, "samples_lost_parts": parts,
            "samples_lost_harness": harness, "daemon_samples_lost": in_daemon,
            "daemon_read_not_processed_parts": {"pipeline_rejected": rejected,
                                                "link_dropped": accepted - processed - rejected,
                                                "internal_faults_any_input": int(daemon.get("internal_faults", 0))},
            "daemon_socket_left_bytes_at_stop": daemon_socket_left_bytes,
            "checks": {k: {"a": a, "b": b, "agree": agree[k], **({"note": notes[k]} if k in notes else {})}
                       for k, (a, b) in checks.items()},
            "observers_agree": not disagree}


def _short_rest_scenario(workdir: Path, rest_s: float = 6.0) -> Path:
    """inclined_rail with its rest shortened: pre-launch and flight both in a short run."""
    scen_text = (ROOT / "sim" / "scenarios" / "inclined_rail.toml").read_text()
    scenario = workdir / "inclined_rail_short_rest.toml"
    scenario.write_text(scen_text.replace("rest_s = 60.0", f"rest_s = {rest_s}"))
    return scenario


def busy_run(busy_s: float, competitors: int = BUSY_COMPETITORS, imu_batch: bool = False,
             daemon_group_nice: int | None = None, drop_imu_every: int = 0,
             start_timeout_s: float = 300.0, udp_rcvbuf_bytes: int | None = None) -> dict:
    """The daemon at 400 Hz (bench.sitl: simulator + tap + daemon as processes over loopback UDP, the
    daemon in a session of its own at ``daemon_group_nice``) beside ``competitors`` CPU-bound
    processes (:class:`Competitors`), started before the daemon and running until it stopped. The
    window (``busy_s``) starts once the daemon sends ATTITUDE; the loss accounting covers the whole
    run (:func:`busy_accounting`). ``drop_imu_every`` > 0: the tap drops every n-th IMU datagram on
    purpose (tests: the accounting must name exactly those). ``udp_rcvbuf_bytes``: the daemon's
    [mavlink] udp_rcvbuf_bytes (None: its default, 4 MiB; 212992 is what a machine with the kernel's
    default net.core.rmem_max grants). Returns the JSON ``busy`` dict."""
    import signal
    import tempfile
    from array import array

    import psutil

    from bench.sitl import Sitl, udp_socket_state
    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-speed-busy-"))
    drop = None
    if drop_imu_every > 0:
        n_imu = [0]

        def drop(msg_type: str) -> bool:
            if msg_type not in BUSY_IMU_TYPES:
                return False
            n_imu[0] += 1
            return n_imu[0] % drop_imu_every == 0
    mav = {"imu_rate_hz": RATE_HZ, "imu_batch": bool(imu_batch)}
    if udp_rcvbuf_bytes is not None:
        mav["udp_rcvbuf_bytes"] = int(udp_rcvbuf_bytes)
    sitl = Sitl(scenario=str(_short_rest_scenario(workdir)), speed=1.0, workdir=workdir,
                config_overrides={"mavlink": mav},
                sim_args=["--duration", "0"], tap=True, tap_record_to_daemon=BUSY_IMU_TYPES,
                tap_drop_to_daemon=drop, tap_rcvbuf_bytes=TAP_RCVBUF_BYTES,
                daemon_own_session=True, daemon_group_nice=daemon_group_nice)
    import tomllib
    with open(sitl.config_path, "rb") as f:
        cfg = tomllib.load(f)
    att_cfg_hz = float(cfg.get("outputs", {}).get("attitude_hz", 50.0))
    try:
        rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    except (OSError, ValueError):
        rmem_max = None
    asked = int(cfg["mavlink"].get("udp_rcvbuf_bytes", 4 * 1024 * 1024))
    tap = sitl.tap
    imu_us, imu_t = array("q"), array("d")     # every IMU sample forwarded: time_usec, forward time
    att_ms, att_t = array("q"), array("d")     # every ATTITUDE from the daemon: time_boot_ms, receive time
    from_daemon_by_type: dict[str, int] = {}

    def compact() -> None:
        for t, m in _take(tap.to_daemon):
            imu_us.append(int(m.time_usec))
            imu_t.append(t)
        for t, m in _take(tap.from_daemon):
            k = m.get_type()
            from_daemon_by_type[k] = from_daemon_by_type.get(k, 0) + 1
            if k == "ATTITUDE":
                att_ms.append(int(m.time_boot_ms))
                att_t.append(t)

    out: dict = {"busy_s": busy_s, "competitors": competitors, "rate_hz": RATE_HZ,
                 "attitude_rate_configured_hz": att_cfg_hz, "workdir": str(workdir),
                 "daemon_udp_rcvbuf_bytes_asked": asked, "net_core_rmem_max": rmem_max,
                 "daemon_udp_rcvbuf_bytes_effective": min(asked, rmem_max) if rmem_max else None,
                 "imu_path": "batch (ImuBatch)" if imu_batch else "message (ImuSample)"}
    loads: list[float] = []
    with Competitors(competitors) as comp:
        t_run0 = time.monotonic()
        with sitl:
            if not sitl.wait_for(lambda: len(tap.sent_by_daemon("ATTITUDE")) > 20, start_timeout_s):
                raise RuntimeError(f"the daemon sent no ATTITUDE within {start_timeout_s:.0f} s; see {workdir}")
            out["start_to_attitude_s"] = time.monotonic() - t_run0
            d0, s0, h0, m0 = (_proc_tree_cpu_s(sitl.daemon.pid), _proc_tree_cpu_s(sitl.sim.pid), comp.cpu_s(),
                              _own_cpu_s())
            compact()
            n_att0 = len(att_t)
            w0 = time.monotonic()
            while time.monotonic() - w0 < busy_s:
                time.sleep(min(1.0, max(0.0, busy_s - (time.monotonic() - w0))))
                compact()
                loads.append(os.getloadavg()[0])
                for p, name in ((sitl.sim, "simulator"), (sitl.daemon, "daemon")):
                    if p.poll() is not None:
                        raise RuntimeError(f"the {name} exited with {p.returncode} during the window; see {workdir}")
            w1 = time.monotonic()
            d1, s1, h1, m1 = (_proc_tree_cpu_s(sitl.daemon.pid), _proc_tree_cpu_s(sitl.sim.pid), comp.cpu_s(),
                              _own_cpu_s())
            compact()
            win_att = [k for k in range(n_att0, len(att_t)) if att_t[k] <= w1]
            # a second observer of the rate: the ground-station port (the daemon's extra output)
            gcs_att = sum(1 for row in list(sitl.listener.attitude) if w0 <= row[4] <= w1)
            out["scheduling"] = {"daemon_autogroup": _autogroup(sitl.daemon.pid),
                                 "simulator_and_tap_autogroup": _autogroup(sitl.sim.pid),
                                 "competitor_autogroups": [_autogroup(p.pid) for p in comp.procs],
                                 "competitor_nice": [os.getpriority(os.PRIO_PROCESS, p.pid) for p in comp.procs],
                                 "daemon_group_nice": daemon_group_nice, "policy": "SCHED_OTHER",
                                 "unit": _unit_scheduling()}
            # the simulator first; the tap and the daemon then read what is queued for them
            sitl.sim.send_signal(signal.SIGTERM)
            sitl.sim.wait(60)
            tap_port, d_port = tap.sim_side_port, sitl.fc_port
            t_end = time.monotonic() + BUSY_DRAIN_S
            quiet_since, last = time.monotonic(), None
            while time.monotonic() < t_end:
                ts, ds = udp_socket_state(tap_port), udp_socket_state(d_port)
                state = (tap.forwarded["to_daemon"], ts and ts["rx_queue_bytes"], ds and ds["rx_queue_bytes"])
                if state != last or state[1] or state[2]:
                    quiet_since, last = time.monotonic(), state
                elif time.monotonic() - quiet_since > 1.0:
                    break
                time.sleep(0.1)
                compact()
            tap_sock, d_sock = udp_socket_state(tap_port) or {}, udp_socket_state(d_port) or {}
            out["drain_s"] = time.monotonic() - (t_end - BUSY_DRAIN_S)
            compact()
        # (sitl's exit stopped the daemon: its "stopped" line has its counters)
        competitors_alive = all(p.poll() is None for p in comp.procs)
    out["run_s"] = time.monotonic() - t_run0
    daemon = stopped_counts(sitl.log("daemon"))
    sim_sent, sim_run = sim_sent_counts(sitl.log("sim"))
    if not daemon or sim_sent is None:
        raise RuntimeError(f"no 'stopped' line from the daemon or the simulator; see {workdir}")
    acc = busy_accounting(sim_sent, {"received_by_type": tap.received_by_type,
                                     "forwarded_by_type": tap.forwarded_by_type,
                                     "dropped_on_purpose": tap.dropped_on_purpose,
                                     "forwarded_before_heartbeat": tap.forwarded_before_heartbeat or {},
                                     "forwarded_datagrams": tap.forwarded["to_daemon"]},
                          int(tap_sock.get("drops", 0)), daemon, int(d_sock.get("drops", 0)),
                          int(d_sock.get("rx_queue_bytes", 0)))
    out.update(acc)
    wall = w1 - w0
    cpu = lambda a, b: 100.0 * sum(b.get(k, 0.0) - a.get(k, 0.0) for k in b) / wall  # noqa: E731
    dpid = sitl.daemon.pid
    out.update({
        "window_s": wall,
        "attitude_in_window": len(win_att),
        "attitude_rate_hz": len(win_att) / wall,
        "attitude_rate_ground_station_hz": gcs_att / wall,
        "daemon_cpu_pct": 100.0 * (d1.get(dpid, 0.0) - d0.get(dpid, 0.0)) / wall,
        "daemon_children_cpu_pct": cpu({k: v for k, v in d0.items() if k != dpid},
                                       {k: v for k, v in d1.items() if k != dpid}),
        "sim_cpu_pct": cpu(s0, s1), "harness_process_cpu_pct": 100.0 * (m1 - m0) / wall,
        "competitor_cpu_pct": [100.0 * (b - a) / wall for a, b in zip(h0, h1)],
        "competitors_ran_until_daemon_stopped": competitors_alive,
        "load_avg_1min_mean": float(np.mean(loads)) if loads else os.getloadavg()[0],
        "load_avg_1min_max": float(np.max(loads)) if loads else os.getloadavg()[0],
        "simulator": sim_run, "simulator_sent": sim_sent, "daemon_stopped": daemon,
        "tap": {"received_by_type": tap.received_by_type, "forwarded_datagrams": tap.forwarded["to_daemon"],
                "dropped_on_purpose": tap.dropped_on_purpose,
                "forwarded_before_heartbeat": tap.forwarded_before_heartbeat,
                "socket_drops": int(tap_sock.get("drops", 0))},
        "daemon_socket": d_sock, "daemon_sent_by_type": from_daemon_by_type,
    })
    if len(win_att) > 1:
        ta = np.array([att_t[k] for k in win_att])
        ms = np.array([att_ms[k] for k in win_att], dtype=float)
        gaps_ms = np.diff(ta) * 1e3
        period_ms = 1e3 / att_cfg_hz
        out["attitude_rate_fc_clock_hz"] = (len(ms) - 1) / ((ms[-1] - ms[0]) / 1e3) if ms[-1] > ms[0] else math.nan
        out["attitude_interval_max_ms"] = float(gaps_ms.max())
        out["attitude_intervals_over_2_periods"] = int(np.sum(gaps_ms > 2 * period_ms))
    lat_all, unmatched = match_latency_ms(list(zip(imu_us, imu_t)), [(att_ms[k], att_t[k]) for k in win_att],
                                          per_message=True)
    lat_ms = lat_all[np.isfinite(lat_all)]
    out.update({"attitude_matched": int(lat_ms.size), "attitude_unmatched": unmatched})
    if len(win_att) > 1 and lat_ms.size:
        # where ATTITUDE slots go: the latency of the message that ends an interval over 1.5 periods
        # (a slot passed) against all messages' (the daemon woke late, or the input came late)
        after_gap = lat_all[1:][np.diff(np.array([att_t[k] for k in win_att])) > 1.5e-3 * period_ms]
        after_gap = after_gap[np.isfinite(after_gap)]
        out["attitude_after_missed_slot_latency_p50_ms"] = float(np.median(after_gap)) if after_gap.size else None
        out["attitude_missed_slot_intervals"] = int(after_gap.size)
    if lat_ms.size:
        out.update({"latency_p50_ms": float(np.percentile(lat_ms, 50)),
                    "latency_p99_ms": float(np.percentile(lat_ms, 99)),
                    "latency_max_ms": float(lat_ms.max())})
    out["daemon_loss_events"] = {k: sitl.log("daemon").count(f"event={k}")
                                 for k in ("input_overflow", "input_loss", "loop_stall", "time_gap", "input_backlog")}
    out["verdict"], out["pass"] = busy_verdict(out)
    return out


def _unit_scheduling(path: Path = ROOT / "systemd" / "azimuthd.service") -> dict:
    """The scheduling keys of the systemd unit (what the bench stands in for)."""
    keys = ("CPUWeight", "Nice", "CPUSchedulingPolicy", "CPUSchedulingPriority", "CPUAffinity", "RestrictRealtime")
    out = {}
    for line in path.read_text().splitlines():
        k, _, v = line.strip().partition("=")
        if k in keys:
            out[k] = v
    return out


def busy_verdict(b: dict) -> tuple[str, bool]:
    """One line against issue 19's must-show: 0 samples lost in the kernel or the daemon, ATTITUDE at
    the configured rate, for the window beside the competitors. A run whose harness lost samples or
    whose simulator fell behind real time, or whose observers disagree, proves nothing: INVALID."""
    fails, invalid = [], []
    if b["daemon_samples_lost"] != 0:
        p = b["samples_lost_parts"]
        fails.append(f"daemon lost {b['daemon_samples_lost']} samples (socket {p['daemon_socket_kernel']}, "
                     f"read but not processed {p['daemon_read_not_processed']})")
    events = b.get("daemon_loss_events", {})
    if b["checks"]["daemon_kernel_counter_vs_bench"]["b"] > 0 and not events.get("input_overflow"):
        fails.append("the kernel dropped datagrams at the daemon's socket and it logged no input_overflow "
                     "(it must report them)")
    left = b.get("daemon_socket_left_bytes_at_stop", 0)
    if left:
        fails.append(f"the daemon had not read its socket {BUSY_DRAIN_S:.0f} s after the simulator stopped "
                     f"({left} bytes left, counted as lost at its socket): it was behind")
    cfg, rate = b["attitude_rate_configured_hz"], b["attitude_rate_hz"]
    if abs(rate - cfg) > BUSY_ATTITUDE_RATE_TOLERANCE * cfg:
        fails.append(f"ATTITUDE {rate:.2f} Hz, configured {cfg:.0f} (tolerance {100 * BUSY_ATTITUDE_RATE_TOLERANCE:.0f} %)")
    if b["samples_lost_harness"] != 0:
        invalid.append(f"the harness lost {b['samples_lost_harness']} samples")
    speed = b.get("simulator", {}).get("achieved_speed", math.nan)
    if not speed >= 0.99:
        invalid.append(f"the simulator ran at {speed:.3f}x real time")
    if not b.get("competitors_ran_until_daemon_stopped", True):
        invalid.append("a competitor exited before the daemon stopped")
    if not b["observers_agree"]:
        invalid.append("observers disagree: " + ", ".join(k for k, c in b["checks"].items() if not c["agree"]))
    head = (f"{b['window_s']:.0f} s at {b['rate_hz']:.0f} Hz beside {b['competitors']} CPU-bound competitors "
            f"(1-min load {b['load_avg_1min_mean']:.1f} mean, {b['load_avg_1min_max']:.1f} max)")
    detail = (f"{b['samples_lost']} of {b['samples_sent']} samples lost (daemon {b['daemon_samples_lost']}, "
              f"harness {b['samples_lost_harness']}), ATTITUDE {rate:.2f} Hz of {cfg:.0f} configured, "
              f"latency p99 {b.get('latency_p99_ms', math.nan):.1f} ms")
    if invalid:
        return f"INVALID: {head}: {detail}; " + "; ".join(invalid + fails), False
    if fails:
        return f"FAIL: {head}: " + "; ".join(fails), False
    return f"PASS: {head}: {detail}; observers agree", True


def _busy_worker(opts: dict) -> dict:
    """``busy_run`` in a worker process that starts a session of its own whose CPU group (autogroup)
    gets ``fc_group_nice``: the simulator it starts and the tap it runs are the FC and its wire."""
    fc_nice = opts.pop("fc_group_nice", None)
    if fc_nice is not None:
        os.setsid()
        Path("/proc/self/autogroup").write_text(str(int(fc_nice)))
    return busy_run(**opts)


def busy_part(args) -> dict:
    """The competing-load run, printed; the JSON ``busy`` dict (its ``error`` when it failed)."""
    import concurrent.futures as cf
    import multiprocessing as mp

    from bench.sitl import unit_nice
    root = os.geteuid() == 0
    opts = {"busy_s": args.busy_s, "competitors": args.busy_competitors, "imu_batch": args.imu_batch,
            "daemon_group_nice": (args.busy_daemon_group_nice if args.busy_daemon_group_nice is not None
                                  else unit_nice() if root else None),
            "fc_group_nice": FC_GROUP_NICE if root else None, "udp_rcvbuf_bytes": args.busy_rcvbuf_bytes}
    print(f"\nbusy: the daemon at {RATE_HZ:.0f} Hz beside {args.busy_competitors} CPU-bound competitors for "
          f"{args.busy_s:.0f} s (daemon group nice {opts['daemon_group_nice']}, simulator + tap group nice "
          f"{opts['fc_group_nice']}; load now {os.getloadavg()[0]:.1f}) ...", flush=True)
    try:
        with cf.ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as ex:
            b = ex.submit(_busy_worker, opts).result()
    except Exception as exc:  # noqa: BLE001 - report, keep the other figures
        b = {"error": f"{type(exc).__name__}: {exc}", "samples_lost": None}
        print(f"  busy run failed: {b['error']}")
        return b
    b["fc_group_nice"] = opts["fc_group_nice"]
    p = b["samples_lost_parts"]
    print(f"  IMU samples sent {b['samples_sent']} (+{b['ignored_before_fc_heartbeat']} before the FC's first "
          f"HEARTBEAT), processed {b['samples_processed']}; lost {b['samples_lost']}: tap socket "
          f"{p['tap_socket_kernel']}, tap on purpose {p['tap_dropped_on_purpose']}, daemon socket "
          f"{p['daemon_socket_kernel']}, daemon read but not processed {p['daemon_read_not_processed']}")
    for k, c in b["checks"].items():
        print(f"  check {k}: {c['a']} vs {c['b']} -> {'agree' if c['agree'] else 'DISAGREE'}"
              + (f" ({c['note']})" if "note" in c else ""))
    print(f"  ATTITUDE {b['attitude_rate_hz']:.2f} Hz received (ground-station port {b['attitude_rate_ground_station_hz']:.2f}; "
          f"configured {b['attitude_rate_configured_hz']:.0f}; "
          f"FC clock {b.get('attitude_rate_fc_clock_hz', math.nan):.2f} Hz; longest interval "
          f"{b.get('attitude_interval_max_ms', math.nan):.0f} ms)")
    if b.get("attitude_missed_slot_intervals"):
        print(f"  {b['attitude_missed_slot_intervals']} ATTITUDE intervals over 1.5 periods; the message after one came "
              f"{b['attitude_after_missed_slot_latency_p50_ms']:.1f} ms after its RAW_IMU (median; all: "
              f"{b.get('latency_p50_ms', math.nan):.1f} ms)")
    if "latency_p99_ms" in b:
        print(f"  latency RAW_IMU in -> ATTITUDE out under load: p50 {b['latency_p50_ms']:.3f} ms, p99 "
              f"{b['latency_p99_ms']:.3f} ms, max {b['latency_max_ms']:.3f} ms ({b['attitude_matched']} matched)")
    print(f"  CPU over {b['window_s']:.0f} s: daemon {b['daemon_cpu_pct']:.1f} % of a core (+ its workers "
          f"{b['daemon_children_cpu_pct']:.1f} %), simulator {b['sim_cpu_pct']:.1f} %, tap + listener "
          f"{b['harness_process_cpu_pct']:.1f} %, competitors " + " / ".join(f"{c:.0f} %" for c in b["competitor_cpu_pct"]))
    print(f"  scheduling: {b['scheduling']}")
    print(f"  daemon's UDP receive buffer: asked {b['daemon_udp_rcvbuf_bytes_asked']} bytes, net.core.rmem_max "
          f"{b['net_core_rmem_max']}: effective {b['daemon_udp_rcvbuf_bytes_effective']}")
    print(f"  daemon's own loss events: {b['daemon_loss_events']}; simulator {b['simulator']}")
    print(f"busy verdict: {b['verdict']}")
    return b


# --- main -------------------------------------------------------------------------------------

def replay_part(quick: bool) -> dict:
    """``azimuthd replay`` of a simulated 400 Hz .tlog as its own process (bench/replay_speed.py; the
    real logs: run that bench): ``replay_x_realtime`` = log duration / wall time, and per CPU second."""
    import tempfile

    from bench.replay_speed import make_tlog_400hz, replay_env, replay_one
    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-speed-replay-"))
    tlog = workdir / "sim-400hz.tlog"
    r = replay_one(tlog, workdir, make_tlog_400hz(tlog, 10.0 if quick else 30.0), replay_env(workdir))
    if "error" in r:
        print(f"\nreplay of a 400 Hz log failed: {r['error']}")
        return {"replay": r}
    print(f"\nazimuthd replay, simulated 400 Hz .tlog ({r['log_s']:.0f} s): {r['replay_x_realtime']:.1f}x real time "
          f"(wall), {r['replay_x_realtime_cpu']:.1f}x per CPU second, {r['replay_x_realtime_loop']:.1f}x without the "
          f"{r['startup_s']:.2f} s start; Pipeline {r['pipeline_us_per_imu_sample']:.0f} us + the rest "
          f"{r['overhead_us_per_imu_sample']:.0f} us per IMU sample (load {r['load_avg_1min']:.1f})")
    return {"replay_x_realtime": r["replay_x_realtime"], "replay_x_realtime_cpu": r["replay_x_realtime_cpu"],
            "replay_x_realtime_loop": r["replay_x_realtime_loop"], "replay": r}


def sitl_part(args) -> dict:
    """Part 2 and 3 (latency, daemon CPU) and the harness floor, printed; the JSON ``sitl`` dict."""
    print("\nSITL: simulator + daemon as processes at 400 Hz (loopback UDP) ...", flush=True)
    try:
        s = sitl_latency_cpu(args.quick, args.profile_daemon, rt_priority=args.rt,
                             imu_batch=args.imu_batch)
    except Exception as exc:  # noqa: BLE001 - report, keep the compute figures
        s = {"error": f"{type(exc).__name__}: {exc}"}
    try:
        s.update(harness_floor(4.0 if args.quick else 10.0, args.rt))
    except Exception as exc:  # noqa: BLE001
        s["floor_error"] = f"{type(exc).__name__}: {exc}"
    if "error" in s:
        print(f"  SITL failed: {s['error']}")
    else:
        print(f"  scheduling: {s['sched']}")
        print(f"  RAW_IMU received by the daemon: {s['imu_rate_received_hz']:.0f} Hz; ATTITUDE matched "
              f"{s['attitude_matched']} (unmatched {s['attitude_unmatched']})")
        if "latency_p50_ms" in s:
            print(f"  latency RAW_IMU in -> ATTITUDE out: p50 {s['latency_p50_ms']:.3f} ms, p99 "
                  f"{s['latency_p99_ms']:.3f} ms, max {s['latency_max_ms']:.3f} ms")
        if "floor_p99_ms" in s:
            print(f"  harness floor (UDP echo through a trivial Python process, same machine): "
                  f"p50 {s['floor_p50_ms']:.3f} ms, p99 {s['floor_p99_ms']:.3f} ms")
        print(f"  CPU over {s['window_s']:.0f} s: daemon {s['daemon_cpu_pct']:.1f} % of a core, "
              f"simulator {s['sim_cpu_pct']:.1f} %")
    if "load_avg_1min" in s:
        print(f"  (1-min load {s['load_avg_1min']:.1f}; daemon: {s['imu_path']}, its CPU group nice "
              f"{s['daemon_group_nice']})")
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter stream and SITL window (< 2 min)")
    ap.add_argument("--json", default=None, help="default bench/results/speed.json (--busy-only: speed_busy.json)")
    ap.add_argument("--no-install", action="store_true", help="do not pip-install missing reference filters")
    ap.add_argument("--no-sitl", action="store_true", help="skip the two-process latency/CPU part")
    ap.add_argument("--sitl-only", action="store_true", help="only the two-process latency/CPU part")
    ap.add_argument("--no-replay", action="store_true", help="skip azimuthd replay of a 400 Hz log (replay_x_realtime)")
    ap.add_argument("--imu-batch", action="store_true",
                    help="the daemon with [mavlink] imu_batch on (a read's RAW_IMU as one batch; default off, "
                         "as the daemon's default: one ImuSample per RAW_IMU)")
    ap.add_argument("--rt", type=int, metavar="PRIO", default=0,
                    help="run the SITL daemon (and the tap) SCHED_FIFO at this priority (needs root): "
                         "latency without preemption by other processes")
    ap.add_argument("--busy", action="store_true",
                    help="also the competing-load run: the daemon at 400 Hz beside CPU-bound competitors (JSON busy)")
    ap.add_argument("--busy-only", action="store_true",
                    help="only the competing-load run (JSON default bench/results/speed_busy.json)")
    ap.add_argument("--busy-s", type=float, default=600.0, help="the competing-load window, s (default 600)")
    ap.add_argument("--busy-competitors", type=int, default=BUSY_COMPETITORS,
                    help=f"CPU-bound competitor processes (default {BUSY_COMPETITORS})")
    ap.add_argument("--busy-daemon-group-nice", type=int, default=None, metavar="N",
                    help="the daemon's CPU-group nice in the busy run (default as root: the unit's Nice=; "
                         "0: no scheduling of its own, for a before/after)")
    ap.add_argument("--busy-rcvbuf-bytes", type=int, default=None, metavar="BYTES",
                    help="the daemon's [mavlink] udp_rcvbuf_bytes in the busy run (default: its own, 4 MiB; "
                         "212992: what the kernel's default net.core.rmem_max grants)")
    ap.add_argument("--profile-daemon", metavar="PATH",
                    help="run the SITL daemon under cProfile, stats to PATH (figures then include its overhead)")
    args = ap.parse_args(argv)
    if not args.busy_s > 0 or args.busy_competitors < 0:
        ap.error("--busy-s must be > 0 and --busy-competitors >= 0")
    if args.json is None:
        args.json = str(ROOT / "bench" / "results" / ("speed_busy.json" if args.busy_only else "speed.json"))
    t_all = time.monotonic()
    if args.busy_only:
        result = {"rate_hz": RATE_HZ, "cpu_count": os.cpu_count(), "busy": busy_part(args),
                  "load_avg_1min": os.getloadavg()[0]}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(json_safe(result), indent=2) + "\n")
        print(f"json: {args.json}")
        return 0
    if args.sitl_only:
        result = {"rate_hz": RATE_HZ, "cpu_count": os.cpu_count(), "sitl": sitl_part(args),
                  "load_avg_1min": os.getloadavg()[0]}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(json_safe(result), indent=2) + "\n")
        print(f"json: {args.json}")
        return 0
    versions = ensure_references(not args.no_install)
    print("reference filters (benchmark only): " +
          ", ".join(f"{k} {v or 'NOT AVAILABLE'}" for k, v in versions.items()))
    from bench.sitl import pipeline_inputs
    run = make_stream(args.quick)
    items = pipeline_inputs(run)   # the samples the daemon's link would hand over, in time order
    n_imu = len(run.time_s)
    print(f"stream: sim inclined_rail, {n_imu} IMU samples at {RATE_HZ:.0f} Hz ({n_imu / RATE_HZ:.0f} s, "
          f"launch at {run.truth.launch_time_s:.0f} s), {len(run.baro_time_s)} pressure, "
          f"{len(run.fc_time_s)} FC attitude; python {sys.version.split()[0]}, numpy {np.__version__}")
    budget = 4.0 if args.quick else 15.0
    rows = []
    for name, pkg, factory in CASES:
        if pkg != "ours" and versions.get(pkg) is None:
            rows.append({"case": name, "error": f"{pkg} not installed"})
            continue
        r = time_case(factory, run, items, n_imu, budget)
        r["case"] = name
        rows.append(r)
        print(f"  measured {name}: " + (f"{r['us_per_imu_sample']:.2f} us" if "error" not in r else r["error"]),
              flush=True)
    ref = next((r for r in rows if r["case"].startswith("imufusion") and "error" not in r), None)
    ref_vqf = next((r for r in rows if r["case"].startswith("vqf") and "error" not in r), None)
    stack = rows[0]
    print()
    print(f"{'case':<54} {'us/IMU sample':>14} {'x imufusion':>12} {'x vqf':>8} {'% of stack':>11}")
    for r in rows:
        if "error" in r:
            print(f"{r['case']:<54} {'error':>14}  {r['error']}")
            continue
        us = r["us_per_imu_sample"]
        r["ratio_vs_imufusion"] = us / ref["us_per_imu_sample"] if ref else math.nan
        r["ratio_vs_vqf"] = us / ref_vqf["us_per_imu_sample"] if ref_vqf else math.nan
        r["fraction_of_stack"] = us / stack["us_per_imu_sample"] if "error" not in stack else math.nan
        print(f"{r['case']:<54} {us:14.2f} {r['ratio_vs_imufusion']:12.1f} {r['ratio_vs_vqf']:8.1f} "
              f"{100 * r['fraction_of_stack']:10.0f}%")
    result = {"rate_hz": RATE_HZ, "imu_samples": n_imu, "reference_versions": versions,
              "python": sys.version.split()[0], "numpy": np.__version__, "cases": rows,
              "stack_us_per_imu_sample": stack.get("us_per_imu_sample", math.nan),
              "target_stack_us_per_imu_sample": TARGET_STACK_US, "cpu_count": os.cpu_count(),
              "load_avg_1min": os.getloadavg()[0]}
    result.update(ported_figures(rows))
    print("\ncompiled core vs the Python reference (same stream, same run):")
    for k, v in result["ported"].items():
        print(f"  {k}: {v:.3f}")
    if not args.no_sitl:
        result["sitl"] = sitl_part(args)
    if not args.no_replay:
        result.update(replay_part(args.quick))
    if args.busy:
        result["busy"] = busy_part(args)
    print("\ntargets:")
    st = result["stack_us_per_imu_sample"]
    print(f"  whole stack <= {TARGET_STACK_US} us/sample: {st:.2f} us -> {'PASS' if st <= TARGET_STACK_US else 'FAIL'}")
    s = result.get("sitl", {})
    if "latency_p99_ms" in s:
        print(f"  latency p99 <= {TARGET_P99_MS} ms: {s['latency_p99_ms']:.3f} ms -> "
              f"{'PASS' if s['latency_p99_ms'] <= TARGET_P99_MS else 'FAIL'}")
    if "daemon_cpu_pct" in s:
        print(f"  daemon CPU <= {TARGET_CPU_PCT} % at 400 Hz: {s['daemon_cpu_pct']:.1f} % -> "
              f"{'PASS' if s['daemon_cpu_pct'] <= TARGET_CPU_PCT else 'FAIL'}")
    if "busy" in result:
        print(f"  busy (issue 19): {result['busy'].get('verdict', result['busy'].get('error'))}")
    print(f"  (machine: {os.cpu_count()} cores, 1-min load {os.getloadavg()[0]:.1f}; bench took "
          f"{time.monotonic() - t_all:.0f} s)")
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_safe(result), indent=2) + "\n")
    print(f"json: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
