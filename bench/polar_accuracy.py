"""Accuracy of the polar-capable cascade (METHODS.md C) on simulated 10-minute flights.

    python bench/polar_accuracy.py [--quick] [--json PATH] [--seeds N] [--grades consumer,tactical]
                                   [--lats 45,78,85,89.9]

Each flight is ``sim.offline.simulate("polar_89", ...)`` (rail launch after 60 s at rest, climb,
legs, a 90-deg turn, a figure-eight at 40 deg of bank, return) at 100 Hz with the site latitude
overridden (longitude 30 E), per IMU grade and seed. The magnetometer's hard iron and launch-site
distortion are switched off: this bench measures method C with a compensated magnetometer (the
compensation, method D, is measured by bench/deviation_declination.py).

What the estimators get: the sensor arrays rotated into the body frame with the configured mount
(run.site), the gyro bias prior from levelling over the first 30 s at rest
(estimators/levelling.py), the site declination (sigma 0: the simulated field is the WMM
itself; in service the WMM sigma is added), and the launcher azimuth as
the heading filter's initial heading (sigma 2 deg: the airframe sits on the rail). The heading
filter's vertical-rate sigma comes from the site latitude and cruise speed
(``vertical_rate_sigma_for_site``). Truth is used only for scoring.

Figures per latitude (JSON keys carry units):
  roll_rms_deg, pitch_rms_deg        whole flight from levelling on (target <= 0.5 deg)
  roll_pitch_nees                    mean (err/sigma)^2 per axis (1 when the sigma is honest)
  heading_rms_valid_deg              heading error while the heading source is available
  heading_unavailable_s              time the source was declared unavailable
  heading_nees                       mean (err^2 / variance) over the whole flight
  heading_nees_valid                 the same while the source is available
  heading_sigma_end_deg              reported heading sigma at the end
  run_time_s                         estimator time per flight
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from estimators.geomag import earth_field  # noqa: E402
from estimators.polar_attitude import (PolarAttitudeParams, polar_attitude_estimate,  # noqa: E402
                                       polar_attitude_init, polar_attitude_step)
from estimators.polar_heading import (HeadingInputs, PolarHeadingParams,  # noqa: E402
                                      polar_heading_estimate, polar_heading_init,
                                      polar_heading_step, vertical_rate_sigma_for_site)
from sim.offline import simulate  # noqa: E402

from bench._prelaunch import levelling_at_rest  # noqa: E402

LATS_DEG = (45.0, 78.0, 85.0, 89.9)
RATE_HZ = 100.0
LEVEL_S = 30.0
SCORE_EVERY = 10          # score at 10 Hz
CRUISE_M_S = 22.0
DEG = math.pi / 180.0

# filter tuning per IMU grade (from the grades' data-sheet class, not from the simulator's draws)
ATT_PARAMS = {
    "consumer": PolarAttitudeParams(gyro_noise_rad_s_rt_hz=0.01 * DEG, gyro_bias_sigma_rad_s=0.05 * DEG,
                                    accel_noise_m_s2=0.05, accel_bias_sigma_m_s2=0.1,
                                    manoeuvre_speed_m_s=CRUISE_M_S),
    "tactical": PolarAttitudeParams(gyro_noise_rad_s_rt_hz=0.005 * DEG, gyro_bias_sigma_rad_s=0.002 * DEG,
                                    gyro_bias_init_sigma_rad_s=0.01 * DEG, accel_noise_m_s2=0.01,
                                    accel_bias_sigma_m_s2=0.02, manoeuvre_speed_m_s=CRUISE_M_S),
}
GYRO_BIAS_PRIOR_SIGMA = {"consumer": 0.02 * DEG, "tactical": 0.005 * DEG}
HEAD_GYRO = {"consumer": (0.01 * DEG, 0.05 * DEG), "tactical": (0.005 * DEG, 0.002 * DEG)}
MAG_NOISE = {"consumer": 0.004, "tactical": 0.001}      # gauss, incl. the 1 mG quantisation


def wrap_pi(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def run_flight(lat_deg: float, seed: int, grade: str, duration_s: float | None) -> dict:
    run = simulate("polar_89", seed=seed, imu_grade=grade, imu_rate_hz=RATE_HZ, duration_s=duration_s,
                   overrides={"site": {"lat_deg": lat_deg},
                              "mag": {"hard_iron_gauss": [0.0, 0.0, 0.0],
                                      "site_distortion_ned_gauss": [0.0, 0.0, 0.0]}})
    site = run.site
    C_bs = np.asarray(site["C_body_from_sensor"], float)
    gyro = run.gyro_rad_s @ C_bs.T
    accel = run.accel_m_s2 @ C_bs.T
    mag = run.mag_gauss @ C_bs.T
    t = run.time_s
    ef = earth_field(site["lat_deg"], site["lon_deg"], site["alt_m"], site["decimal_year"])
    decl = ef.declination_rad
    # the simulator's field IS the WMM main field (no model error), so the declination is exact
    # here and the filter is told so; in service the WMM sigma (0.35 deg at 45 N, 1.4 deg at
    # 85 N here) is given and adds to the reported heading sigma
    decl_sig = 0.0

    t_start = time.perf_counter()
    # pre-launch levelling: gyro bias prior (the mean rate at rest, Earth rate included)
    lev = levelling_at_rest(t, gyro, accel, LEVEL_S)
    pa = ATT_PARAMS[grade]
    sa = polar_attitude_init(pa, gyro_bias_rad_s=lev.gyro_mean_rad_s,
                             gyro_bias_sigma_rad_s=GYRO_BIAS_PRIOR_SIGMA[grade])
    arw, bsig = HEAD_GYRO[grade]
    ph = PolarHeadingParams(gyro_noise_rad_s_rt_hz=arw, gyro_bias_sigma_rad_s=bsig,
                            mag_noise_gauss=MAG_NOISE[grade],
                            mag_heading_floor_rad=math.radians(0.5),   # compensated magnetometer
                            vertical_rate_sigma_rad_s=vertical_rate_sigma_for_site(math.radians(lat_deg), CRUISE_M_S),
                            vertical_rate_tau_s=60.0)
    sh = polar_heading_init(math.radians(site["launcher_azimuth_deg"]), math.radians(2.0), ph,
                            gyro_bias_yz_rad_s=(0.0, lev.gyro_mean_rad_s[2]))

    est = None
    rows = []
    unavailable_s = 0.0
    for i in range(len(t)):
        sa, d = polar_attitude_step(sa, t[i], gyro[i], accel[i], pa)
        if d.updated:
            est = polar_attitude_estimate(sa)
        if est is None:
            continue
        m = mag[i] if np.all(np.isfinite(mag[i])) else None
        # the flights' hard iron and site anomaly are zeroed (a compensated magnetometer): no
        # uncalibrated-magnetometer term in C's sigma (polar_heading's consider term)
        sh, dh = polar_heading_step(sh, HeadingInputs(t[i], gyro[i], est.roll_rad, est.pitch_rad,
                                                      est.cov_roll_pitch_rad2, m, decl, decl_sig,
                                                      mag_residual_sigma_gauss=0.0), ph)
        if not sh.source_available and i > 0:
            unavailable_s += t[i] - t[i - 1]
        if i % SCORE_EVERY == 0:
            he = polar_heading_estimate(sh)
            c = est.cov_roll_pitch_rad2
            rows.append((i, est.roll_rad, est.pitch_rad, c[0, 0], c[1, 1], he.heading_rad,
                         he.variance_rad2, float(sh.source_available)))
    run_time = time.perf_counter() - t_start
    r = np.array(rows)
    idx = r[:, 0].astype(int)
    tru = run.truth.euler_rad[idx]
    er = wrap_pi(r[:, 1] - tru[:, 0])
    ep = wrap_pi(r[:, 2] - tru[:, 1])
    eh = wrap_pi(r[:, 5] - tru[:, 2])
    valid = r[:, 7] == 1.0
    nees_h = eh ** 2 / r[:, 6]
    return {
        "roll_rms_deg": math.degrees(math.sqrt(np.mean(er ** 2))),
        "pitch_rms_deg": math.degrees(math.sqrt(np.mean(ep ** 2))),
        "roll_max_deg": math.degrees(np.abs(er).max()),
        "pitch_max_deg": math.degrees(np.abs(ep).max()),
        "roll_pitch_nees": float(np.mean(np.concatenate([er ** 2 / r[:, 3], ep ** 2 / r[:, 4]]))),
        "heading_rms_valid_deg": math.degrees(math.sqrt(np.mean(eh[valid] ** 2))) if valid.any() else math.nan,
        "heading_rms_all_deg": math.degrees(math.sqrt(np.mean(eh ** 2))),
        "heading_unavailable_s": unavailable_s,
        "heading_nees": float(np.mean(nees_h)),
        "heading_nees_valid": float(np.mean(nees_h[valid])) if valid.any() else math.nan,
        "heading_sigma_end_deg": math.degrees(math.sqrt(r[-1, 6])),
        "horizontal_field_gauss": float(math.hypot(ef.e_ned_gauss[0], ef.e_ned_gauss[1])),
        "flight_s": float(t[-1] - t[0]),
        "run_time_s": run_time,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="1 seed, consumer grade only")
    ap.add_argument("--json", default=str(pathlib.Path(__file__).resolve().parent / "results" / "polar_accuracy.json"))
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--grades", default=None)
    ap.add_argument("--lats", default=",".join(str(x) for x in LATS_DEG))
    a = ap.parse_args()
    seeds = a.seeds if a.seeds is not None else (1 if a.quick else 3)
    grades = (a.grades or ("consumer" if a.quick else "consumer,tactical")).split(",")
    lats = [float(x) for x in a.lats.split(",")]
    out = {"bench": "polar_accuracy", "imu_rate_hz": RATE_HZ, "seeds": seeds, "scenario": "polar_89",
           "results": {}}
    keys = ("roll_rms_deg", "pitch_rms_deg", "roll_pitch_nees", "heading_rms_valid_deg",
            "heading_unavailable_s", "heading_nees", "heading_nees_valid", "heading_sigma_end_deg")
    print(f"{'grade':9s} {'lat':>5s} {'H_G':>6s} {'roll':>6s} {'pitch':>6s} {'rpNEES':>7s} {'hdg_v':>6s} "
          f"{'unav_s':>7s} {'hNEES':>7s} {'hNEESv':>7s} {'sig_end':>7s}  (deg RMS over {seeds} seed(s))")
    for grade in grades:
        for lat in lats:
            per = [run_flight(lat, s, grade, None) for s in range(seeds)]
            agg = {}
            for k in per[0]:
                vals = np.array([p[k] for p in per], float)
                if np.all(np.isnan(vals)):
                    agg[k] = math.nan
                    continue
                if k.endswith("_rms_deg") or k.endswith("rms_valid_deg") or k.endswith("rms_all_deg"):
                    agg[k] = float(np.sqrt(np.nanmean(vals ** 2)))
                elif k.endswith("_max_deg"):
                    agg[k] = float(np.nanmax(vals))
                else:
                    agg[k] = float(np.nanmean(vals))
            agg["roll_pitch_target_met"] = bool(max(agg["roll_rms_deg"], agg["pitch_rms_deg"]) <= 0.5)
            out["results"][f"{grade}_lat{lat:g}"] = {"grade": grade, "lat_deg": lat, **agg,
                                                     "per_seed": per}
            print(f"{grade:9s} {lat:5.1f} {agg['horizontal_field_gauss']:6.3f} "
                  + " ".join(f"{agg[k]:6.2f}" if "nees" not in k else f"{agg[k]:7.2f}" for k in keys))
    p = pathlib.Path(a.json)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=1))
    print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
