"""What method C's published heading sigma is made of, on one polar_accuracy flight through the Pipeline.

    python bench/c_sigma_breakdown.py [--lat-deg 45] [--seed 300] [--duration-s 150] [--json PATH]

The flight and the operator's config are bench/polar_accuracy.py's headline ones (compensated
magnetometer: ``[heading] uncalibrated_hard_iron_gauss = 0``, ``uncalibrated_soft_iron = 0``).
Every second of the flight, from C's heading-filter state in the Pipeline (decision half on a
sealed run; the truth only scores): the heading error, the published sigma, the filter's own
sqrt(P_psi), the uncalibrated-magnetometer consider term sqrt(r_uncal) and the consider floor
(estimators/polar_heading.py: published variance = max(P_psi, floor) + r_uncal). JSON keys carry
units; ``var_share_filter_P`` is the mean share of P_psi in the published variance.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import polar_accuracy as pa  # noqa: E402
from _fc_status import feed, merged_items  # noqa: E402
from _truth_guard import sealed  # noqa: E402
from estimators.polar_heading import polar_heading_estimate  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sitl import scenario_site  # noqa: E402


def decide(run, lat_deg: float) -> list:
    """The Pipeline on a (sealed) run, the config polar_accuracy's headline gives it; rows every
    second: (FC time, heading, published var, P_psi, r_uncal, floor) in rad / rad^2."""
    cfg = scenario_site("polar_89")
    cfg["site"]["lat_deg"] = lat_deg
    cfg["heading"] = {"cruise_speed_m_s": pa.CRUISE_M_S, "uncalibrated_hard_iron_gauss": 0.0,
                      "uncalibrated_soft_iron": 0.0}
    p = Pipeline(validate({**cfg, "mavlink": {"imu_rate_hz": pa.RATE_HZ}}))
    rows, n = [], 0
    for it in merged_items(run, 0.0):
        sol = feed(p, it)
        if sol is None:
            continue
        n += 1
        st = p.polar_hdg
        if n % 50 or not st.initialised:          # solutions at 50 Hz: one row a second
            continue
        he = polar_heading_estimate(st)
        rows.append((sol.time_fc_s, he.heading_rad, he.variance_rad2, float(st.P[0, 0]), st.r_uncal_rad2,
                     st.r_corr_avg_rad2 or 0.0))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lat-deg", type=float, default=45.0)
    ap.add_argument("--seed", type=int, default=300)
    ap.add_argument("--duration-s", type=float, default=150.0)
    ap.add_argument("--json", default=str(pathlib.Path(__file__).resolve().parent / "results" / "c_sigma_breakdown.json"))
    a = ap.parse_args(argv)
    run = pa.simulate_flight(a.lat_deg, a.seed, "consumer", a.duration_s)
    rows = np.array(decide(sealed(run), float(run.site["lat_deg"])), float)
    # scoring: truth from here on
    k = np.minimum(np.searchsorted(run.time_s, rows[:, 0] - 1e-9), len(run.time_s) - 1)
    err = pa.wrap_pi(rows[:, 1] - run.truth.euler_rad[k, 2])
    deg = np.degrees
    print(f"{'t_s':>6} {'err':>6} {'sigma':>6} {'sqrtP':>6} {'uncal':>6} {'floor':>6}  (deg)")
    for i in range(0, len(rows), 10):
        print(f"{rows[i, 0]:6.1f} {deg(err[i]):+6.2f} {deg(math.sqrt(rows[i, 2])):6.2f} {deg(math.sqrt(rows[i, 3])):6.2f} "
              f"{deg(math.sqrt(rows[i, 4])):6.2f} {deg(math.sqrt(rows[i, 5])):6.2f}")
    out = {"bench": "c_sigma_breakdown", "lat_deg": a.lat_deg, "seed": a.seed, "flight_s": a.duration_s,
           "heading_rms_deg": float(deg(math.sqrt(np.mean(err ** 2)))),
           "sigma_median_deg": float(deg(np.median(np.sqrt(rows[:, 2])))),
           "sqrt_P_median_deg": float(deg(np.median(np.sqrt(rows[:, 3])))),
           "sqrt_r_uncal_median_deg": float(deg(np.median(np.sqrt(rows[:, 4])))),
           "var_share_filter_P": float(np.mean(np.maximum(rows[:, 3], rows[:, 5]) / rows[:, 2])),
           "nees": float(np.mean(err ** 2 / rows[:, 2])),
           "within_2sigma_fraction": float(np.mean(err ** 2 <= 4.0 * rows[:, 2])),
           "within_3sigma_fraction": float(np.mean(err ** 2 <= 9.0 * rows[:, 2]))}
    print(" ".join(f"{k} {v:.3g}" for k, v in out.items() if isinstance(v, float)))
    p = pathlib.Path(a.json)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=1))
    print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
