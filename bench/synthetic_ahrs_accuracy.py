"""Synthetic AHRS accuracy (METHODS.md B2) over simulated 10-minute flights with the FC's
reference lost 60 s after launch.

    python bench/synthetic_ahrs_accuracy.py [--quick] [--json PATH] [--flights N] [--silent]

Each flight: scenario ``runway_gnss_denied`` (sim.offline.simulate, consumer IMU at 100 Hz),
randomised runway heading, wind, and per airframe magnetometer hard/soft iron; GNSS is lost at
launch + 60 s; the flight lasts launch + 600 s. Flights are grouped by airframe (``--per-airframe``
flights each, same hard/soft iron): KF1's estimate of flight k is stored through the calibration
store's serialisation and applied in flight k+1 (the "at least one flight old" rule), so the first
flight of each airframe flies without a magnetometer calibration.

The loss is signalled (EKF horiz_pos_ok cleared at the sim's GNSS-loss time, as the simulator
sends it on the wire); ``--silent`` withholds the signal so that only the agreement test can
detect the FC's degradation. The simulator's field is IGRF + the WMM's error budget + a crustal
field (docs/SIMULATOR.md), not the estimators' WMM.

Headline (``--modes pipeline``): every flight through the daemon's own ``service.pipeline.Pipeline``
as its link feeds it (bench/sitl.py's pipeline_inputs; HEARTBEAT and EKF status from the FC's
own sensors, bench/_fc_status.py), with the operator's config for the scenario (site, date,
runway take-off, aligned mount) and KF1 kept across an airframe's flights by the daemon's own
``service.calibration_keeper.CalibrationKeeper`` (a state directory per airframe, one flight per
start). Scored: method B as the Pipeline runs it (``Pipeline.ahrs_out``: 50 Hz on mean
increments) and the attitude the daemon publishes (its fused heading, roll/pitch), at 25 Hz.
Diagnostic (``--modes per_method``): B2 alone at 100 Hz on the sensor events (the figures
before session 4), with a gyro-only baseline: the same attitude and gyro bias at the moment of
the loss, integrated with the gyros alone (estimators.strapdown).
Both decision halves run on a sealed run (bench/_truth_guard.py): truth only scores, from the
loss to the end of the flight (roll, pitch and heading error RMS and p95, deg).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from estimators.geomag import earth_field_ned_gauss  # noqa: E402
from estimators.mag_error_kf import kf1_from_dict, kf1_to_dict  # noqa: E402
from estimators.rotations import dcm_from_quat, euler_from_dcm  # noqa: E402
from estimators.strapdown import strapdown_init, strapdown_step  # noqa: E402
from estimators.synthetic_ahrs import (AirEvent, FcAttitudeEvent, FcStatusEvent, ImuEvent,  # noqa: E402
                                       SyntheticAhrsParams, synthetic_ahrs_init, synthetic_ahrs_step)
from sim.offline import simulate  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _fc_status import feed, merged_items  # noqa: E402
from _truth_guard import sealed  # noqa: E402

REST_S = 60.0
LOSS_AFTER_LAUNCH_S = 60.0
FLIGHT_S = 600.0
IMU_HZ = 100.0
SCORE_EVERY = 5
"""Outputs are scored at IMU_HZ / SCORE_EVERY = 20 Hz (the estimator runs on every sample)."""


def airframe_overrides(rng: np.random.Generator) -> dict:
    """Residual magnetometer errors of one airframe (after the FC's own compass calibration)."""
    hard = rng.normal(0.0, 0.02, 3)
    soft = np.eye(3) + np.diag(rng.normal(0.0, 0.02, 3))
    off = rng.normal(0.0, 0.01, (3, 3))
    np.fill_diagonal(off, 0.0)
    soft = soft + off
    return {"mag": {"hard_iron_gauss": hard.tolist(), "soft_iron": soft.tolist()}}


def flight_overrides(rng: np.random.Generator, airframe: dict) -> dict:
    wind_dir = rng.uniform(0.0, 2.0 * math.pi)
    wind = rng.uniform(0.0, 7.0)
    return {**airframe,
            "launcher": {"azimuth_deg": float(rng.uniform(0.0, 360.0)), "rest_s": REST_S},
            "wind": {"north_m_s": wind * math.cos(wind_dir), "east_m_s": wind * math.sin(wind_dir),
                     "gust_sigma_m_s": float(rng.uniform(0.3, 1.0))},
            "gnss": {"lost_at_s": REST_S + LOSS_AFTER_LAUNCH_S}}


def events_of(run, signalled: bool):
    """All sensor events of a run merged in time order (IMU first at equal times)."""
    ev = [(0.0, 0, FcStatusEvent(0.0, system_status=4, attitude_ok=True, horiz_pos_ok=True))]
    t, g, m = run.time_s, run.gyro_rad_s, run.mag_gauss
    ev += [(t[i], 1, ImuEvent(t[i], g[i], m[i])) for i in range(len(t))]
    ev += [(run.baro_time_s[i], 2, AirEvent(run.baro_time_s[i], run.press_abs_pa[i], run.press_diff_pa[i],
                                            run.temperature_k[i])) for i in range(len(run.baro_time_s))]
    ev += [(run.fc_time_s[i], 3, FcAttitudeEvent(run.fc_time_s[i], run.fc_euler_rad[i]))
           for i in range(len(run.fc_time_s))]
    if signalled and run.gnss_lost_time_s is not None:
        ev.append((run.gnss_lost_time_s, 0, FcStatusEvent(run.gnss_lost_time_s, horiz_pos_ok=False)))
    ev.sort(key=lambda e: (e[0], e[1]))
    return [e[2] for e in ev]


def wrap(a):
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


def run_flight(run, params: SyntheticAhrsParams, kf1_applied, kf1_learn, signalled: bool):
    st = synthetic_ahrs_init(params, kf1_learn=kf1_learn, kf1_applied=kf1_applied)
    n = len(run.time_s)
    est = np.full((n, 3), np.nan)
    sig = np.full((n, 3), np.nan)
    trusted = np.zeros(n, bool)
    k = 0
    loss_state = None
    t_loss = run.gnss_lost_time_s
    for ev in events_of(run, signalled):
        is_imu = isinstance(ev, ImuEvent)
        st, out = synthetic_ahrs_step(st, ev, params, output=is_imu and k % SCORE_EVERY == 0)
        if is_imu:
            if out is not None and out.valid:
                est[k] = (out.roll_rad, out.pitch_rad, out.heading_rad)
                sig[k] = (out.roll_sigma_rad, out.pitch_sigma_rad, out.heading_sigma_rad)
            trusted[k] = st.trusted
            if loss_state is None and ev.time_s >= t_loss and st.kf2 is not None:
                loss_state = (k, st.kf2.q_nav_from_body.copy(), st.kf2.gyro_bias_rad_s.copy())
            k += 1
    # gyro-only baseline from the loss: same attitude and bias, integrated with the gyros alone
    k0, q0, b0 = loss_state
    base = np.full((n, 3), np.nan)
    C_bs = np.array(params.C_body_from_sensor)
    sd = strapdown_init(q0, run.time_s[k0])
    sd = strapdown_step(sd, C_bs @ run.gyro_rad_s[k0] - b0, run.time_s[k0])[0]
    base[k0] = euler_from_dcm(dcm_from_quat(q0))
    for i in range(k0 + 1, n):
        sd, _ = strapdown_step(sd, C_bs @ run.gyro_rad_s[i] - b0, run.time_s[i])
        if np.isfinite(est[i, 0]):   # scored at the same samples as the estimator
            base[i] = euler_from_dcm(dcm_from_quat(sd.q_ref_from_sensor))
    return st, est, sig, base, trusted, k0


PIPELINE_SCORE_EVERY = 2
"""Pipeline solutions come at [heading] filter_rate_hz (50 Hz): every 2nd is scored (25 Hz)."""


def pipeline_decide(run, keeper) -> dict:
    """The daemon's decision half on a (sealed) run: KF1 from the calibration keeper as the
    daemon starts it, a Pipeline with the operator's config, fed as the link feeds it; the
    flight's KF1 estimate saved at the end as the daemon does. Per scored solution: method B's
    roll/pitch/heading and sigmas (nan while B has no valid output), the published roll/pitch/
    heading and sigmas, and the solution's IMU index. Reads no truth."""
    from service.config import validate
    from service.pipeline import Pipeline
    from sitl import scenario_site
    cfg = scenario_site("runway_gnss_denied")
    s = run.site
    cfg["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    kf1_learn, kf1_applied = keeper.start()
    p = Pipeline(validate({**cfg, "mavlink": {"imu_rate_hz": IMU_HZ}}), kf1_learn=kf1_learn, kf1_applied=kf1_applied)
    t = run.time_s
    nan = math.nan
    rows, n = [], 0
    for it in merged_items(run, 0.0):
        sol = feed(p, it)
        if sol is None:
            continue
        n += 1
        if n % PIPELINE_SCORE_EVERY:
            continue
        i = min(int(np.searchsorted(t, sol.time_fc_s - 1e-9)), len(t) - 1)
        b = p.ahrs_out
        bok = b is not None and b.valid
        fused_ok = sol.roll_rad is not None
        hok = sol.heading_valid
        rows.append((i, *((b.roll_rad, b.pitch_rad, b.heading_rad, b.roll_sigma_rad, b.pitch_sigma_rad,
                           b.heading_sigma_rad) if bok else (nan,) * 6),
                     bool(bok and b.reference_trusted),
                     sol.roll_rad if fused_ok else nan, sol.pitch_rad if fused_ok else nan,
                     sol.heading_rad if hok else nan, sol.heading_sigma_rad if hok else nan))
    keeper.save(p.kf1_estimate(), final=True)
    return {"rows": rows, "kf1_applied": kf1_applied is not None, "mag_status": p.mag_status}


def stats(err_deg):
    e = np.abs(err_deg[np.isfinite(err_deg)])
    if not e.size:
        return math.nan, math.nan
    return float(np.sqrt(np.mean(e ** 2))), float(np.percentile(e, 95))


def score_rows(run, rows: list, k0_time_s: float) -> dict:
    """Truth only scores: B's and the published attitude from the loss on, per flight."""
    r = np.array(rows, float)
    keep = run.time_s[r[:, 0].astype(int)] >= k0_time_s
    r = r[keep]
    truth = run.truth.euler_rad[r[:, 0].astype(int)]
    errs = {}
    for label, cols in (("b", (1, 2, 3)), ("fused", (8, 9, 10))):
        errs[label] = np.degrees(np.c_[wrap(r[:, cols[0]] - truth[:, 0]), r[:, cols[1]] - truth[:, 1],
                                       wrap(r[:, cols[2]] - truth[:, 2])])
    errs["b_sigma"] = np.degrees(r[:, 4:7])
    errs["fused_heading_sigma"] = np.degrees(r[:, 11])
    errs["b_trusted"] = r[:, 7] == 1.0
    return errs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="5 flights")
    ap.add_argument("--flights", type=int, default=None)
    ap.add_argument("--per-airframe", type=int, default=5)
    ap.add_argument("--silent", action="store_true", help="do not signal the GNSS loss (agreement test only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--flight-s", type=float, default=FLIGHT_S,
                    help=f"flight after launch, s (default {FLIGHT_S:.0f}; the loss stays at launch + {LOSS_AFTER_LAUNCH_S:.0f} s)")
    ap.add_argument("--modes", default="pipeline,per_method",
                    help="pipeline (the headline: the daemon's Pipeline) and/or per_method (B2 alone, diagnostic)")
    ap.add_argument("--json", default=str(pathlib.Path(__file__).resolve().parent / "results" / "synthetic_ahrs_accuracy.json"))
    a = ap.parse_args(argv)
    import tempfile
    from service.calibration_keeper import CalibrationKeeper
    modes = [m for m in a.modes.split(",") if m]
    if "pipeline" in modes and a.silent:
        ap.error("--silent is a per_method diagnostic (the Pipeline's FC status comes from bench/_fc_status.py)")
    n_flights = a.flights if a.flights is not None else (5 if a.quick else 50)
    t_start = time.time()
    rng = np.random.default_rng(a.seed)
    rows = []
    agg = {k: [] for k in ("roll", "pitch", "heading", "roll_base", "pitch_base", "heading_base")}
    pagg = {k: [] for k in ("b_roll", "b_pitch", "b_heading", "fused_roll", "fused_pitch", "fused_heading",
                            "b_nees_heading", "fused_nees_heading")}
    stored = None  # KF1 estimate of the previous flight of this airframe, as the store keeps it
    tmp = tempfile.TemporaryDirectory(prefix="azimuthd-b-bench-")
    fake_clock = [1.0e9]
    keeper = None
    for f in range(n_flights):
        if f % a.per_airframe == 0:
            airframe = airframe_overrides(rng)
            stored = None
            # the daemon's calibration keeper, one state directory per airframe; a day between flights
            keeper = CalibrationKeeper(pathlib.Path(tmp.name) / f"airframe{f // a.per_airframe}",
                                       clock=lambda: fake_clock[0])
        fake_clock[0] += 86400.0
        ov = flight_overrides(rng, airframe)
        run = simulate("runway_gnss_denied", seed=a.seed * 1000 + f, imu_grade="consumer", imu_rate_hz=IMU_HZ,
                       duration_s=REST_S + a.flight_s, overrides=ov)
        row = {"flight": f, "airframe_flight": f % a.per_airframe}
        msg = f"flight {f:2d}"
        if "pipeline" in modes:
            d = pipeline_decide(sealed(run), keeper)
            e = score_rows(run, d["rows"], run.gnss_lost_time_s)
            row["pipeline_kf1_applied"] = d["kf1_applied"]
            row["pipeline_mag_status"] = d["mag_status"]
            for j, name in enumerate(("roll", "pitch", "heading")):
                row[f"pipeline_b_{name}_rms_deg"], row[f"pipeline_b_{name}_p95_deg"] = stats(e["b"][:, j])
                row[f"pipeline_fused_{name}_rms_deg"], row[f"pipeline_fused_{name}_p95_deg"] = stats(e["fused"][:, j])
                pagg[f"b_{name}"].append(e["b"][:, j])
                pagg[f"fused_{name}"].append(e["fused"][:, j])
            row["pipeline_b_valid_fraction"] = float(np.mean(np.isfinite(e["b"][:, 2])))
            row["pipeline_fused_heading_valid_fraction"] = float(np.mean(np.isfinite(e["fused"][:, 2])))
            pagg["b_nees_heading"].append((e["b"][:, 2] / e["b_sigma"][:, 2]) ** 2)
            pagg["fused_nees_heading"].append((e["fused"][:, 2] / e["fused_heading_sigma"]) ** 2)
            msg += (f" | pipeline kf1={int(d['kf1_applied'])} B {row['pipeline_b_roll_rms_deg']:5.2f} "
                    f"{row['pipeline_b_pitch_rms_deg']:5.2f} {row['pipeline_b_heading_rms_deg']:5.2f} published "
                    f"{row['pipeline_fused_roll_rms_deg']:5.2f} {row['pipeline_fused_pitch_rms_deg']:5.2f} "
                    f"{row['pipeline_fused_heading_rms_deg']:5.2f}")
        if "per_method" in modes:
            s = run.site
            field = earth_field_ned_gauss(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"])
            params = SyntheticAhrsParams(variant="b2", C_body_from_sensor=s["C_body_from_sensor"],
                                         field_nav_gauss=tuple(field))
            applied = None if stored is None else kf1_from_dict(stored)
            st, est, sig, base, trusted, k0 = run_flight(sealed(run), params, applied, applied, not a.silent)
            stored = json.loads(json.dumps(kf1_to_dict(st.kf1_learn)))   # what the store would persist
            truth = run.truth.euler_rad          # scoring only
            sl = slice(k0, None)
            err = np.degrees(np.c_[wrap(est[sl, 0] - truth[sl, 0]), est[sl, 1] - truth[sl, 1],
                                   wrap(est[sl, 2] - truth[sl, 2])])
            errb = np.degrees(np.c_[wrap(base[sl, 0] - truth[sl, 0]), base[sl, 1] - truth[sl, 1],
                                    wrap(base[sl, 2] - truth[sl, 2])])
            row["calibrated"] = applied is not None
            for i, name in enumerate(("roll", "pitch", "heading")):
                row[f"{name}_rms_deg"], row[f"{name}_p95_deg"] = stats(err[:, i])
                row[f"{name}_base_rms_deg"], row[f"{name}_base_p95_deg"] = stats(errb[:, i])
                row[f"{name}_sigma_mean_deg"] = float(np.degrees(np.nanmean(sig[sl, i])))
                agg[name].append(err[:, i])
                agg[name + "_base"].append(errb[:, i])
            lost = np.nonzero(~trusted[k0:])[0]
            row["loss_detect_delay_s"] = float(lost[0] / IMU_HZ) if len(lost) else None
            row["mag_fused"], row["mag_rejected"] = st.kf2.n_mag_fused, st.kf2.n_mag_rejected
            row["air_fused"], row["air_rejected"] = st.kf2.n_air_fused, st.kf2.n_air_rejected
            msg += (f" | per-method cal={int(row['calibrated'])} {row['roll_rms_deg']:5.2f} {row['pitch_rms_deg']:5.2f} "
                    f"{row['heading_rms_deg']:5.2f} gyro-only {row['roll_base_rms_deg']:5.2f} "
                    f"{row['pitch_base_rms_deg']:5.2f} {row['heading_base_rms_deg']:6.2f}")
        rows.append(row)
        print(f"{msg}  ({time.time() - t_start:.0f} s)", flush=True)
    tmp.cleanup()
    res = {"bench": "synthetic_ahrs_accuracy", "variant": "b2", "flights": n_flights, "modes": modes,
           "headline": "pipeline", "scenario": "runway_gnss_denied", "imu_grade": "consumer", "imu_rate_hz": IMU_HZ,
           "loss_after_launch_s": LOSS_AFTER_LAUNCH_S, "flight_after_launch_s": a.flight_s,
           "loss_signalled": not a.silent, "scored": "from the reference loss to the end of the flight",
           "target_roll_pitch_rms_deg": 1.0, "target_heading_rms_deg": 2.0}
    if "pipeline" in modes:
        print(f"\nthe daemon's Pipeline ({n_flights} flights): {'':4s} {'rms':>7s} {'p95':>7s}  (deg)")
        for who in ("b", "fused"):
            for name in ("roll", "pitch", "heading"):
                r, p = stats(np.concatenate(pagg[f"{who}_{name}"]))
                res[f"pipeline_{who}_{name}_rms_deg"], res[f"pipeline_{who}_{name}_p95_deg"] = r, p
                print(f"  {'method B' if who == 'b' else 'published':10s} {name:8s} {r:7.2f} {p:7.2f}")
            nees = np.concatenate(pagg[f"{who}_nees_heading"])
            nees = nees[np.isfinite(nees)]
            res[f"pipeline_{who}_heading_nees"] = float(np.mean(nees)) if nees.size else math.nan
            res[f"pipeline_{who}_heading_within_2sigma"] = float(np.mean(nees <= 4.0)) if nees.size else math.nan
            res[f"pipeline_{who}_heading_within_3sigma"] = float(np.mean(nees <= 9.0)) if nees.size else math.nan
            res[f"pipeline_{who}_heading_valid_fraction"] = float(np.mean(np.isfinite(np.concatenate(pagg[f"{who}_heading"]))))
            print(f"  {'':10s} heading NEES {res[f'pipeline_{who}_heading_nees']:.2f}, within 2/3 sigma "
                  f"{100 * res[f'pipeline_{who}_heading_within_2sigma']:.0f} / {100 * res[f'pipeline_{who}_heading_within_3sigma']:.0f} %, "
                  f"valid {100 * res[f'pipeline_{who}_heading_valid_fraction']:.0f} %")
    if "per_method" in modes:
        print(f"\nper method (diagnostic) {'':2s} {'B2 rms':>8s} {'B2 p95':>8s} {'gyro rms':>9s} {'gyro p95':>9s}   (deg, {n_flights} flights)")
        for name in ("roll", "pitch", "heading"):
            r, p = stats(np.concatenate(agg[name]))
            rb, pb = stats(np.concatenate(agg[name + "_base"]))
            res[f"{name}_rms_deg"], res[f"{name}_p95_deg"] = r, p
            res[f"{name}_gyro_only_rms_deg"], res[f"{name}_gyro_only_p95_deg"] = rb, pb
            print(f"  {name:10s} {r:8.2f} {p:8.2f} {rb:9.2f} {pb:9.2f}")
        for label, sel in (("uncalibrated", [not r["calibrated"] for r in rows]), ("calibrated", [r["calibrated"] for r in rows])):
            idx = [i for i, s_ in enumerate(sel) if s_]
            if idx:
                for name in ("roll", "pitch", "heading"):
                    res[f"{name}_{label}_rms_deg"] = stats(np.concatenate([agg[name][i] for i in idx]))[0]
                print(f"  {label:13s} ({len(idx)} flights): heading rms {res[f'heading_{label}_rms_deg']:.2f} deg, "
                      f"roll {res[f'roll_{label}_rms_deg']:.2f}, pitch {res[f'pitch_{label}_rms_deg']:.2f}")
    res["runtime_s"] = time.time() - t_start
    res["per_flight"] = rows
    os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
    with open(a.json, "w") as fh:
        json.dump(res, fh, indent=1, default=lambda o: None if o is None else float(o))
    print(f"wrote {a.json} ({res['runtime_s']:.0f} s)")
    return res


if __name__ == "__main__":
    main()
