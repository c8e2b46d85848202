"""Accuracy of the polar-capable cascade (METHODS.md C) on simulated 10-minute flights.

    python bench/polar_accuracy.py [--quick] [--json PATH] [--seeds N] [--grades consumer,tactical]
                                   [--lats 45,78,85,89.9]

Each flight is ``sim.offline.simulate("polar_89", ...)`` (rail launch after 60 s at rest, climb,
legs, a 90-deg turn, a figure-eight at 40 deg of bank, return) at 100 Hz with the site latitude
overridden (longitude 30 E), per IMU grade and seed. The magnetometer's hard iron and launch-site
distortion are switched off: this bench measures method C with a compensated magnetometer (the
compensation, method D, is measured by bench/deviation_declination.py). The simulator's field is
IGRF + the WMM's error budget + a crustal field (docs/SIMULATOR.md), not the estimators' WMM.

Headline (``pipeline``): every flight through the daemon's own ``service.pipeline.Pipeline`` as
its link feeds it (bench/sitl.py's pipeline_inputs + the FC's status from its own sensors,
bench/_fc_status.py), with the config an operator writes (site, date, launcher, mount, cruise
speed; ``[heading] uncalibrated_hard_iron_gauss = 0`` and ``uncalibrated_soft_iron = 0``: the
magnetometer is compensated, as the flights' is: no hard iron, no soft iron, axes aligned with the
IMU's; before session 5 the soft-iron term was no key and stayed at its 1 % prior here: part of
C's too-wide sigma, docs/SIGMAS.md). Scored:
the published roll/pitch (C's attitude filter once levelled) and C's heading filter as the
Pipeline runs it (50 Hz on mean increments, the magnetometer usability check, the WMM
declination and its sigma); the fused heading the daemon publishes is shown beside it.

Diagnostic (``per_method``): C's two filters alone at 100 Hz with grade-specific tuning, the gyro
bias prior from levelling over the first 30 s at rest (estimators/levelling.py), the WMM
declination with its sigma; the heading filter waits for its first magnetometer measurement as in
the daemon (it was seeded from the true launcher azimuth before session 4: truth only scores).
Both decision halves run on a sealed run (bench/_truth_guard.py, tests/test_truth_isolation.py).

Figures per latitude (JSON keys carry units):
  roll_rms_deg, pitch_rms_deg        whole flight from levelling on (target <= 0.5 deg)
  roll_pitch_nees                    mean (err/sigma)^2 per axis (1 when the sigma is honest)
  heading_rms_valid_deg              heading error while the heading source is available
  heading_unavailable_s              time the source was declared unavailable
  heading_nees                       mean (err^2 / variance) over the whole flight
  heading_nees_valid                 the same while the source is available
  heading_within_2sigma_valid, heading_within_3sigma_valid
                                     share of samples within 2 / 3 reported sigmas while available
  heading_sigma_end_deg              reported heading sigma at the end
  heading_fused_rms_deg               the daemon's published heading where valid (pipeline only)
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
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402

from bench._prelaunch import levelling_at_rest  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _fc_status import feed, merged_items  # noqa: E402
from _truth_guard import sealed  # noqa: E402
from sitl import scenario_site  # noqa: E402

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


def simulate_flight(lat_deg: float, seed: int, grade: str, duration_s: float | None):
    return simulate("polar_89", seed=seed, imu_grade=grade, imu_rate_hz=RATE_HZ, duration_s=duration_s,
                    overrides={"site": {"lat_deg": lat_deg},
                               "mag": {"hard_iron_gauss": [0.0, 0.0, 0.0],
                                       "site_distortion_ned_gauss": [0.0, 0.0, 0.0]}})


def pipeline_decide(run) -> list:
    """The daemon's decision half on a (sealed) run: the Pipeline with the operator's config.
    Rows at 10 Hz: (IMU index, roll, pitch, var roll, var pitch, C heading, C variance, C source
    available, fused heading or nan, fused sigma or nan)."""
    cfg = scenario_site("polar_89")
    cfg["site"]["lat_deg"] = float(run.site["lat_deg"])
    cfg["heading"] = {"cruise_speed_m_s": CRUISE_M_S, "uncalibrated_hard_iron_gauss": 0.0,
                      "uncalibrated_soft_iron": 0.0}
    p = Pipeline(validate({**cfg, "mavlink": {"imu_rate_hz": RATE_HZ}}))
    t = run.time_s
    rows, n = [], 0
    for it in merged_items(run, 0.0):
        sol = feed(p, it)
        if sol is None:
            continue
        n += 1
        if n % (SCORE_EVERY // 2) or sol.roll_rad is None:   # solutions at 50 Hz: score at 10 Hz
            continue
        i = min(int(np.searchsorted(t, sol.time_fc_s - 1e-9)), len(t) - 1)
        he = polar_heading_estimate(p.polar_hdg)
        ok = sol.heading_valid
        rows.append((i, sol.roll_rad, sol.pitch_rad, sol.roll_sigma_rad ** 2, sol.pitch_sigma_rad ** 2,
                     he.heading_rad if he.initialised else math.nan,
                     he.variance_rad2 if he.initialised else math.nan,
                     float(bool(p.polar_hdg.source_available)),
                     sol.heading_rad if ok else math.nan, sol.heading_sigma_rad if ok else math.nan))
    return rows


def per_method_decide(run, grade: str) -> list:
    """Diagnostic: C's filters alone on a (sealed) run at the IMU rate; rows as pipeline_decide's."""
    site = run.site
    lat_deg = site["lat_deg"]
    C_bs = np.asarray(site["C_body_from_sensor"], float)    # the configured mount
    gyro = run.gyro_rad_s @ C_bs.T
    accel = run.accel_m_s2 @ C_bs.T
    mag = run.mag_gauss @ C_bs.T
    t = run.time_s
    ef = earth_field(site["lat_deg"], site["lon_deg"], site["alt_m"], site["decimal_year"])
    decl = ef.declination_rad
    # the WMM's own 1-sigma declination error (its technical report's error model): the simulated
    # field is IGRF + that error budget + a crustal field, not the WMM
    decl_sig = ef.declination_sigma_rad if math.isfinite(ef.declination_sigma_rad) else 0.0
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
    # no heading prior: the filter starts at its first magnetometer measurement, as in the daemon
    sh = polar_heading_init(params=ph, gyro_bias_yz_rad_s=(0.0, lev.gyro_mean_rad_s[2]))
    est = None
    rows = []
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
        if i % SCORE_EVERY == 0:
            he = polar_heading_estimate(sh)
            c = est.cov_roll_pitch_rad2
            rows.append((i, est.roll_rad, est.pitch_rad, c[0, 0], c[1, 1],
                         he.heading_rad if he.initialised else math.nan,
                         he.variance_rad2 if he.initialised else math.nan,
                         float(sh.source_available), math.nan, math.nan))
    return rows


def score(run, rows: list, run_time_s: float) -> dict:
    """Truth only scores: the rows of a decision half against the simulator's truth."""
    r = np.array(rows, float)
    idx = r[:, 0].astype(int)
    t = run.time_s
    dt = np.diff(t[idx], prepend=t[idx[0]])
    tru = run.truth.euler_rad[idx]
    er = wrap_pi(r[:, 1] - tru[:, 0])
    ep = wrap_pi(r[:, 2] - tru[:, 1])
    eh = wrap_pi(r[:, 5] - tru[:, 2])
    init = np.isfinite(r[:, 5])
    valid = (r[:, 7] == 1.0) & init
    nees_h = eh ** 2 / r[:, 6]
    ef = np.abs(wrap_pi(r[:, 8] - tru[:, 2]))
    fused = np.isfinite(ef)
    site = run.site
    field = earth_field(site["lat_deg"], site["lon_deg"], site["alt_m"], site["decimal_year"])
    rms = lambda e: math.degrees(math.sqrt(np.mean(e ** 2))) if e.size else math.nan  # noqa: E731
    return {
        "roll_rms_deg": rms(er), "pitch_rms_deg": rms(ep),
        "roll_max_deg": math.degrees(np.abs(er).max()), "pitch_max_deg": math.degrees(np.abs(ep).max()),
        "roll_pitch_nees": float(np.mean(np.concatenate([er ** 2 / r[:, 3], ep ** 2 / r[:, 4]]))),
        "heading_rms_valid_deg": rms(eh[valid]),
        "heading_rms_all_deg": rms(eh[init]),
        "heading_unavailable_s": float(np.sum(dt[~valid])),
        "heading_nees": float(np.mean(nees_h[init])) if init.any() else math.nan,
        "heading_nees_valid": float(np.mean(nees_h[valid])) if valid.any() else math.nan,
        "heading_within_2sigma_valid": float(np.mean(nees_h[valid] <= 4.0)) if valid.any() else math.nan,
        "heading_within_3sigma_valid": float(np.mean(nees_h[valid] <= 9.0)) if valid.any() else math.nan,
        "heading_sigma_end_deg": math.degrees(math.sqrt(r[-1, 6])) if init[-1] else math.nan,
        "heading_fused_rms_deg": rms(ef[fused]),
        "heading_fused_valid_fraction": float(np.mean(fused)) if np.isfinite(r[:, 8]).any() else math.nan,
        "horizontal_field_gauss": float(math.hypot(field.e_ned_gauss[0], field.e_ned_gauss[1])),
        "flight_s": float(t[-1] - t[0]),
        "run_time_s": run_time_s,
    }


def run_flight(lat_deg: float, seed: int, grade: str, duration_s: float | None, mode: str = "pipeline") -> dict:
    """One flight: simulate, decide on the sealed run (``mode`` pipeline or per_method), score."""
    run = simulate_flight(lat_deg, seed, grade, duration_s)
    t0 = time.perf_counter()
    rows = pipeline_decide(sealed(run)) if mode == "pipeline" else per_method_decide(sealed(run), grade)
    return score(run, rows, time.perf_counter() - t0)


def aggregate(per: list[dict]) -> dict:
    agg = {}
    for k in per[0]:
        vals = np.array([p[k] for p in per], float)
        if np.all(np.isnan(vals)):
            agg[k] = math.nan
        elif "_rms_" in k:
            agg[k] = float(np.sqrt(np.nanmean(vals ** 2)))
        elif k.endswith("_max_deg"):
            agg[k] = float(np.nanmax(vals))
        else:
            agg[k] = float(np.nanmean(vals))
    agg["roll_pitch_target_met"] = bool(max(agg["roll_rms_deg"], agg["pitch_rms_deg"]) <= 0.5)
    return agg


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="1 seed, consumer grade only, 300 s flights")
    ap.add_argument("--json", default=str(pathlib.Path(__file__).resolve().parent / "results" / "polar_accuracy.json"))
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--seed-base", type=int, default=0)
    ap.add_argument("--duration-s", type=float, default=None,
                    help="flight length from the simulator's start, s (default 600; --quick 300; 60 s on the rail)")
    ap.add_argument("--grades", default=None)
    ap.add_argument("--lats", default=",".join(str(x) for x in LATS_DEG))
    ap.add_argument("--modes", default="pipeline,per_method",
                    help="pipeline (the headline: the daemon's Pipeline) and/or per_method (C alone, diagnostic)")
    a = ap.parse_args()
    seeds = a.seeds if a.seeds is not None else (1 if a.quick else 3)
    grades = (a.grades or ("consumer" if a.quick else "consumer,tactical")).split(",")
    lats = [float(x) for x in a.lats.split(",")]
    modes = [m for m in a.modes.split(",") if m]
    duration = a.duration_s if a.duration_s is not None else (300.0 if a.quick else None)
    out = {"bench": "polar_accuracy", "imu_rate_hz": RATE_HZ, "seeds": seeds, "seed_base": a.seed_base,
           "scenario": "polar_89", "flight_s": duration or 600.0, "headline": "pipeline", "results": {}}
    keys = ("roll_rms_deg", "pitch_rms_deg", "roll_pitch_nees", "heading_rms_valid_deg",
            "heading_unavailable_s", "heading_nees_valid", "heading_within_2sigma_valid",
            "heading_within_3sigma_valid", "heading_sigma_end_deg",
            "heading_fused_rms_deg")
    print(f"{'mode':10s} {'grade':9s} {'lat':>5s} {'H_G':>6s} {'roll':>6s} {'pitch':>6s} {'rpNEES':>7s} {'hdg_v':>6s} "
          f"{'unav_s':>7s} {'hNEESv':>7s} {'h<2s':>7s} {'h<3s':>7s} {'sig_end':>7s} {'fused':>6s}  (deg RMS over {seeds} seed(s))")
    for mode in modes:
        for grade in grades:
            for lat in lats:
                per = [run_flight(lat, s, grade, duration, mode) for s in range(a.seed_base, a.seed_base + seeds)]
                agg = aggregate(per)
                out["results"][f"{mode}/{grade}_lat{lat:g}"] = {"mode": mode, "grade": grade, "lat_deg": lat, **agg,
                                                                "per_seed": per}
                print(f"{mode:10s} {grade:9s} {lat:5.1f} {agg['horizontal_field_gauss']:6.3f} "
                      + " ".join(f"{agg[k]:6.2f}" if "nees" not in k and "sigma_valid" not in k
                                 else f"{agg[k]:7.2f}" for k in keys), flush=True)
    p = pathlib.Path(a.json)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=1))
    print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
