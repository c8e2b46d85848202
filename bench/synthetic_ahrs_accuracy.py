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
detect the FC's degradation.

Scored from the loss to the end of the flight against the simulator's truth: roll, pitch and
heading error RMS and p95 (deg) for B2, and a gyro-only baseline: the same attitude and gyro
bias at the moment of the loss, integrated with the gyros alone (estimators.strapdown).
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


def stats(err_deg):
    e = np.abs(err_deg[np.isfinite(err_deg)])
    return float(np.sqrt(np.mean(e ** 2))), float(np.percentile(e, 95))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="5 flights")
    ap.add_argument("--flights", type=int, default=None)
    ap.add_argument("--per-airframe", type=int, default=5)
    ap.add_argument("--silent", action="store_true", help="do not signal the GNSS loss (agreement test only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=str(pathlib.Path(__file__).resolve().parent / "results" / "synthetic_ahrs_accuracy.json"))
    a = ap.parse_args(argv)
    n_flights = a.flights if a.flights is not None else (5 if a.quick else 50)
    t_start = time.time()
    rng = np.random.default_rng(a.seed)
    rows = []
    agg = {k: [] for k in ("roll", "pitch", "heading", "roll_base", "pitch_base", "heading_base")}
    stored = None  # KF1 estimate of the previous flight of this airframe, as the store keeps it
    for f in range(n_flights):
        if f % a.per_airframe == 0:
            airframe = airframe_overrides(rng)
            stored = None
        ov = flight_overrides(rng, airframe)
        run = simulate("runway_gnss_denied", seed=a.seed * 1000 + f, imu_grade="consumer", imu_rate_hz=IMU_HZ,
                       duration_s=REST_S + FLIGHT_S, overrides=ov)
        s = run.site
        field = earth_field_ned_gauss(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"])
        params = SyntheticAhrsParams(variant="b2", C_body_from_sensor=s["C_body_from_sensor"],
                                     field_nav_gauss=tuple(field))
        applied = None if stored is None else kf1_from_dict(stored)
        st, est, sig, base, trusted, k0 = run_flight(run, params, applied, applied, not a.silent)
        stored = json.loads(json.dumps(kf1_to_dict(st.kf1_learn)))   # what the store would persist
        truth = run.truth.euler_rad
        sl = slice(k0, None)
        err = np.degrees(np.c_[wrap(est[sl, 0] - truth[sl, 0]), est[sl, 1] - truth[sl, 1],
                               wrap(est[sl, 2] - truth[sl, 2])])
        errb = np.degrees(np.c_[wrap(base[sl, 0] - truth[sl, 0]), base[sl, 1] - truth[sl, 1],
                                wrap(base[sl, 2] - truth[sl, 2])])
        row = {"flight": f, "airframe_flight": f % a.per_airframe, "calibrated": applied is not None}
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
        rows.append(row)
        print(f"flight {f:2d} cal={int(row['calibrated'])} roll {row['roll_rms_deg']:5.2f} pitch {row['pitch_rms_deg']:5.2f} "
              f"heading {row['heading_rms_deg']:5.2f} deg rms | gyro-only {row['roll_base_rms_deg']:5.2f} "
              f"{row['pitch_base_rms_deg']:5.2f} {row['heading_base_rms_deg']:6.2f} | detect "
              f"{row['loss_detect_delay_s']} s | air {row['air_fused']}/{row['air_rejected']} mag "
              f"{row['mag_fused']}/{row['mag_rejected']}  ({time.time() - t_start:.0f} s)", flush=True)
    res = {"bench": "synthetic_ahrs_accuracy", "variant": "b2", "flights": n_flights,
           "scenario": "runway_gnss_denied", "imu_grade": "consumer", "imu_rate_hz": IMU_HZ,
           "loss_after_launch_s": LOSS_AFTER_LAUNCH_S, "flight_after_launch_s": FLIGHT_S,
           "loss_signalled": not a.silent, "scored": "from the reference loss to the end of the flight",
           "target_roll_pitch_rms_deg": 1.0, "target_heading_rms_deg": 2.0}
    print(f"\n{'':10s} {'B2 rms':>8s} {'B2 p95':>8s} {'gyro rms':>9s} {'gyro p95':>9s}   (deg, {n_flights} flights)")
    for name in ("roll", "pitch", "heading"):
        r, p = stats(np.concatenate(agg[name]))
        rb, pb = stats(np.concatenate(agg[name + "_base"]))
        res[f"{name}_rms_deg"], res[f"{name}_p95_deg"] = r, p
        res[f"{name}_gyro_only_rms_deg"], res[f"{name}_gyro_only_p95_deg"] = rb, pb
        print(f"{name:10s} {r:8.2f} {p:8.2f} {rb:9.2f} {pb:9.2f}")
    for label, sel in (("uncalibrated", [not r["calibrated"] for r in rows]), ("calibrated", [r["calibrated"] for r in rows])):
        idx = [i for i, s_ in enumerate(sel) if s_]
        if idx:
            for name in ("roll", "pitch", "heading"):
                res[f"{name}_{label}_rms_deg"] = stats(np.concatenate([agg[name][i] for i in idx]))[0]
            print(f"{label:13s} ({len(idx)} flights): heading rms {res[f'heading_{label}_rms_deg']:.2f} deg, "
                  f"roll {res[f'roll_{label}_rms_deg']:.2f}, pitch {res[f'pitch_{label}_rms_deg']:.2f}")
    res["runtime_s"] = time.time() - t_start
    res["per_flight"] = rows
    os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
    with open(a.json, "w") as fh:
        json.dump(res, fh, indent=1)
    print(f"wrote {a.json} ({res['runtime_s']:.0f} s)")
    return res


if __name__ == "__main__":
    main()
