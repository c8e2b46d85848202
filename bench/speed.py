"""Speed: per-IMU-sample cost of our stack and of each estimator, against imufusion, VQF and ahrs;
end-to-end latency RAW_IMU -> ATTITUDE and the daemon's CPU, with the simulator and the daemon as
separate processes at 400 Hz.

    python bench/speed.py [--quick] [--json PATH] [--no-install] [--no-sitl] [--sitl-only] [--imu-batch]
                          [--no-replay]

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
   stream's N x 3 arrays in one call). JSON ``ported``: per-sample costs and speed-ups
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
        from service.pipeline import Pipeline
        cfg = site_config(run)

        def one_pass():
            before = os.environ.get("AZIMUTHD_CORE")
            os.environ["AZIMUTHD_CORE"] = backend
            try:
                p = Pipeline(cfg)
            finally:
                os.environ.pop("AZIMUTHD_CORE") if before is None else os.environ.update(AZIMUTHD_CORE=before)
            if p.core.name != backend:
                raise RuntimeError(f"asked for {backend}, got {p.core.name}: {p.core.why}")
            for _ in feed_pipeline(p, items):
                pass
        return one_pass
    return factory


case_pipeline = _pipeline_case("core")
case_pipeline_python = _pipeline_case("python")


def case_phases(run, items):
    from service.phases import PhaseParams, PhaseState, phase_step
    t, g, a = run.time_s.tolist(), list(run.gyro_rad_s), list(run.accel_m_s2)
    params = PhaseParams()

    def one_pass():
        st = PhaseState()
        for k in range(len(t)):
            st, _ = phase_step(st, g[k], a[k], t[k], params)
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
    ("phases: levelling + launch detection", "ours", case_phases),
    ("strapdown (estimators.strapdown)", "ours", case_strapdown),
    ("strapdown, core, per sample (held state)", "ours", case_strapdown_core_held),
    ("strapdown, core, batch (N x 3 array)", "ours", case_strapdown_core_batch),
    ("rest accumulator (estimators.levelling)", "ours", case_levelling),
    ("rest accumulator, core, per-sample drop-in", "ours", case_levelling_core_step),
    ("rest accumulator, core, batch (N x 3 arrays)", "ours", case_levelling_core_batch),
    ("method A azimuth (estimators.azimuth)", "ours", case_azimuth),
    ("method B synthetic AHRS (estimators.synthetic_ahrs)", "ours", case_synthetic_ahrs),
    ("polar attitude (estimators.polar_attitude)", "ours", case_polar_attitude),
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
    # match ATTITUDE -> RAW_IMU by FC time
    imu_us = np.array([u for u, _ in imu_fwd], dtype=np.int64)
    imu_t = np.array([t for _, t in imu_fwd])
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
            continue
        lat.append(t_rx - imu_t[lo])
    lat_ms = np.array(lat) * 1e3
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
    }
    out = {k: us.get(v, math.nan) for k, v in pick.items()}
    for part in ("strapdown", "levelling"):
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
    return {"ported": out, "stack_python_reference_us_per_imu_sample": stack_py}


# --- main -------------------------------------------------------------------------------------

def replay_part(quick: bool) -> dict:
    """``azimuthd replay`` of a simulated 400 Hz .tlog as its own process (bench/replay_speed.py; the
    real logs: run that bench): ``replay_x_realtime`` = log duration / wall time, and per CPU second."""
    import tempfile

    from bench.replay_speed import make_tlog_400hz, replay_one
    workdir = Path(tempfile.mkdtemp(prefix="azimuthd-speed-replay-"))
    tlog = workdir / "sim-400hz.tlog"
    r = replay_one(tlog, workdir, make_tlog_400hz(tlog, 10.0 if quick else 30.0))
    if "error" in r:
        print(f"\nreplay of a 400 Hz log failed: {r['error']}")
        return {"replay": r}
    print(f"\nazimuthd replay, simulated 400 Hz .tlog ({r['log_s']:.0f} s): {r['replay_x_realtime']:.1f}x real time "
          f"(wall), {r['replay_x_realtime_cpu']:.1f}x per CPU second; Pipeline {r['pipeline_us_per_imu_sample']:.0f} us "
          f"per IMU sample (load {r['load_avg_1min']:.1f})")
    return {"replay_x_realtime": r["replay_x_realtime"], "replay_x_realtime_cpu": r["replay_x_realtime_cpu"],
            "replay": r}


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
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "speed.json"))
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
    ap.add_argument("--profile-daemon", metavar="PATH",
                    help="run the SITL daemon under cProfile, stats to PATH (figures then include its overhead)")
    args = ap.parse_args(argv)
    t_all = time.monotonic()
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
    print(f"  (machine: {os.cpu_count()} cores, 1-min load {os.getloadavg()[0]:.1f}; bench took "
          f"{time.monotonic() - t_all:.0f} s)")
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_safe(result), indent=2) + "\n")
    print(f"json: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
