"""Method A's heading error and sigma after its fit window (issue 18 item 3), on the flights of
bench/synthetic_ahrs_accuracy.py through the daemon's Pipeline.

    python bench/azimuth_in_run_bias.py [--flights N] [--flight-s S] [--json PATH]

Flight k is synthetic_ahrs_accuracy's flight k (same seeds, airframes, KF1 carried by the
calibration keeper; its pipeline_decide, plus A's output). Every 0.5 s while A has a solution:
A's heading and its published sigma, the last magnetometer sample the solution used (t_last).
Decisions run on the sealed run; truth only scores. Printed and written: per 50-s window the
error RMS and the mean sigma under A's model with and without its after-the-window term, and
under the alternative in-run bias models (docs/SIGMAS.md, Method A after its fit window):
  constant change (the code):  var += (sigma_b T)^2,                T = t - t_last
  rate random walk q:          var += q T^3 / 3
  random walk + window:        var += q (W T^2 / 3 + T^3 / 3),      W = t_last - launch
NEES and share within 3 sigma per model and flight.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import synthetic_ahrs_accuracy as S  # noqa: E402
from _fc_status import feed, merged_items  # noqa: E402
from _truth_guard import sealed  # noqa: E402
from sim.offline import simulate  # noqa: E402

Q_DEG2_S3 = (1e-6, 3e-6, 1e-5, 1.33e-4)
"""Rate random walks tried, (deg/s)^2/s; 1.33e-4 = C's in-run process 2 (0.2 deg/s)^2 / 600 s."""


def decide(run, keeper) -> tuple[list, dict]:
    """A's output through the Pipeline on a sealed run, every 25th solution (0.5 s). Reads no truth."""
    import estimators.azimuth as az
    from service.config import validate
    from service.pipeline import Pipeline
    from sitl import scenario_site
    cfg = scenario_site("runway_gnss_denied")
    s = run.site
    cfg["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    kl, ka = keeper.start()
    p = Pipeline(validate({**cfg, "mavlink": {"imu_rate_hz": S.IMU_HZ}}), kf1_learn=kl, kf1_applied=ka)
    t = run.time_s
    rows, n = [], 0
    for it in merged_items(run, 0.0):
        sol = feed(p, it)
        if sol is None:
            continue
        n += 1
        if n % 25:
            continue
        a, st = p.azimuth_out, p.azimuth
        if a is None or not a.valid or st.solution is None:
            continue
        i = min(int(np.searchsorted(t, sol.time_fc_s - 1e-9)), len(t) - 1)
        last = max((r.time_s for r in st.samples if r.time_s <= st.solution.time_s), default=math.nan)
        rows.append(dict(i=i, t=float(t[i]), heading_rad=a.heading_rad, sigma_rad=a.heading_sigma_rad,
                         last_sample_s=last, launch_s=st.launch_time_s,
                         fit_sigma_rad=az._heading_now(st, st.solution)[1]))
    keeper.save(p.kf1_estimate(), final=True)
    pa = p.azimuth.params
    return rows, dict(gyro_bias_sigma_rad_s=pa.gyro_bias_sigma_rad_s, max_fit_samples=pa.max_fit_samples,
                      has_term="last_sample_s" in az.Solution.__dataclass_fields__)


def models(rows: list, params: dict) -> dict:
    """Sigma per row under each model, from A's sigma without its after-the-window term."""
    t = np.array([r["t"] for r in rows])
    s = np.array([r["sigma_rad"] for r in rows])
    last = np.array([r["last_sample_s"] for r in rows])
    T = np.maximum(t - last, 0.0)
    W = np.maximum(last - rows[0]["launch_s"], 0.0)
    sb = params["gyro_bias_sigma_rad_s"]
    base = np.sqrt(np.maximum(s ** 2 - (sb * T) ** 2, 0.0)) if params["has_term"] else s
    d2 = math.radians(1.0) ** 2
    out = {"fit only (no term)": base, "constant change sigma_b (code)": np.sqrt(base ** 2 + (sb * T) ** 2)}
    for q in Q_DEG2_S3:
        out[f"random walk q={q:g}"] = np.sqrt(base ** 2 + d2 * q * T ** 3 / 3.0)
    for q in Q_DEG2_S3[:2]:
        out[f"walk+window q={q:g}"] = np.sqrt(base ** 2 + d2 * q * (W * T ** 2 / 3.0 + T ** 3 / 3.0))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", type=int, default=3)
    ap.add_argument("--flight-s", type=float, default=S.FLIGHT_S)
    ap.add_argument("--json", default=str(pathlib.Path(__file__).resolve().parent / "results" / "azimuth_in_run_bias.json"))
    a = ap.parse_args(argv)
    from service.calibration_keeper import CalibrationKeeper
    rng = np.random.default_rng(0)           # synthetic_ahrs_accuracy's --seed 0 draws, in its order
    tmp = tempfile.TemporaryDirectory(prefix="azimuthd-a-inrun-")
    clock = [1.0e9]
    result = {"flights": []}
    pooled: dict = {}
    keeper = airframe = None
    for f in range(a.flights):
        if f % 5 == 0:
            airframe = S.airframe_overrides(rng)
            keeper = CalibrationKeeper(pathlib.Path(tmp.name) / f"airframe{f // 5}", clock=lambda: clock[0])
        clock[0] += 86400.0
        ov = S.flight_overrides(rng, airframe)
        run = simulate("runway_gnss_denied", seed=f, imu_grade="consumer", imu_rate_hz=S.IMU_HZ,
                       duration_s=S.REST_S + a.flight_s, overrides=ov)
        rows, params = decide(sealed(run), keeper)
        if not rows:
            print(f"flight {f}: A never solved")
            continue
        truth_yaw = run.truth.euler_rad[[r["i"] for r in rows], 2]      # truth only scores
        e = np.array([S.wrap(r["heading_rad"] - y) for r, y in zip(rows, truth_yaw)])
        t = np.array([r["t"] for r in rows])
        ms = models(rows, params)
        t_last = float(np.nanmax([r["last_sample_s"] for r in rows]))
        print(f"flight {f}: launch {rows[0]['launch_s']:.1f} s, A from {t[0]:.1f} s, fit's last sample "
              f"{t_last:.1f} s, sigma_b {math.degrees(params['gyro_bias_sigma_rad_s']):g} deg/s")
        print("  window (s)  err RMS  " + "  ".join(f"{k[:24]:>24s}" for k in ms) + "  (mean sigma, deg)")
        for w0 in range(int(t[0] // 50 * 50), int(t[-1]) + 1, 50):
            m = (t >= w0) & (t < w0 + 50)
            if m.any():
                print(f"  {w0:4d}-{w0 + 50:4d}  {math.degrees(math.sqrt(np.mean(e[m] ** 2))):7.2f}  "
                      + "  ".join(f"{math.degrees(float(np.mean(v[m]))):24.2f}" for v in ms.values()))
        fl = {"flight": f, "t_last_s": t_last, "models": {}}
        for k, v in ms.items():
            nees = float(np.mean((e / v) ** 2))
            w3 = float(np.mean(np.abs(e) <= 3.0 * v) * 100.0)
            fl["models"][k] = {"nees": nees, "within_3_sigma_pct": w3, "sigma_end_deg": math.degrees(float(v[-1]))}
            pooled.setdefault(k, []).append((e / v) ** 2)
            print(f"  {k:32s} NEES {nees:6.2f}  within 3 sigma {w3:5.1f} %  sigma at the end {math.degrees(float(v[-1])):5.2f} deg")
        fl["error_end_deg"] = math.degrees(float(e[-1]))
        result["flights"].append(fl)
    result["pooled"] = {k: {"nees": float(np.mean(np.concatenate(v))),
                            "within_3_sigma_pct": float(np.mean(np.concatenate(v) <= 9.0) * 100.0)}
                        for k, v in pooled.items()}
    print("pooled:")
    for k, v in result["pooled"].items():
        print(f"  {k:32s} NEES {v['nees']:6.2f}  within 3 sigma {v['within_3_sigma_pct']:5.1f} %")
    pathlib.Path(a.json).write_text(json.dumps(result, indent=1))
    print("wrote", a.json)


if __name__ == "__main__":
    main()
