"""Geofence bench: divert before the breach with GNSS denied, and no divert while inside.

    python bench/geofence.py [--quick] [--json PATH] [--mode headline|daemon|pipeline|offline|closed|all]
                             [--load idle|busy|both] [--busy] [--seeds N] [--seed0 S] [--speed X]
                             [--jobs N] [--imu-rate-hz HZ] [--sim-base-rate-hz HZ] [--fc-nice N] [--daemon-nice N]
                             [--daemon-group-nice N]

The issue-16 headline, on a quiet machine (1-min load < 1), as root, ~80 min per set:

    nice -n 10 python bench/geofence.py --mode daemon --load idle --jobs 2 --json bench/results/geofence_daemon_idle.json
    nice -n 10 python bench/geofence.py --mode daemon --load busy --jobs 2 --json bench/results/geofence_daemon_busy.json

Scenarios (docs/GEOFENCE.md): a 5 km x 5 km inclusion square around the launch site (plus a
300 m ceiling band: 20..400 m above the launch site); a rail launch, GNSS lost 25 s after the
launch, random wind (0-8 m/s, any direction, gusts 0.5 m/s).
* ``outbound``: the vehicle flies a straight leg toward the fence at an angle drawn per seed
  (launch azimuth 0..360 deg: incidence 0..45 deg on an edge); without a divert it crosses the
  fence after ~110-160 s.
* ``inside``: a climb-out, back to the launch site, loiters around it and a 600 m excursion:
  within ~1 km of the launch site (> 1.4 km inside the fence). The look-ahead is a straight line
  along the current track: a vehicle circling closer than ground speed x look-ahead + margin +
  k sigma to the fence is diverted (conservative by design).

Headline modes (truth only scores):
* ``daemon``: the real daemon (``azimuthd run``) and the simulator (``azimuthd sim``) as two
  processes over UDP (bench/sitl.py). The daemon has the operator's config and MAVLink only
  (SIMSTATE, the truth on the wire, is not streamed unless asked for, and nothing in the
  daemon's code reads it: tests/test_truth_isolation.py); its own heading, phases and monitor decide; the
  simulator's truth log scores the TRUE track: fence exits (< 0 m) and margin violations (< 50 m),
  false diverts of the inside flights; the UDP tap counts the RAW_IMU the daemon was sent against
  the samples it processed (its "stopped" log line), and the ATTITUDE latency. ``--load busy``:
  two CPU-bound competitor processes for the whole run. The operator asks for RAW_IMU at 50 Hz
  (stock ArduPilot; the simulated FC samples at 200 Hz). The daemon runs as its systemd unit
  does (own session; its CPU group at the unit's Nice=, -10, standing in for the unit's
  CPUWeight); the simulator and the tap (FC and wire) in a CPU group at autogroup nice -15, above
  the daemon's (a real FC has its own CPU). Each flight records the simulator's achieved speed, the 1-min load average and the
  daemon's CPU: a flight where the simulator fell behind real time (a real FC never does; the
  daemon then sees FC-clock lags) is invalid; a valid one where the daemon fell behind (ATTITUDE
  p99 > 5 s, or a backlog 30 s after the flight) is reported as such, apart.
* ``pipeline``: the same flights offline (sim.offline), through the daemon's own
  ``service.pipeline.Pipeline`` and ``GeofenceMonitor`` as service/daemon.py wires them: no wall
  clock, so no machine load in the figure. Open loop: the latch must come before the TRUE track
  crosses the fence (lead time), the inside flights must never latch. The decision half runs
  on a sealed SimRun (bench/_truth_guard.py): it cannot read truth.

Diagnostics (keys ``diagnostic_truth_heading.*``, never a headline): ``offline`` and ``closed``
give the monitor the TRUE yaw plus a per-seed bias N(0, 1.5 deg) and white noise 0.5 deg
(sigma told 1.6 deg; ``closed`` reads it from SIMSTATE) and the truth's phase labels (offline):
what the monitor does with a heading of known quality, not what the daemon does.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimators.air_data import air_data_init, air_data_step  # noqa: E402
from estimators.geodesy import LocalGnomonic, signed_distance_polygon, vincenty_inverse  # noqa: E402
from service.geofence import GeofenceMonitor  # noqa: E402
from service.geofence_config import validate_geofence  # noqa: E402

SITE = {"lat_deg": 47.3, "lon_deg": 8.5, "alt_m": 450.0}
HALF_SIZE_M = 2500.0
HEADING_BIAS_SIGMA_DEG = 1.5
HEADING_WHITE_SIGMA_DEG = 0.5
HEADING_STATED_SIGMA_DEG = 1.6
GNSS_LOST_AFTER_LAUNCH_S = 25.0
REST_S = 5.0


def fence_square(half_size_m: float = HALF_SIZE_M, site: dict = SITE) -> list:
    """Square inclusion polygon (lat_deg, lon_deg) centred on the site (corners by geodesic)."""
    from estimators.geodesy import vincenty_direct
    lat0, lon0 = math.radians(site["lat_deg"]), math.radians(site["lon_deg"])
    r = half_size_m * math.sqrt(2.0)
    out = []
    for az in (45.0, 135.0, 225.0, 315.0):
        la, lo = vincenty_direct(lat0, lon0, math.radians(az), r)
        out.append([math.degrees(la), math.degrees(lo)])
    return out


def fence_raw(**over) -> dict:
    raw = {"enabled": True, "inclusion": [fence_square()], "alt_min_m": 20.0, "alt_max_m": 400.0,
           "margin_m": 50.0, "sigma_k": 2.0, "lookahead_s": 20.0, "trigger_hold_s": 0.5,
           "actions": ["rtl", "rtl_mode", "reposition"], "safe_lat_deg": SITE["lat_deg"],
           "safe_lon_deg": SITE["lon_deg"], "safe_alt_m": 150.0, "wind_source": "estimate",
           "wind_sigma_m_s": 4.0, "command_timeout_s": 1.0, "command_tries": 5}
    raw.update(over)
    return raw


def scenario(kind: str, seed: int) -> dict:
    """The scenario dict (sim/scenario.py keys) for one seed."""
    rng = np.random.default_rng([seed, 8 if kind == "outbound" else 9])
    az = float(rng.uniform(0.0, 360.0))
    wspd, wdir = float(rng.uniform(0.0, 8.0)), float(rng.uniform(0.0, 2 * math.pi))
    sc = {"scenario": {"name": f"geofence_{kind}_{seed}", "duration_s": REST_S + 240.0, "date": "2026-11-22"},
          "site": dict(SITE),
          "launcher": {"type": "rail", "azimuth_deg": az, "elevation_deg": 15.0, "rest_s": REST_S},
          "flight": {"cruise_airspeed_m_s": 22.0},
          "wind": {"north_m_s": wspd * math.cos(wdir), "east_m_s": wspd * math.sin(wdir), "gust_sigma_m_s": 0.5},
          "gnss": {"lost_at_s": REST_S + GNSS_LOST_AFTER_LAUNCH_S}}
    if kind == "outbound":
        sc["legs"] = [{"type": "climb", "alt_m": 150.0, "rate_m_s": 4.0, "heading_deg": az},
                      {"type": "level", "duration_s": 600.0, "heading_deg": az}]
    else:
        side = math.radians(az + 90.0)
        sc["legs"] = [{"type": "climb", "alt_m": 120.0, "rate_m_s": 6.0, "heading_deg": az},
                      {"type": "goto", "north_m": 0.0, "east_m": 0.0},
                      {"type": "loiter", "radius_m": 200.0, "duration_s": 60.0,
                       "lat_deg": SITE["lat_deg"], "lon_deg": SITE["lon_deg"]},
                      {"type": "goto", "north_m": 600.0 * math.cos(side), "east_m": 600.0 * math.sin(side)},
                      {"type": "loiter", "radius_m": 300.0, "lat_deg": SITE["lat_deg"], "lon_deg": SITE["lon_deg"]}]
    return sc


class HeadingNoise:
    """DIAGNOSTIC stand-in (offline/closed modes only): truth heading + a per-seed constant bias +
    white noise; the sigma the monitor is told. Never a headline figure."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng([seed, 77])
        self.bias_rad = math.radians(HEADING_BIAS_SIGMA_DEG) * float(self.rng.standard_normal())
        self.sigma_rad = math.radians(HEADING_STATED_SIGMA_DEG)

    def __call__(self, yaw_true_rad: float) -> float:
        w = math.radians(HEADING_WHITE_SIGMA_DEG) * float(self.rng.standard_normal())
        return (yaw_true_rad + self.bias_rad + w) % (2 * math.pi)


def true_clearance_m(lat_rad: np.ndarray, lon_rad: np.ndarray, cfg) -> np.ndarray:
    """Signed distance (m, > 0 inside) of the TRUE track to the inclusion fence (the scoring)."""
    plane = LocalGnomonic(math.radians(SITE["lat_deg"]), math.radians(SITE["lon_deg"]))
    pts = plane.forward(np.asarray(lat_rad), np.asarray(lon_rad))
    best = np.full(len(pts), np.inf)
    for poly in cfg.inclusion:
        p = np.radians(np.array(poly))
        d, _ = signed_distance_polygon(pts, plane.forward(p[:, 0], p[:, 1]))
        best = np.minimum(best, d)
    return best


# --- offline, open loop --------------------------------------------------------------------------

def run_offline(kind: str, seed: int, raw: dict | None = None, rate_hz: float = 10.0,
                flight_s: float | None = None) -> dict:
    """DIAGNOSTIC (truth heading + noise, truth phase labels): open loop on sim.offline data, when
    does the monitor latch vs when does the truth cross? The headline is run_pipeline."""
    from sim.offline import simulate
    raw = raw or fence_raw()
    cfg = validate_geofence(raw)
    sc = scenario(kind, seed)
    if flight_s is not None:
        sc["scenario"]["duration_s"] = REST_S + flight_s
    run = simulate(sc, seed=seed, imu_rate_hz=50.0)
    tr = run.truth
    mon = GeofenceMonitor(cfg, SITE["lat_deg"], SITE["lon_deg"], SITE["alt_m"])
    mon.on_heartbeat(SimpleNamespace(armed=True, autopilot="ardupilot", vehicle_type=1))
    noise = HeadingNoise(seed)
    ad_state = air_data_init()
    t_imu = tr.time_s
    lost = run.gnss_lost_time_s
    latch_t = None
    first_cmd = None
    dr_err_m = dr_sigma_m = None
    step = max(1, int(round(run.baro_time_s.size / (run.baro_time_s[-1] * rate_hz))))
    for j in range(0, run.baro_time_s.size, 1):
        tb = float(run.baro_time_s[j])
        ad_state, ad = air_data_step(ad_state, float(run.press_abs_pa[j]), float(run.press_diff_pa[j]),
                                     float(run.temperature_k[j]), tb)
        if j % step:
            continue
        k = min(int(np.searchsorted(t_imu, tb)), t_imu.size - 1)
        phase = "pre-launch" if tr.phase[k] == "rest" else "in-flight"
        gnss_ok = lost is None or tb < lost
        mon.on_gnss_health(gnss_ok)
        if gnss_ok:
            v = tr.vel_ned_m_s[k]
            mon.on_fc_position(tb, math.degrees(tr.lat_rad[k]), math.degrees(tr.lon_rad[k]), float(tr.alt_m[k]),
                               float(v[0]), float(v[1]))
        sol = SimpleNamespace(time_fc_s=tb, phase=phase, heading_valid=True,
                              heading_rad=noise(float(tr.euler_rad[k, 2])), heading_sigma_rad=noise.sigma_rad)
        cmds = mon.step(sol, ad, tb)
        if cmds and first_cmd is None:
            first_cmd = (tb, cmds[0].name)
        if mon.latched and latch_t is None:
            latch_t = tb
            st = mon.state()
            dr_err_m, _a, _b = vincenty_inverse(float(tr.lat_rad[k]), float(tr.lon_rad[k]),
                                                math.radians(st["lat_deg"]), math.radians(st["lon_deg"]))
            dr_sigma_m = st["pos_sigma_major_m"]
    clear = true_clearance_m(tr.lat_rad, tr.lon_rad, cfg)
    out_idx = np.nonzero(clear < 0.0)[0]
    cross_t = float(t_imu[out_idx[0]]) if out_idx.size else None
    return {"kind": kind, "seed": seed, "latch_time_s": latch_t, "true_cross_time_s": cross_t,
            "lead_time_s": (cross_t - latch_t) if (cross_t is not None and latch_t is not None) else None,
            "first_command": first_cmd[1] if first_cmd else None,
            "dr_error_at_latch_m": dr_err_m, "dr_sigma_major_at_latch_m": dr_sigma_m,
            "launch_azimuth_deg": sc["launcher"]["azimuth_deg"], "gnss_lost_time_s": lost}


# --- the daemon's Pipeline, offline: its own heading and phases, no wall clock --------------------

IMU_RATE_HZ = 50.0
"""RAW_IMU rate the operator asks of the FC (``[mavlink] imu_rate_hz``), daemon and pipeline modes:
what a stock ArduPilot streams (issue 15: its 50 Hz loop refuses more; 200 Hz needs SCHED_LOOP_RATE raised)."""
PIPELINE_IMU_HZ = IMU_RATE_HZ
"""The pipeline mode's IMU rate: the daemon's (outbound seed 1 at 100 Hz: lead 25.1 s, DR error 0.66 sigma;
at 50 Hz: 26.0 s, 0.36 sigma)."""


def operator_config(decimal_year: float) -> dict:
    """What the operator configures for the bench's flights: the site, the date, a rail
    launcher (``[launch] vehicle`` said: the offline feed has no FC HEARTBEAT for ``auto``), the
    IMU mount (level) and the IMU rate asked of the FC."""
    return {"site": {**SITE, "decimal_year": float(decimal_year)},
            "launch": {"case": "inclined", "vehicle": "launcher"},
            "imu": {"mount_roll_deg": 0.0, "mount_pitch_deg": 0.0, "mount_yaw_deg": 0.0},
            "mavlink": {"imu_rate_hz": PIPELINE_IMU_HZ}}


def fc_gnss_positions(run, rate_hz: float = 5.0) -> list[tuple]:
    """The simulated FC's GLOBAL_POSITION_INT while its GNSS is healthy (sim/autopilot.py sends the
    simulated position then): (time_fc_s, lat_deg, lon_deg, alt_m, v_north, v_east). A harness
    input the daemon also gets, cut at the FC's reported GNSS loss; nothing after it."""
    tr = run.truth
    lost = run.gnss_lost_time_s
    out = []
    for t in np.arange(0.0, float(run.time_s[-1]), 1.0 / rate_hz).tolist():
        if lost is not None and t >= lost:
            break
        k = min(int(np.searchsorted(run.time_s, t)), run.time_s.size - 1)
        v = tr.vel_ned_m_s[k]
        out.append((float(run.time_s[k]), math.degrees(tr.lat_rad[k]), math.degrees(tr.lon_rad[k]),
                    float(tr.alt_m[k]), float(v[0]), float(v[1])))
    return out


def pipeline_decide(run, fc_positions: list[tuple], raw: dict) -> dict:
    """The daemon's decision path on a (sealed) SimRun: Pipeline (heading, phases, air data) ->
    GeofenceMonitor, as service/daemon.py wires them (_geofence_step per solution). Reads no
    truth: bench/_truth_guard.sealed(run) is what it gets in tests/test_truth_isolation.py."""
    from mavlink_io.samples import FcEkfStatus, ImuSample
    from service.config import validate
    from service.pipeline import Pipeline
    from sitl import pipeline_inputs
    cfg = validate_geofence(raw)
    p = Pipeline(validate(operator_config(run.site["decimal_year"])))
    mon = GeofenceMonitor(cfg, SITE["lat_deg"], SITE["lon_deg"], SITE["alt_m"])
    mon.on_heartbeat(SimpleNamespace(armed=True, autopilot="ardupilot", vehicle_type=1))
    lost = run.gnss_lost_time_s
    items = pipeline_inputs(run)
    ekf = [FcEkfStatus(t, True, lost is None or t < lost, 0, "ekf_status_report", t)
           for t in np.arange(0.0, float(run.time_s[-1]), 0.5).tolist()]
    merged = sorted([(it.time_rx_s, 0, i, it) for i, it in enumerate(ekf)]
                    + [(f[0], 1, i, f) for i, f in enumerate(fc_positions)]
                    + [(it.time_rx_s, 2, i, it) for i, it in enumerate(items)], key=lambda x: x[:3])
    latch = first_cmd = latch_state = None
    heading_src: dict[str, int] = {}
    for _t, kind, _i, it in merged:
        if kind == 0:
            p.on_fc_ekf_status(it)
            mon.on_gnss_health(bool(it.horiz_pos_ok))
        elif kind == 1:
            mon.on_fc_position(*it)
        elif type(it) is ImuSample:
            sol = p.on_imu(it)
            p.drain_events()
            if sol is None:
                continue
            heading_src[sol.heading_source] = heading_src.get(sol.heading_source, 0) + 1
            cmds = mon.step(sol, p.air_data(), sol.time_fc_s)
            if cmds and first_cmd is None:
                first_cmd = (sol.time_fc_s, cmds[0].name)
            if mon.latched and latch is None:
                latch, latch_state = sol.time_fc_s, mon.state()
        elif hasattr(it, "press_abs_pa"):
            p.on_pressure(it)
        else:
            p.on_fc_attitude(it)
    return {"latch_time_s": latch, "first_command": first_cmd[1] if first_cmd else None,
            "latch_state": latch_state, "heading_sources": heading_src}


def run_pipeline(kind: str, seed: int, raw: dict | None = None, flight_s: float | None = None) -> dict:
    """One flight: simulate, decide on the sealed run (no truth), then score against the truth."""
    from sim.offline import simulate

    from _truth_guard import sealed
    raw = raw or fence_raw()
    cfg = validate_geofence(raw)
    sc = scenario(kind, seed)
    if flight_s is not None:
        sc["scenario"]["duration_s"] = REST_S + flight_s
    run = simulate(sc, seed=seed, imu_rate_hz=PIPELINE_IMU_HZ)
    d = pipeline_decide(sealed(run), fc_gnss_positions(run), raw)
    # scoring (truth from here on)
    tr = run.truth
    clear = true_clearance_m(tr.lat_rad, tr.lon_rad, cfg)
    out_idx = np.nonzero(clear < 0.0)[0]
    cross_t = float(run.time_s[out_idx[0]]) if out_idx.size else None
    dr_err = dr_sig = None
    if d["latch_time_s"] is not None:
        k = min(int(np.searchsorted(run.time_s, d["latch_time_s"])), run.time_s.size - 1)
        st = d["latch_state"]
        dr_err, _a, _b = vincenty_inverse(float(tr.lat_rad[k]), float(tr.lon_rad[k]),
                                          math.radians(st["lat_deg"]), math.radians(st["lon_deg"]))
        dr_sig = st["pos_sigma_major_m"]
    latch = d["latch_time_s"]
    return {"kind": kind, "seed": seed, "latch_time_s": latch, "true_cross_time_s": cross_t,
            "lead_time_s": (cross_t - latch) if (cross_t is not None and latch is not None) else None,
            "first_command": d["first_command"], "dr_error_at_latch_m": dr_err,
            "dr_sigma_major_at_latch_m": dr_sig, "heading_sources": d["heading_sources"],
            "launch_azimuth_deg": sc["launcher"]["azimuth_deg"], "gnss_lost_time_s": run.gnss_lost_time_s}


# --- closed loop against the live simulator, with an in-process stand-in for the daemon loop -----

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return repr(float(v)) if isinstance(v, float) else repr(v)


def write_scenario_toml(sc: dict, path: Path) -> Path:
    lines = []
    for section, body in sc.items():
        if section == "legs":
            continue
        lines.append(f"[{section}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in body.items()]
        lines.append("")
    for leg in sc.get("legs", []):
        lines.append("[[legs]]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in leg.items()]
        lines.append("")
    path.write_text("\n".join(lines))
    return path


def run_closed(kind: str, seed: int, raw: dict | None = None, speed: float = 20.0,
               flight_s: float = 200.0, workdir: Path | None = None) -> dict:
    """DIAGNOSTIC (the SIMSTATE truth yaw + noise): one closed-loop flight, simulator process +
    this process as a stand-in for the daemon loop. The headline is run_daemon."""
    from mavlink_io.commands import CommandProtocol, CommandProtocolParams
    from mavlink_io.link import LinkConfig, MavlinkLink
    from mavlink_io.samples import CommandAck, FcHeartbeat, FcSysStatus, PressureSample
    from sim.truthlog import MODES, load_truth_log
    from sitl import free_udp_port

    raw = raw or fence_raw()
    cfg = validate_geofence(raw)
    wd = Path(workdir or tempfile.mkdtemp(prefix="azimuthd-geofence-"))
    sc = scenario(kind, seed)
    sc["scenario"]["duration_s"] = REST_S + flight_s
    scen = write_scenario_toml(sc, wd / "scenario.toml")
    port = free_udp_port()
    truth_path = wd / "truth.csv"
    sim_cmd = [sys.executable, "-m", "sim", "--scenario", str(scen), "--mavlink", f"udpout:127.0.0.1:{port}",
               "--speed", str(speed), "--seed", str(seed), "--truth-log", str(truth_path), "--truth-log-rate", "10"]
    link = MavlinkLink(LinkConfig(url=f"udpin:127.0.0.1:{port}",
                                  stream_rates_hz={"SCALED_PRESSURE": 20.0, "SIMSTATE": 20.0,
                                                   "GLOBAL_POSITION_INT": 5.0, "SYS_STATUS": 2.0}))
    mon = GeofenceMonitor(cfg, SITE["lat_deg"], SITE["lon_deg"], SITE["alt_m"])
    proto = CommandProtocol(link.send, lambda: (link.target_system, link.target_component),
                            CommandProtocolParams(ack_timeout_s=cfg.command_timeout_s, max_tries=cfg.command_tries))
    noise = HeadingNoise(seed)
    latest = {"yaw": None, "status": 3}
    sent: list[tuple[float, str]] = []
    outcomes = []

    def on_raw(msg):
        t = msg.get_type()
        if t == "SIMSTATE":
            latest["yaw"] = float(msg.yaw)
        elif t == "GLOBAL_POSITION_INT":
            mon.on_fc_position(msg.time_boot_ms / 1000.0, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1000.0,
                               msg.vx / 100.0, msg.vy / 100.0)
    link.subscribe(on_raw)
    ad_state = air_data_init()
    ad = None
    log = open(wd / "sim.log", "w")
    sim = subprocess.Popen(sim_cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
    t_fc = 0.0
    try:
        t_end = time.monotonic() + flight_s / speed + 60.0
        while sim.poll() is None and time.monotonic() < t_end:
            now = time.monotonic()
            for item in link.poll(0.01):
                if isinstance(item, FcHeartbeat):
                    mon.on_heartbeat(item)
                    latest["status"] = item.system_status
                elif isinstance(item, FcSysStatus):
                    mon.on_gnss_health(bool(item.gps_healthy))
                elif isinstance(item, CommandAck):
                    for o in proto.on_command_ack(item, now):
                        outcomes.append(o)
                        for spec in mon.on_command_outcome(o, t_fc):
                            proto.submit(spec, now)
                            sent.append((t_fc, spec.name))
                elif isinstance(item, PressureSample):
                    if ad_state.time_s is not None and item.time_fc_s <= ad_state.time_s:
                        continue
                    ad_state, ad = air_data_step(ad_state, item.press_abs_pa, item.press_diff_pa,
                                                 item.temperature_k, item.time_fc_s)
                    t_fc = item.time_fc_s
                    if latest["yaw"] is None:
                        continue
                    phase = "in-flight" if latest["status"] == 4 else "pre-launch"
                    sol = SimpleNamespace(time_fc_s=t_fc, phase=phase, heading_valid=True,
                                          heading_rad=noise(latest["yaw"]), heading_sigma_rad=noise.sigma_rad)
                    for spec in mon.step(sol, ad, now):
                        proto.submit(spec, now)
                        sent.append((t_fc, spec.name))
            for o in proto.poll(time.monotonic()):
                outcomes.append(o)
                for spec in mon.on_command_outcome(o, t_fc):
                    proto.submit(spec, time.monotonic())
                    sent.append((t_fc, spec.name))
    finally:
        if sim.poll() is None:
            sim.terminate()
            try:
                sim.wait(15)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait(5)
        link.close()
        log.close()
    tr = load_truth_log(str(truth_path))
    clear = true_clearance_m(tr["lat_rad"], tr["lon_rad"], cfg)
    flying = tr["phase"] != 0
    alt_rel = tr["alt_m"] - SITE["alt_m"]
    modes = sorted({MODES[int(m)] for m in tr["mode"]}) if tr["mode"].size else []
    return {"kind": kind, "seed": seed, "diverts_sent": len(sent),
            "first_divert_time_fc_s": sent[0][0] if sent else None, "actions": [n for _, n in sent],
            "outcomes": [f"{o.name}:{o.status}" for o in outcomes],
            "min_true_clearance_m": float(np.min(clear[flying])) if flying.any() else None,
            "max_alt_rel_m": float(np.max(alt_rel)) if alt_rel.size else None,
            "modes_seen": modes, "truth_rows": int(tr["time_s"].size),
            "launch_azimuth_deg": sc["launcher"]["azimuth_deg"], "workdir": str(wd)}


# --- the daemon itself: the headline ----------------------------------------------------------

def _logfmt_fields(line: str) -> dict:
    """key=value pairs of one logfmt line (service/logs.py), values unquoted."""
    import shlex
    out = {}
    try:
        parts = shlex.split(line)
    except ValueError:
        return out
    for p in parts:
        k, sep, v = p.partition("=")
        if sep:
            out[k] = v
    return out


def attitude_latency_ms(tap) -> np.ndarray:
    """Latency of every daemon ATTITUDE: tap receive time minus the tap's forward time of the
    RAW_IMU with the same FC time (within 1 ms; bench/speed.py's matching). One clock, one thread."""
    imu = sorted((m.time_usec, t) for t, m in tap.to_daemon)
    if not imu:
        return np.zeros(0)
    us = np.array([u for u, _ in imu], dtype=np.int64)
    tf = np.array([t for _, t in imu])
    lat = []
    for t_rx, m in tap.from_daemon:
        if m.get_type() != "ATTITUDE":
            continue
        lo = np.searchsorted(us, m.time_boot_ms * 1000 - 1000, side="left")
        hi = np.searchsorted(us, m.time_boot_ms * 1000 + 1000, side="right")
        if hi - lo == 1:
            lat.append(t_rx - tf[lo])
    return np.array(lat) * 1e3


class CpuHogs:
    """``n`` CPU-bound competitor processes for the whole run (``--busy``), killed on exit."""

    def __init__(self, n: int):
        self.n, self.procs = n, []

    def __enter__(self):
        # each in a session (a CPU group) of its own, as other services on a companion computer
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True)
                      for _ in range(self.n)]
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
            p.wait(5)


SIM_BASE_RATE_HZ = {50.0: 200.0, 200.0: 500.0}
"""The simulated FC's sensor rate per RAW_IMU rate: each message averages 4 (50 Hz) or 2-3 (200 Hz)
base samples. The FC's own configuration (a real FC samples on its own CPU)."""
DRAIN_S = 30.0
"""After the flight, how long a daemon behind it may work off its backlog before it is stopped
(what it has not processed then counts as lost)."""
DAEMON_BEHIND_S = 5.0
"""A daemon whose ATTITUDE lags its RAW_IMU by more than this (p99), or which had not worked off its
backlog DRAIN_S after the flight, did not keep up: the flight then measures the CPU it got (a
finding for the compiled core when the machine was otherwise idle; the crowding when it was not),
and is reported as such, apart from the flights where it kept up."""
ABORT_LAG_S = 30.0
"""A flight whose simulator falls this far behind real time is stopped: it is invalid already
(> 5 s, the daemon's reboot_lag_s) and only costs the bench's time."""


def _proc_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process (/proc/PID/stat fields 14, 15), None if gone."""
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def run_daemon(kind: str, seed: int, raw: dict | None = None, speed: float = 1.0, flight_s: float = 200.0,
               imu_rate_hz: float = IMU_RATE_HZ, sim_base_rate_hz: float | None = None,
               sim_nice: int | None = None, daemon_nice: int | None = None,
               daemon_own_session: bool = True, daemon_group_nice: int | None = None) -> dict:
    """One flight with the real daemon (``azimuthd sim`` + ``azimuthd run`` processes over UDP,
    bench/sitl.py). The daemon gets only the operator's config (site, launcher case, IMU mount,
    the RAW_IMU rate it asks for, [geofence]) and MAVLink; its own heading and phases drive its
    monitor. The UDP tap between them records the commands it sends, the RAW_IMU it was forwarded
    and its ATTITUDE (latency); its "stopped" log line gives the samples it processed. Truth (the
    simulator's truth log) only scores: the true track's clearance to the fence.

    ``speed`` 1: real time, as an FC runs. The daemon runs as systemd/azimuthd.service runs it: a
    service in a session (so, with autogroup scheduling, a CPU group) of its own, that group at
    nice ``daemon_group_nice`` (the unit's Nice=, standing in for its cgroup's CPUWeight: main()
    reads it from systemd/azimuthd.service), the daemon's own nice ``daemon_nice``. ``sim_nice``:
    the simulator's nice value within this process's group (daemon_flights puts the simulator and
    the tap, the FC and its wire, in a group of their own above the daemon's: a real FC has its
    own CPU)."""
    from sim.truthlog import load_truth_log
    from sitl import Sitl
    raw = raw or fence_raw()
    cfg = validate_geofence(raw)
    wd = Path(tempfile.mkdtemp(prefix="azimuthd-geofence-daemon-"))
    sc = scenario(kind, seed)
    sc["scenario"]["duration_s"] = REST_S + flight_s
    scen = write_scenario_toml(sc, wd / "scenario.toml")
    base_hz = sim_base_rate_hz or SIM_BASE_RATE_HZ.get(float(imu_rate_hz), 1000.0)
    # SIMSTATE (the truth on the wire) not streamed by default (a legacy REQUEST_DATA_STREAM EXTRA1
    # turns it on; the daemon's code never reads it: tests/test_truth_isolation.py).
    sim_args = ["--truth-log-rate", "10", "--set", "autopilot.simstate_rate_hz=0",
                "--set", f"autopilot.base_rate_hz={base_hz:g}"]
    load0 = os.getloadavg()[0]
    t_wall0 = time.monotonic()
    cpu = {"sim": None, "daemon": None}
    lag = {"max_s": 0.0, "aborted": False}

    def sim_done_or_hopeless(s) -> bool:
        """Polled while flying: CPU time so far, and how far the simulator is behind real time."""
        for name, p in (("sim", s.sim), ("daemon", s.daemon)):
            c = _proc_cpu_s(p.pid) if p.poll() is None else None
            if c is not None:
                cpu[name] = c
        fwd = s.tap.to_daemon
        if len(fwd) > 1:
            behind = (fwd[-1][0] - fwd[0][0]) - (fwd[-1][1].time_usec - fwd[0][1].time_usec) * 1e-6
            lag["max_s"] = max(lag["max_s"], behind)
            if behind > ABORT_LAG_S:
                lag["aborted"] = True
                return True
        return s.sim.poll() is not None

    sitl = Sitl(scenario=str(scen), speed=speed, seed=seed, tap=True, workdir=wd,
                tap_record_to_daemon=("RAW_IMU",),
                config_overrides={"geofence": raw, "mavlink": {"imu_rate_hz": float(imu_rate_hz)}},
                sim_args=sim_args, sim_nice=sim_nice, daemon_nice=daemon_nice,
                daemon_own_session=daemon_own_session, daemon_group_nice=daemon_group_nice)
    with sitl as s:
        # a slow simulator is waited for (its flight must be complete) until it is hopeless
        s.wait_for(lambda: sim_done_or_hopeless(s), 6.0 * flight_s / speed + 120, poll_s=0.5)
        # the flight is over; a daemon behind it works off its backlog (late, not lost) for up
        # to DRAIN_S, until its ATTITUDE reaches the last RAW_IMU's FC time
        t_drain0 = time.monotonic()
        fwd = s.tap.to_daemon
        last_imu_ms = fwd[-1][1].time_usec / 1000.0 if fwd else None
        drained = False
        while last_imu_ms is not None and s.daemon.poll() is None and time.monotonic() - t_drain0 < DRAIN_S:
            att = next((m for _, m in reversed(s.tap.from_daemon[-200:]) if m.get_type() == "ATTITUDE"), None)
            if att is not None and att.time_boot_ms >= last_imu_ms - 500.0:
                drained = True
                break
            time.sleep(0.5)
        drain_s = time.monotonic() - t_drain0
        c = _proc_cpu_s(s.daemon.pid) if s.daemon.poll() is None else None
        cpu["daemon"] = c if c is not None else cpu["daemon"]
    wall_s = time.monotonic() - t_wall0
    load1 = os.getloadavg()[0]
    divert_cmds = {20, 176, 192, 185}
    sent = [m for m in s.tap.sent_by_daemon("COMMAND_LONG") + s.tap.sent_by_daemon("COMMAND_INT")
            if m.command in divert_cmds]
    tr = load_truth_log(str(s.truth_log))
    clear = true_clearance_m(tr["lat_rad"], tr["lon_rad"], cfg)
    flying = tr["phase"] != 0
    log_text = s.log("daemon")
    stopped = {}
    events: dict[str, int] = {}
    for line in log_text.splitlines():
        if "msg=stopped" in line:
            stopped = _logfmt_fields(line)
        if " event=geofence_" in line:
            ev = _logfmt_fields(line).get("event", "?")
            events[ev] = events.get(ev, 0) + 1
    forwarded = len(s.tap.to_daemon)
    processed = int(stopped.get("imu_samples", -1))
    lat = attitude_latency_ms(s.tap)
    # the simulator's pace: FC time of the RAW_IMU stream against the tap's wall clock. A real FC
    # keeps real time; a simulator that fell behind it makes the daemon see FC-clock lags (and
    # declare reboots): such a flight measures the harness, not the daemon.
    fwd = s.tap.to_daemon
    sim_rate = ((fwd[-1][1].time_usec - fwd[0][1].time_usec) * 1e-6 / (fwd[-1][0] - fwd[0][0])
                if len(fwd) > 1 and fwd[-1][0] > fwd[0][0] else 0.0)
    worst_lag_s = 0.0
    if len(fwd) > 1:
        t_fc = np.array([m.time_usec for _, m in fwd]) * 1e-6
        t_w = np.array([t for t, _ in fwd])
        worst_lag_s = float(np.max((t_w - t_w[0]) - (t_fc - t_fc[0])))  # behind real time, s
    flown_s = float(tr["time_s"][-1]) if tr["time_s"].size else 0.0
    reboots = log_text.count("event=fc_reboot")
    return {"kind": kind, "seed": seed, "diverts_sent": len(sent), "commands": sorted({m.command for m in sent}),
            "min_true_clearance_m": float(np.min(clear[flying])) if flying.any() else None,
            "raw_imu_forwarded": forwarded, "imu_samples_processed": processed,
            "imu_samples_lost": (forwarded - processed) if processed >= 0 else None,
            "kernel_rx_drops": int(stopped.get("kernel_rx_drops", 0) or 0),
            "link_seq_lost": int(stopped.get("link_seq_lost", 0) or 0),
            "attitude_latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
            "attitude_latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
            "attitude_latency_max_ms": float(lat.max()) if lat.size else None,
            "geofence_events": events, "daemon_stopped_cleanly": bool(stopped),
            "daemon_declared_fc_reboots": reboots,
            "sim_flown_s": flown_s, "flight_complete": flown_s >= REST_S + flight_s - 1.0,
            "sim_speed_achieved": sim_rate, "sim_behind_real_time_max_s": worst_lag_s,
            # the daemon declares an FC reboot past 5 s of lag (mavlink_io/timebase.py reboot_lag_s)
            "valid": flown_s >= REST_S + flight_s - 1.0 and worst_lag_s < 5.0,
            "daemon_kept_up": bool(drained and lat.size and float(np.percentile(lat, 99)) < 1e3 * DAEMON_BEHIND_S),
            "wall_s": wall_s, "loadavg_1min_start": load0, "loadavg_1min_end": load1,
            "sim_aborted_behind_s": ABORT_LAG_S if lag["aborted"] else None,
            "daemon_backlog_drain_s": drain_s, "daemon_backlog_drained": drained,
            "imu_rate_hz": float(imu_rate_hz), "sim_base_rate_hz": float(base_hz),
            "sim_nice": sim_nice, "daemon_nice": daemon_nice, "daemon_own_session": daemon_own_session,
            "daemon_group_nice": daemon_group_nice,
            "fc_group_nice": _autogroup_nice(),
            "daemon_cpu_s": cpu["daemon"], "sim_cpu_s": cpu["sim"],
            "launch_azimuth_deg": sc["launcher"]["azimuth_deg"], "workdir": str(wd)}


# --- main ---------------------------------------------------------------------------------------

def _open_loop_summary(results: list[dict], prefix: str) -> dict:
    out = [r for r in results if r["kind"] == "outbound"]
    ins = [r for r in results if r["kind"] == "inside"]
    ok = [r for r in out if r["latch_time_s"] is not None and r["true_cross_time_s"] is not None
          and r["lead_time_s"] > 0]
    leads = [r["lead_time_s"] for r in out if r["lead_time_s"] is not None]
    ratios = [r["dr_error_at_latch_m"] / r["dr_sigma_major_at_latch_m"] for r in out
              if r["dr_error_at_latch_m"] is not None and r["dr_sigma_major_at_latch_m"]]
    return {f"{prefix}outbound_runs": len(out), f"{prefix}inside_runs": len(ins),
            f"{prefix}outbound_latched_before_true_crossing": len(ok),
            f"{prefix}dr_error_over_sigma_at_latch_max": max(ratios) if ratios else None,
            f"{prefix}dr_error_over_sigma_at_latch_rms": float(np.sqrt(np.mean(np.square(ratios)))) if ratios else None,
            f"{prefix}lead_time_min_s": min(leads) if leads else None,
            f"{prefix}lead_time_median_s": float(np.median(leads)) if leads else None,
            f"{prefix}inside_no_latch": sum(r["latch_time_s"] is None for r in ins)}


def _closed_loop_summary(results: list[dict], margin_m: float, prefix: str) -> dict:
    failed = [r for r in results if "error" in r]
    results = [r for r in results if "error" not in r]
    out = [r for r in results if r["kind"] == "outbound"]
    ins = [r for r in results if r["kind"] == "inside"]
    mins = [r["min_true_clearance_m"] for r in out + ins if r["min_true_clearance_m"] is not None]
    s = {f"{prefix}outbound_runs": len(out), f"{prefix}inside_runs": len(ins),
         f"{prefix}outbound_diverted": sum(r["diverts_sent"] > 0 for r in out),
         # an exit: the TRUE track outside the fence (< 0 m), or inside the 50 m margin (< margin)
         f"{prefix}fence_exits": sum(r["min_true_clearance_m"] is not None and r["min_true_clearance_m"] < 0.0
                                     for r in out + ins),
         f"{prefix}margin_violations": sum(r["min_true_clearance_m"] is not None
                                           and r["min_true_clearance_m"] < margin_m for r in out + ins),
         f"{prefix}min_true_clearance_m": min(mins) if mins else None,
         f"{prefix}inside_false_diverts": sum(r["diverts_sent"] > 0 for r in ins)}
    if failed:
        s[f"{prefix}flights_failed"] = len(failed)
    if results and "raw_imu_forwarded" in results[0]:
        valid = [r for r in results if r.get("valid")]
        lost = [r["imu_samples_lost"] for r in results if r["imu_samples_lost"] is not None]
        fwd = sum(r["raw_imu_forwarded"] for r in results)
        p99 = [r["attitude_latency_p99_ms"] for r in results if r["attitude_latency_p99_ms"] is not None]
        p50 = [r["attitude_latency_p50_ms"] for r in results if r["attitude_latency_p50_ms"] is not None]
        s.update({f"{prefix}flights_valid": len(valid),
                  f"{prefix}flights_sim_behind_real_time": sum(not r["valid"] for r in results),
                  f"{prefix}raw_imu_forwarded": fwd,
                  f"{prefix}imu_samples_lost": int(sum(lost)) if lost else None,
                  f"{prefix}imu_samples_lost_pct": 100.0 * sum(lost) / fwd if lost and fwd else None,
                  f"{prefix}kernel_rx_drops": sum(r["kernel_rx_drops"] for r in results),
                  f"{prefix}flights_daemon_backlog_not_drained": sum(not r.get("daemon_backlog_drained", True)
                                                                     for r in results),
                  f"{prefix}daemon_declared_fc_reboots": sum(r["daemon_declared_fc_reboots"] for r in results),
                  f"{prefix}attitude_latency_p50_median_ms": float(np.median(p50)) if p50 else None,
                  f"{prefix}attitude_latency_p99_max_ms": max(p99) if p99 else None,
                  f"{prefix}sim_speed_achieved_min": min(r["sim_speed_achieved"] for r in results),
                  f"{prefix}loadavg_1min_max": max(max(r["loadavg_1min_start"], r["loadavg_1min_end"])
                                                   for r in results)})
        cpu = [r["daemon_cpu_s"] / r["sim_flown_s"] for r in results
               if r.get("daemon_cpu_s") is not None and r["sim_flown_s"] > 0]
        s.update({f"{prefix}loadavg_1min_median": float(np.median([r["loadavg_1min_end"] for r in results])),
                  f"{prefix}daemon_cpu_s_per_flight_s_median": float(np.median(cpu)) if cpu else None})
        kept = [r for r in valid if r.get("daemon_kept_up")]
        s[f"{prefix}flights_valid_daemon_behind"] = len(valid) - len(kept)
        for k, sub in (("valid_", valid), ("valid_daemon_kept_up_", kept)):
            if sub:
                sub_mins = [r["min_true_clearance_m"] for r in sub if r["min_true_clearance_m"] is not None]
                sub_lost = [r["imu_samples_lost"] for r in sub if r["imu_samples_lost"] is not None]
                sub_p50 = [r["attitude_latency_p50_ms"] for r in sub if r["attitude_latency_p50_ms"] is not None]
                sub_p99 = [r["attitude_latency_p99_ms"] for r in sub if r["attitude_latency_p99_ms"] is not None]
                s.update({f"{prefix}{k}outbound_runs": sum(r["kind"] == "outbound" for r in sub),
                          f"{prefix}{k}inside_runs": sum(r["kind"] == "inside" for r in sub),
                          f"{prefix}{k}outbound_diverted": sum(r["diverts_sent"] > 0 for r in sub
                                                               if r["kind"] == "outbound"),
                          f"{prefix}{k}fence_exits": sum(m < 0.0 for m in sub_mins),
                          f"{prefix}{k}margin_violations": sum(m < margin_m for m in sub_mins),
                          f"{prefix}{k}min_true_clearance_m": min(sub_mins) if sub_mins else None,
                          f"{prefix}{k}inside_false_diverts": sum(r["diverts_sent"] > 0 for r in sub
                                                                  if r["kind"] == "inside"),
                          f"{prefix}{k}imu_samples_lost": int(sum(sub_lost)) if sub_lost else None,
                          f"{prefix}{k}raw_imu_forwarded": sum(r["raw_imu_forwarded"] for r in sub),
                          f"{prefix}{k}attitude_latency_p50_median_ms": float(np.median(sub_p50)) if sub_p50 else None,
                          f"{prefix}{k}attitude_latency_p99_max_ms": max(sub_p99) if sub_p99 else None})
    return s


def _line(mode: str, r: dict) -> str:
    if mode in ("pipeline", "offline"):
        lead = "-" if r["lead_time_s"] is None else f"{r['lead_time_s']:.1f} s"
        err = ("" if r["dr_error_at_latch_m"] is None else
               f"  DR error {r['dr_error_at_latch_m']:.0f} m (sigma {r['dr_sigma_major_at_latch_m']:.0f} m)")
        return f"latch {r['latch_time_s']}  true crossing {r['true_cross_time_s']}  lead {lead}{err}"
    if "error" in r:
        return f"FAILED: {r['error']}"
    line = f"diverts {r['diverts_sent']}  min true clearance {r['min_true_clearance_m']:.0f} m"
    if mode == "closed":
        return line + f" {r['actions']} {r['outcomes']}  modes {r['modes_seen']}"
    p50, p99 = r["attitude_latency_p50_ms"], r["attitude_latency_p99_ms"]
    return line + (f"  imu lost {r['imu_samples_lost']}/{r['raw_imu_forwarded']}  ATTITUDE latency p50/p99 "
                   f"{-1 if p50 is None else p50 / 1e3:.2f}/{-1 if p99 is None else p99 / 1e3:.2f} s  "
                   f"daemon cpu {r['daemon_cpu_s']} s  drained {r['daemon_backlog_drained']}  sim x{r['sim_speed_achieved']:.2f} "
                   f"behind {r['sim_behind_real_time_max_s']:.1f} s  reboots {r['daemon_declared_fc_reboots']}  "
                   f"load {r['loadavg_1min_start']:.1f}  {'valid' if r['valid'] else 'INVALID (sim behind)'}"
                   f"{'' if r.get('daemon_kept_up') else ', DAEMON BEHIND (not its own divert geometry)'}")


def _autogroup_nice() -> int | None:
    """This process's CPU group nice (/proc/self/autogroup "/autogroup-N nice X"), None without autogroup."""
    try:
        return int(Path("/proc/self/autogroup").read_text().split()[-1])
    except (OSError, ValueError, IndexError):
        return None


def _daemon_flight(kind: str, seed: int, opts: dict) -> dict:
    """One daemon-mode flight in a worker process: an error is a failed flight, reported as one.

    ``opts["fc_group_nice"]`` (not None): this worker starts a session of its own and gives its
    CPU group (kernel autogroup) that nice value: the simulator it starts and the UDP tap it runs
    (the FC and its wire) then compete with the daemon's group and the machine's others as one
    group above them, the stand-in for an FC's own CPU."""
    bench_dir = str(ROOT / "bench")
    if bench_dir not in sys.path:
        sys.path.insert(0, bench_dir)
    opts = dict(opts)
    fc_nice = opts.pop("fc_group_nice", None)
    try:
        if fc_nice is not None:
            os.setsid()
            Path("/proc/self/autogroup").write_text(str(int(fc_nice)))
        return run_daemon(kind, seed, **opts)
    except Exception as e:  # noqa: BLE001  (a flight that failed is counted, with its reason)
        return {"kind": kind, "seed": seed, "error": f"{type(e).__name__}: {e}", "valid": False}


def daemon_flights(flights: list[tuple[str, int]], opts: dict, jobs: int):
    """Yield run_daemon results as they finish, ``jobs`` flights at once (one process each: its
    own tap thread, simulator, daemon, free ports and work dir)."""
    import concurrent.futures as cf
    import multiprocessing as mp
    with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                max_tasks_per_child=1) as ex:
        futs = [ex.submit(_daemon_flight, kind, seed, opts) for kind, seed in flights]
        for f in cf.as_completed(futs):
            yield f.result()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 seeds per kind, shorter flights")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "geofence.json"))
    ap.add_argument("--mode", default="headline",
                    choices=("daemon", "pipeline", "offline", "closed", "headline", "all"),
                    help="headline = daemon + pipeline; offline/closed are truth-heading diagnostics")
    ap.add_argument("--load", default="both", choices=("idle", "busy", "both"),
                    help="daemon mode: as the machine is, and/or with two competing CPU-bound processes")
    ap.add_argument("--busy", action="store_true", help="same as --load busy")
    ap.add_argument("--seeds", type=int, default=None, help="seeds per scenario kind (default 20, quick 2)")
    ap.add_argument("--seed0", type=int, default=0, help="first seed")
    ap.add_argument("--speed", type=float, default=None, help="simulator speed (daemon default 1, closed 20)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="daemon mode: flights at once (each its own simulator, daemon, ports, work dir)")
    ap.add_argument("--imu-rate-hz", type=float, default=IMU_RATE_HZ,
                    help="daemon mode: RAW_IMU rate the operator asks of the FC (default 50, stock ArduPilot)")
    ap.add_argument("--sim-base-rate-hz", type=float, default=None,
                    help="daemon mode: the simulated FC's sensor rate (default 200 for 50 Hz RAW_IMU, 500 for 200 Hz)")
    root = os.geteuid() == 0
    from sitl import unit_nice
    ap.add_argument("--fc-nice", type=int, default=-15 if root else None,
                    help="daemon mode: CPU-group nice of the simulator and the UDP tap, the FC and its wire "
                         "(default -15 as root, above the daemon's group: a real FC has its own CPU; else inherited)")
    ap.add_argument("--daemon-nice", type=int, default=None,
                    help="daemon mode: nice value of the daemon within its own group (default: inherited)")
    ap.add_argument("--daemon-group-nice", type=int, default=unit_nice() if root else None,
                    help="daemon mode: nice of the daemon's CPU group, its own session (default as root: the "
                         "Nice= of systemd/azimuthd.service, standing in for the unit's cgroup CPUWeight)")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs must be >= 1, got {args.jobs}")
    sys.path.insert(0, str(ROOT / "bench"))
    n = args.seeds or (2 if args.quick else 20)
    seeds = range(args.seed0, args.seed0 + n)
    raw = fence_raw()
    margin = raw["margin_m"]
    flight_s = 160.0 if args.quick else 200.0
    summary: dict = {"seeds_per_kind": n, "seed0": args.seed0, "margin_m": margin, "fence_half_size_m": HALF_SIZE_M,
                     "flight_s": flight_s, "gnss_lost_after_launch_s": GNSS_LOST_AFTER_LAUNCH_S}
    runs: dict = {}
    modes = {"headline": ["pipeline", "daemon"], "all": ["pipeline", "daemon", "offline", "closed"]}.get(
        args.mode, [args.mode])
    loads = ["busy"] if args.busy else (["idle", "busy"] if args.load == "both" else [args.load])
    for mode in modes:
        for load in (loads if mode == "daemon" else [None]):
            label = mode if load is None else f"daemon_{load}"
            prefix = {"offline": "diagnostic_truth_heading.offline.",
                      "closed": "diagnostic_truth_heading.closed."}.get(mode, f"{label}.")
            res = []
            t0 = time.monotonic()
            flights = [(kind, seed) for kind in ("outbound", "inside") for seed in seeds]
            with CpuHogs(2 if load == "busy" else 0):
                if mode == "daemon":
                    opts = {"raw": raw, "speed": args.speed or 1.0, "flight_s": flight_s,
                            "imu_rate_hz": args.imu_rate_hz, "sim_base_rate_hz": args.sim_base_rate_hz,
                            "fc_group_nice": args.fc_nice, "daemon_nice": args.daemon_nice,
                            "daemon_group_nice": args.daemon_group_nice}
                    for r in daemon_flights(flights, opts, args.jobs):
                        print(f"{label:12s} {r['kind']:8s} seed {r['seed']:2d} az {r.get('launch_azimuth_deg', 0):5.1f}  "
                              f"{_line(mode, r)}", flush=True)
                        res.append(r)
                        # each flight is minutes: what has flown is kept if the run is stopped
                        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                        Path(args.json).write_text(json.dumps(
                            {"partial": True, "summary": {**summary, **_closed_loop_summary(res, margin, prefix)},
                             "runs": {**runs, label: res}}, indent=1, default=str))
                    res.sort(key=lambda r: (r["kind"] != "outbound", r["seed"]))
                    summary.update({f"{prefix}jobs": args.jobs, f"{prefix}imu_rate_hz": args.imu_rate_hz,
                                    f"{prefix}sim_base_rate_hz": res[0].get("sim_base_rate_hz") if res else None,
                                    f"{prefix}fc_group_nice": args.fc_nice, f"{prefix}daemon_nice": args.daemon_nice,
                                    f"{prefix}daemon_group_nice": args.daemon_group_nice,
                                    f"{prefix}daemon_own_session": True})
                for kind, seed in (flights if mode != "daemon" else []):
                    if mode == "pipeline":
                        r = run_pipeline(kind, seed, raw, flight_s=flight_s)
                    elif mode == "offline":
                        r = run_offline(kind, seed, raw)
                    else:
                        r = run_closed(kind, seed, raw, speed=args.speed or 20.0, flight_s=flight_s)
                    print(f"{label:12s} {kind:8s} seed {seed:2d} az {r.get('launch_azimuth_deg', 0):5.1f}  "
                          f"{_line(mode, r)}", flush=True)
                    res.append(r)
            summary.update(_open_loop_summary(res, prefix) if mode in ("pipeline", "offline")
                           else _closed_loop_summary(res, margin, prefix))
            summary[f"{prefix}wall_s"] = round(time.monotonic() - t0, 1)
            runs[label] = res
    if "offline" in modes or "closed" in modes:
        summary.update({"diagnostic_truth_heading.heading_bias_sigma_deg": HEADING_BIAS_SIGMA_DEG,
                        "diagnostic_truth_heading.heading_white_sigma_deg": HEADING_WHITE_SIGMA_DEG,
                        "diagnostic_truth_heading.heading_stated_sigma_deg": HEADING_STATED_SIGMA_DEG})
    print()
    print(f"{'figure':60s} value")
    for k, v in summary.items():
        print(f"{k:60s} {v}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"summary": summary, "runs": runs}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
