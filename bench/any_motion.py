"""Attitude and heading through any motion: azimuthd beside VQF and x-io Fusion on the same IMU.

    python bench/any_motion.py [--quick] [--json PATH] [--seeds N] [--seed0 S] [--scenarios a,b]

Scenarios (sim/scenarios/any_motion_*.toml, launcher type ``rig``: the attitude follows scripted
segments, the position stays put; consumer IMU at 100 Hz with the simulator's own Earth field,
sensor errors and, where set, motor vibration):

- undisturbed: ``handheld`` (slow and fast tumbles through every orientation, upside down, pitch
  +-90 deg, up to ~700 deg/s, pauses), ``aerobatic`` (loops, rolls, knife edge, split-S),
  ``hover_spin`` (a hovering multicopter's small tilts and yaw spins with vibration);
- disturbed: ``magnet_nearby`` (a stationary extra field of ~0.3 G for 20 s), ``magnet_attached``
  (a new hard iron of ~0.3 G from 40 s on).

Estimators, each fed the same decoded RAW_IMU stream (gyro, accel, mag in the sensor frame = body
FRD, no mount):
- ``azimuthd``: ``service.pipeline.Pipeline`` fed by bench/sitl.py's ``pipeline_inputs`` exactly
  as the daemon's link hands it, IMU samples only: a hand-held IMU has no FC attitude and no air
  data. Config an operator would write: the site and date, launch case "aligned", vehicle "hand",
  ``heading.use_fc_yaw = false``, the in-process solver. Its published ``q_nav_from_body``;
  heading/total are scored only where it publishes a valid heading (the share is reported as
  ``heading_available_fraction``), inclination wherever it publishes roll/pitch.
- ``vqf``: VQF (PyPI vqf) 9D, default parameters, online (``update`` per sample, ``getQuat9D``).
- ``fusion``: x-io Fusion (PyPI imufusion) ``Ahrs`` with default settings (NWU convention).
  Both peers get the samples turned into FLU (x, -y, -z: a level body starts near their identity),
  and their output quaternions (ENU resp. NWU from FLU) turned into q_nav_from_body (NED from FRD):
      q_NED_from_FRD = q_NED_from_E (x) q_E_from_FLU (x) q_FLU_from_FRD,
  q_FLU_from_FRD = q_NED_from_NWU = [0, 1, 0, 0] (180 deg about x), q_NED_from_ENU = [0, s, s, 0],
  s = 1/sqrt(2) (180 deg about (N + E)/sqrt(2): it swaps x, y and flips z).
  Their frame's north is magnetic (the horizontal field): the WMM declination at the site (what an
  operator knows, estimators.geomag) turns it to true, q_true = qz(D) (x) q_magnetic.

Metric (the benchmark's: RMS over the samples while moving, |true body rate| >= 5 deg/s, after
the first rest), with the error rotation in the navigation frame q_err = q_est (x) q_true^-1
(C_err = C_est C_true^T), split by swing-twist about the vertical, q_err = q_incl (x) q_head:
- heading error = the angle of the twist q_head = (w, 0, 0, z)/|.|: 2 atan2(z, w), signed, wrapped;
  a pure heading error qz(d) gives d;
- inclination error = the angle of the swing q_incl (axis horizontal): 2 acos(sqrt(w^2 + z^2)); it
  equals the angle between the vertical seen in the true and in the estimated body frame,
  acos(<C_true^T e_z, C_est^T e_z>) (the tilt error an accelerometer sees), so a pure heading
  error has none;
- total error = the angle of q_err, 2 acos(|w|).
Per set (undisturbed, disturbed) the RMS is the mean of the scenario RMS values (as the benchmark
averages its trials); the top-level ``<estimator>.*`` is the mean over all scenarios.

Sigma (azimuthd only, on the same moving rows): heading |error| <= k heading_sigma, inclination
<= k max(roll_sigma, pitch_sigma) (a 2-D error of per-axis sigma: a Rayleigh radius, 86.5 % within 2
and 98.9 % within 3 sigma if honest); ``within_3sigma_fraction`` pools both checks.

Install the peers with ``pip install -e '.[bench]'`` (vqf, imufusion); a peer that is missing is
reported as such and skipped.
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
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine
import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

IMU_HZ = 100.0
MOVING_RATE_RAD_S = math.radians(5.0)
SCENARIOS = {  # name -> disturbed
    "any_motion_handheld": False, "any_motion_aerobatic": False, "any_motion_hover_spin": False,
    "any_motion_magnet_nearby": True, "any_motion_magnet_attached": True,
}
ESTIMATORS = ("azimuthd", "vqf", "fusion")
PEER_PACKAGES = {"vqf": "vqf", "fusion": "imufusion"}
Q_FLU_FROM_FRD = np.array([0.0, 1.0, 0.0, 0.0])
Q_NED_FROM_NWU = Q_FLU_FROM_FRD
Q_NED_FROM_ENU = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])


# ---- quaternions (Hamilton, scalar first), vectorised over rows -----------------------------------
def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    p, q = np.broadcast_arrays(np.asarray(p, float), np.asarray(q, float))
    w1, x1, y1, z1 = np.moveaxis(p, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def qconj(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def qz(angle_rad) -> np.ndarray:
    a = np.asarray(angle_rad, float) / 2.0
    return np.stack([np.cos(a), 0 * a, 0 * a, np.sin(a)], -1)


def frd_to_flu(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float) * np.array([1.0, -1.0, -1.0])


def q_ned_frd_from_enu_flu(q_enu_from_flu: np.ndarray) -> np.ndarray:
    """VQF's output (ENU from FLU) as q_nav_from_body (NED from FRD)."""
    return qmul(qmul(Q_NED_FROM_ENU, q_enu_from_flu), Q_FLU_FROM_FRD)


def q_ned_frd_from_nwu_flu(q_nwu_from_flu: np.ndarray) -> np.ndarray:
    """Fusion's output (NWU from FLU) as q_nav_from_body (NED from FRD)."""
    return qmul(qmul(Q_NED_FROM_NWU, q_nwu_from_flu), Q_FLU_FROM_FRD)


def attitude_errors_rad(q_true: np.ndarray, q_est: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(heading (signed, est - true), inclination, total) errors in rad, per row (module docstring)."""
    e = qmul(q_est, qconj(q_true))
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    w, z = e[..., 0], e[..., 3]
    heading = np.angle(np.exp(2j * np.arctan2(z, w)))
    incl = 2.0 * np.arccos(np.clip(np.hypot(w, z), 0.0, 1.0))
    total = 2.0 * np.arccos(np.clip(np.abs(w), 0.0, 1.0))
    return heading, incl, total


def rms_deg(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.degrees(np.sqrt(np.mean(x * x)))) if len(x) else math.nan


# ---- the estimators -----------------------------------------------------------------------------
def operator_config(run) -> dict:
    from service.config import validate
    s = run.site
    return validate({
        "site": {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"],
                 "decimal_year": s["decimal_year"]},
        "launch": {"case": "aligned", "vehicle": "hand"},
        "heading": {"use_fc_yaw": False},
        "azimuth": {"solve_in_background": False},
        "mavlink": {"imu_rate_hz": IMU_HZ},
    })


def run_azimuthd(run) -> dict:
    """Per IMU sample: q (NaN rows where nothing was published), heading valid, sigmas (rad)."""
    from mavlink_io.samples import ImuSample
    from service.pipeline import Pipeline
    from sitl import pipeline_inputs
    items = [it for it in pipeline_inputs(run) if type(it) is ImuSample]  # no FC, no air data
    p = Pipeline(operator_config(run))
    n = len(run.time_s)
    q = np.full((n, 4), np.nan)
    sig = np.full((n, 3), np.nan)  # roll, pitch, heading
    hv = np.zeros(n, bool)
    got = np.zeros(n, bool)
    idx = {t: i for i, t in enumerate(run.time_s.tolist())}
    nan = math.nan
    for it in items:
        # the daemon's dispatch: a filter step's solution, else the last one brought to this sample
        # by the gyros (Pipeline.propagated_solution; service/daemon.py sends that between steps)
        sol = p.on_imu(it)
        if sol is None:
            sol = p.propagated_solution()
        p.drain_events()
        if sol is None:
            continue
        i = idx[sol.time_fc_s]
        got[i] = True
        if sol.q_nav_from_body is None or sol.roll_rad is None:
            continue
        q[i] = sol.q_nav_from_body
        sig[i] = (nan if sol.roll_sigma_rad is None else sol.roll_sigma_rad,
                  nan if sol.pitch_sigma_rad is None else sol.pitch_sigma_rad,
                  nan if sol.heading_sigma_rad is None else sol.heading_sigma_rad)
        hv[i] = bool(sol.heading_valid) and sol.heading_sigma_rad is not None
    # A sample without a solution (before levelling) holds the last one (what a consumer of the stream has).
    j = np.maximum.accumulate(np.where(got, np.arange(n), -1))
    held = j >= 0
    jj = np.maximum(j, 0)
    return {"q": np.where(held[:, None], q[jj], nan), "sigma": np.where(held[:, None], sig[jj], nan),
            "heading_valid": held & hv[jj], "solutions": int(got.sum())}


def _declination_rad(run) -> float:
    from estimators.geomag import declination_rad
    s = run.site
    return float(declination_rad(s["lat_deg"], s["lon_deg"], s["alt_m"], s["decimal_year"]))


def run_vqf(run) -> dict:
    from vqf import VQF
    f = VQF(1.0 / IMU_HZ)
    g, a, m = (np.ascontiguousarray(frd_to_flu(x)) for x in (run.gyro_rad_s, run.accel_m_s2, run.mag_gauss))
    out = np.empty((len(g), 4))
    for k in range(len(g)):
        f.update(g[k], a[k], m[k])
        out[k] = f.getQuat9D()
    return {"q": qmul(qz(_declination_rad(run)), q_ned_frd_from_enu_flu(out))}


def run_fusion(run) -> dict:
    import imufusion
    f = imufusion.Ahrs()
    f.set_sample_period(1.0 / IMU_HZ)
    g = np.degrees(frd_to_flu(run.gyro_rad_s))
    a = frd_to_flu(run.accel_m_s2) / 9.80665   # g
    m = frd_to_flu(run.mag_gauss) * 100.0      # uT (any unit)
    out = np.empty((len(g), 4))
    for k in range(len(g)):
        f.update(g[k], a[k], m[k])
        out[k] = f.get_quaternion()  # [w, x, y, z]
    return {"q": qmul(qz(_declination_rad(run)), q_ned_frd_from_nwu_flu(out))}


RUNNERS = {"azimuthd": run_azimuthd, "vqf": run_vqf, "fusion": run_fusion}


def peer_missing(name: str) -> str | None:
    import importlib.util
    pkg = PEER_PACKAGES.get(name)
    if pkg and importlib.util.find_spec(pkg) is None:
        return f"{name}: Python package {pkg!r} not installed (pip install -e '.[bench]' or pip install {pkg})"
    return None


# ---- scoring ------------------------------------------------------------------------------------
def score(run, est: dict) -> dict:
    tr = run.truth
    moving = np.linalg.norm(tr.omega_nb_body_rad_s, axis=1) >= MOVING_RATE_RAD_S
    q = est["q"]
    has = np.isfinite(q[:, 0])
    h, inc, tot = attitude_errors_rad(tr.q_nav_from_body, np.where(has[:, None], q, [1.0, 0, 0, 0]))
    hv = est.get("heading_valid", has)
    rows_h = moving & has & hv
    rows_i = moving & has
    out = {"moving_samples": int(moving.sum()),
           "total_rms_deg": rms_deg(tot[rows_h]), "heading_rms_deg": rms_deg(h[rows_h]),
           "inclination_rms_deg": rms_deg(inc[rows_i]),
           "heading_max_abs_deg": float(np.degrees(np.max(np.abs(h[rows_h])))) if rows_h.any() else math.nan,
           "inclination_max_deg": float(np.degrees(np.max(inc[rows_i]))) if rows_i.any() else math.nan,
           "heading_available_fraction": float(rows_h.sum() / max(1, moving.sum())),
           "attitude_available_fraction": float(rows_i.sum() / max(1, moving.sum()))}
    if "sigma" in est:
        s = est["sigma"]
        s_h = s[rows_h, 2]
        s_i = np.fmax(s[rows_i, 0], s[rows_i, 1])
        for kk in (2, 3):
            ok_h = np.abs(h[rows_h]) <= kk * s_h
            ok_i = inc[rows_i] <= kk * s_i
            out[f"heading_within_{kk}sigma_fraction"] = float(ok_h.mean()) if len(ok_h) else math.nan
            out[f"inclination_within_{kk}sigma_fraction"] = float(ok_i.mean()) if len(ok_i) else math.nan
            pooled = np.concatenate([ok_h, ok_i])
            out[f"within_{kk}sigma_fraction"] = float(pooled.mean()) if len(pooled) else math.nan
        out["heading_sigma_median_deg"] = float(np.degrees(np.nanmedian(s_h))) if len(s_h) else math.nan
    return out


SET_KEYS = ("total_rms_deg", "heading_rms_deg", "inclination_rms_deg", "heading_available_fraction",
            "within_2sigma_fraction", "within_3sigma_fraction")


def summarise(per: dict, names: list[str]) -> dict:
    out = {}
    for est in ESTIMATORS:
        rows = [per[n][est] for n in names if est in per[n] and "error" not in per[n][est]]
        if not rows:
            continue
        out[est] = {k: float(np.nanmean([r[k] for r in rows])) for k in SET_KEYS if all(k in r for r in rows)}
        out[est]["scenarios"] = len(rows)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="seed 0 only (default: seeds 0..--seeds-1)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--seed0", type=int, default=0, help="first seed (e.g. 100: seeds no default was chosen on)")
    ap.add_argument("--json", type=pathlib.Path, help="write the figures here")
    ap.add_argument("--scenarios", default=None,
                    help="comma-separated subset, short names (e.g. magnet_nearby,hover_spin; default: all five)")
    args = ap.parse_args(argv)
    scenarios = SCENARIOS
    if args.scenarios:
        want = ["any_motion_" + x.strip().removeprefix("any_motion_") for x in args.scenarios.split(",") if x.strip()]
        unknown = [w for w in want if w not in SCENARIOS]
        if unknown or not want:
            ap.error(f"--scenarios: unknown {[u.removeprefix('any_motion_') for u in unknown] or args.scenarios!r}; known: "
                     + ", ".join(n.removeprefix("any_motion_") for n in SCENARIOS))
        scenarios = {n: SCENARIOS[n] for n in want}
    from sim.offline import simulate
    seeds = [args.seed0] if args.quick else list(range(args.seed0, args.seed0 + max(1, args.seeds)))
    missing = {e: peer_missing(e) for e in ESTIMATORS if peer_missing(e)}
    for msg in missing.values():
        print(f"skipped {msg}")
    per: dict = {}
    t0 = time.monotonic()
    for name, disturbed in scenarios.items():
        rows = {e: [] for e in ESTIMATORS if e not in missing}
        for seed in seeds:
            run = simulate(name, seed=seed, imu_grade="consumer", imu_rate_hz=IMU_HZ)
            for e in rows:
                rows[e].append(score(run, RUNNERS[e](run)))
        short = name.removeprefix("any_motion_")
        per[short] = {"disturbed": disturbed}
        for e, rs in rows.items():
            per[short][e] = {k: float(np.nanmean([r[k] for r in rs])) for k in rs[0]}
        print(f"{short}: done ({time.monotonic() - t0:.0f} s)", file=sys.stderr)
    names = list(per)
    res = {"imu_rate_hz": IMU_HZ, "seeds": seeds, "moving_rate_threshold_deg_s": math.degrees(MOVING_RATE_RAD_S),
           "skipped": list(missing.values()), "scenarios": per,
           "undisturbed": summarise(per, [n for n in names if not per[n]["disturbed"]]),
           "disturbed": summarise(per, [n for n in names if per[n]["disturbed"]])}
    res.update(summarise(per, names))
    print(f"RMS error while moving (deg), consumer IMU {IMU_HZ:.0f} Hz, seeds {seeds}; azimuthd heading/total "
          f"only where it publishes a heading (avail = that share of moving samples)")
    print(f"{'scenario':<18} {'estimator':<9} {'total':>7} {'heading':>8} {'incl':>7} {'avail':>6} {'<=2sig':>7} {'<=3sig':>7}")
    for n in names + ["undisturbed", "disturbed", "all"]:
        src = per[n] if n in per else (res[n] if n != "all" else {e: res[e] for e in ESTIMATORS if e in res})
        for e in ESTIMATORS:
            r = src.get(e)
            if not r:
                continue
            f = lambda k, pct=False: (f"{100 * r[k]:.0f}%" if pct else f"{r[k]:.2f}") if k in r and math.isfinite(r[k]) else "-"  # noqa: E731
            print(f"{n:<18} {e:<9} {f('total_rms_deg'):>7} {f('heading_rms_deg'):>8} {f('inclination_rms_deg'):>7} "
                  f"{f('heading_available_fraction', True):>6} {f('within_2sigma_fraction', True):>7} "
                  f"{f('within_3sigma_fraction', True):>7}")
    if args.json:
        from service.replay import json_safe
        args.json.write_text(json.dumps(json_safe(res), indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
