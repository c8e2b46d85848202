"""Is the published heading sigma honest? Simulated flights through the daemon's own Pipeline.

    python bench/heading_consistency.py [--quick] [--json PATH]

Cases (sim.offline.simulate, consumer IMU at 100 Hz, fed to ``service.pipeline.Pipeline`` as the
daemon's link hands it the samples: bench/sitl.py's ``pipeline_inputs`` plus a 1 Hz HEARTBEAT
(armed; system_status ArduPlane's is_flying() from the FC's OWN airspeed, bench/_fc_status.py)
and a 1 Hz EKF status whose ``horiz_pos_ok`` clears at the GNSS loss the FC sees, as the simulator
sends EKF_STATUS_REPORT on the wire). The decision half (``decide``) runs on a sealed run
(bench/_truth_guard.py): the truth only scores (tests/test_truth_isolation.py).

- ``inclined_rail``: rail launch, climb, turns; method A solves in flight; no GNSS loss;
- ``inclined_rail_in_flight``: the same flight, the daemon started 60 s after the launch (no
  levelling, method A off: the FC's yaw and method B are fused while the FC is trusted; the case of
  tests/test_pipeline_started_in_flight.py);
- ``runway_gnss_denied``: runway take-off, GNSS lost (the FC's yaw drifts, its trust ends).

In every flight a 10 s link outage (no IMU, no pressure, no FC message) is injected in flight.

Scored against the simulator's truth yaw, for every NavSolution with a valid heading: error
(deg), the fraction within 1/2/3 published sigmas and the NEES = mean((err / sigma)^2) (1 for an
honest Gaussian sigma), overall, per window (before / after the GNSS loss, the 30 s after the
outage), per ``heading_source``, and for the inputs the arbitration gets (B, C, the FC's yaw).
Targets (honest heading): >= 95 % within 3 sigma and NEES in [0.5, 2] in every window.

``--random-iron``: each flight's hard and soft iron drawn from the prior method C's published
sigma assumes for an uncompensated magnetometer ([heading] uncalibrated_hard_iron_gauss per axis,
[heading] uncalibrated_soft_iron per element, seeded by the flight's seed) instead of the
scenario's own: a calibration check of that consider model (C's input NEES ~1 on average when the
airframes are drawn from the prior; a scenario's fixed iron is one draw).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import time

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from estimators.polar_heading import polar_heading_estimate  # noqa: E402
from mavlink_io.samples import ImuSample  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from service.replay import json_safe  # noqa: E402
from sim.offline import simulate  # noqa: E402
from _fc_status import feed, merged_items  # noqa: E402
from _truth_guard import sealed  # noqa: E402
from sitl import scenario_site  # noqa: E402

IMU_HZ = 100.0
GAP_S = 10.0
"""Length of the injected outage (s)."""
AFTER_GAP_S = 30.0
"""The 'after_gap' window: this long after the outage ends (s)."""
WINDOWS = ("overall", "before_gnss_loss", "after_gnss_loss", "after_gap")
TARGET_WITHIN_3SIGMA = 0.95
FC_SIGMA_RAD = [math.nan]
"""The FC yaw sigma in use ([heading] fc_yaw_sigma_deg's default unless --fc-yaw-sigma-deg)."""
TARGET_NEES = (0.5, 2.0)


def cases(quick: bool) -> list[dict]:
    """Times in s on the simulator clock (0 at sim start)."""
    rest = 15.0
    if quick:
        return [
            dict(name="inclined_rail", scenario="inclined_rail", duration_s=160.0, feed_from_s=0.0,
                 gap_start_s=110.0, overrides={"launcher": {"rest_s": rest}}),
            dict(name="inclined_rail_in_flight", scenario="inclined_rail", duration_s=200.0,
                 feed_from_s=rest + 60.0, gap_start_s=140.0, overrides={"launcher": {"rest_s": rest}}),
            dict(name="runway_gnss_denied", scenario="runway_gnss_denied", duration_s=200.0, feed_from_s=0.0,
                 gap_start_s=140.0, overrides={"launcher": {"rest_s": rest}, "gnss": {"lost_at_s": 100.0}}),
        ]
    return [
        dict(name="inclined_rail", scenario="inclined_rail", duration_s=330.0, feed_from_s=0.0,
             gap_start_s=110.0, overrides={"launcher": {"rest_s": rest}}),
        dict(name="inclined_rail_in_flight", scenario="inclined_rail", duration_s=330.0,
             feed_from_s=rest + 60.0, gap_start_s=140.0, overrides={"launcher": {"rest_s": rest}}),
        dict(name="runway_gnss_denied", scenario="runway_gnss_denied", duration_s=420.0, feed_from_s=0.0,
             gap_start_s=260.0, overrides={"launcher": {"rest_s": rest}, "gnss": {"lost_at_s": 180.0}}),
    ]


def items_for(run, case: dict) -> list:
    """The Pipeline inputs in time order, with HEARTBEAT and EKF status (bench/_fc_status.py: from
    the FC's own sensors), the outage cut out."""
    g0, g1 = case["gap_start_s"], case["gap_start_s"] + GAP_S
    return merged_items(run, case["feed_from_s"], cut=lambda t: g0 <= t < g1)


def random_iron_overrides(case: dict, seed: int) -> dict:
    """``case`` with its magnetometer's hard/soft iron drawn from method C's uncalibrated prior."""
    from service.config import SPEC
    rng = np.random.default_rng(7919 + seed)
    hard_sigma = SPEC["heading"]["uncalibrated_hard_iron_gauss"].default   # what the Pipeline is given
    soft_sigma = SPEC["heading"]["uncalibrated_soft_iron"].default
    mag = {"hard_iron_gauss": rng.normal(0.0, hard_sigma, 3).tolist(),
           "soft_iron": (np.eye(3) + rng.normal(0.0, soft_sigma, (3, 3))).tolist()}
    return {**case, "overrides": {**case["overrides"], "mag": {**case["overrides"].get("mag", {}), **mag}}}


def decide(run, case: dict, fc_yaw_sigma_deg: float | None = None) -> dict:
    """The daemon's decision half on a (sealed) SimRun: a fresh Pipeline with the operator's config
    (site and date, launcher, mount: bench/sitl.py's scenario_site), fed as the daemon's link feeds
    it. Per-solution lists: time, the published heading and sigma, its source, and the inputs the
    arbitration got (B, C, the trusted FC's yaw). Reads no truth."""
    cfg = scenario_site(case["scenario"])
    s = run.site
    cfg["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"],
                       decimal_year=s["decimal_year"])
    p = Pipeline(validate({**cfg, "mavlink": {"imu_rate_hz": IMU_HZ}}))
    if fc_yaw_sigma_deg is not None:
        p.ahrs_params = dataclasses.replace(p.ahrs_params, fc_sigma_yaw_rad=math.radians(fc_yaw_sigma_deg))
    rec = {k: [] for k in ("t", "h", "s", "src", "b_h", "b_s", "c_h", "c_s", "f_h")}
    nan = math.nan
    for it in items_for(run, case):
        sol = feed(p, it)
        if type(it) is not ImuSample or sol is None:
            continue
        rec["t"].append(sol.time_fc_s)
        ok = sol.heading_valid
        rec["h"].append(sol.heading_rad if ok else nan)
        rec["s"].append(sol.heading_sigma_rad if ok else nan)
        rec["src"].append(sol.heading_source)
        b = p.ahrs_out
        bok = b is not None and b.valid
        rec["b_h"].append(b.heading_rad if bok else nan)
        rec["b_s"].append(b.heading_sigma_rad if bok else nan)
        h = polar_heading_estimate(p.polar_hdg)
        rec["c_h"].append(h.heading_rad if h.initialised else nan)
        rec["c_s"].append(math.sqrt(h.variance_rad2) if h.initialised else nan)
        fc = p.fc_attitude
        trusted = bok and b.reference_trusted and fc is not None
        rec["f_h"].append(fc.yaw_rad if trusted else nan)
    return rec


def fly(case: dict, seed: int, fc_yaw_sigma_deg: float | None = None) -> dict:
    """One flight: simulate, decide on the sealed run, score against the truth. ``fc_yaw_sigma_deg``:
    the FC's yaw sigma the pipeline assumes (None = [heading] fc_yaw_sigma_deg's default), for a
    sensitivity run."""
    run = simulate(scenario=case["scenario"], seed=seed, imu_grade="consumer", imu_rate_hz=IMU_HZ,
                   duration_s=case["duration_s"], overrides=case["overrides"])
    rec = decide(sealed(run), case, fc_yaw_sigma_deg)
    # scoring: truth from here on
    t = np.array(rec["t"])
    k = np.minimum(np.searchsorted(run.time_s, t - 1e-9), len(run.time_s) - 1)
    yaw = run.truth.euler_rad[k, 2]
    out = dict(t=t, src=np.array(rec["src"], dtype=object), yaw=yaw)
    for key in ("h", "s", "b_h", "b_s", "c_h", "c_s", "f_h"):
        out[key] = np.array(rec[key], dtype=float)
    loss = run.gnss_lost_time_s
    g1 = case["gap_start_s"] + GAP_S
    after_gap = (t >= g1) & (t < g1 + AFTER_GAP_S)
    out["win"] = {
        "overall": np.ones(len(t), bool),
        "before_gnss_loss": ~after_gap & ((t < loss) if loss is not None else True),
        "after_gnss_loss": ~after_gap & ((t >= loss) if loss is not None else False),
        "after_gap": after_gap,
    }
    return out


def wrap_pi(a):
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


def stats(err_rad: np.ndarray, sigma_rad: np.ndarray) -> dict:
    ok = np.isfinite(err_rad) & np.isfinite(sigma_rad) & (sigma_rad > 0)
    e, s = np.abs(err_rad[ok]), sigma_rad[ok]
    if len(e) == 0:
        return {"n": 0}
    r = e / s
    return {"n": int(len(e)), "rms_error_deg": float(np.degrees(np.sqrt(np.mean(e * e)))),
            "p95_error_deg": float(np.degrees(np.percentile(e, 95))),
            "median_sigma_deg": float(np.degrees(np.median(s))),
            "within_1sigma_fraction": float(np.mean(r <= 1)), "within_2sigma_fraction": float(np.mean(r <= 2)),
            "within_3sigma_fraction": float(np.mean(r <= 3)), "nees": float(np.mean(r * r))}


def meets(st: dict) -> bool | None:
    if st.get("n", 0) == 0:
        return None
    return bool(st["within_3sigma_fraction"] >= TARGET_WITHIN_3SIGMA and TARGET_NEES[0] <= st["nees"] <= TARGET_NEES[1])


def score(flights: list[dict]) -> dict:
    """Pooled over the flights given."""
    cat = {k: np.concatenate([f[k] for f in flights]) for k in ("t", "h", "s", "yaw", "b_h", "b_s", "c_h", "c_s",
                                                                "f_h")}
    src = np.concatenate([f["src"] for f in flights])
    win = {w: np.concatenate([f["win"][w] for f in flights]) for w in WINDOWS}
    err = wrap_pi(cat["h"] - cat["yaw"])
    out = {"windows": {}, "sources": {}, "inputs": {}}
    for w in WINDOWS:
        m = win[w]
        st = stats(err[m], cat["s"][m])
        st["valid_fraction"] = float(np.mean(np.isfinite(cat["h"][m]))) if m.any() else math.nan
        st["meets_target"] = meets(st)
        out["windows"][w] = st
    for name in sorted(set(src.tolist())):
        m = src == name
        out["sources"][name] = stats(err[m], cat["s"][m])
    fc_sigma = FC_SIGMA_RAD[0]  # what the pipeline hands the arbitration for the FC (fc_sigma_yaw_rad)
    for name, h, s in (("synthetic_ahrs", cat["b_h"], cat["b_s"]), ("heading_filter", cat["c_h"], cat["c_s"]),
                       ("fc_trusted", cat["f_h"], np.full(len(cat["f_h"]), fc_sigma))):
        out["inputs"][name] = stats(wrap_pi(h - cat["yaw"]), s)
    return out


def _row(label: str, st: dict) -> str:
    if st.get("n", 0) == 0:
        return f"{label:<42} {'0':>7}"
    tick = {True: "ok", False: "NO", None: ""}[st.get("meets_target")] if "meets_target" in st else ""
    return (f"{label:<42} {st['n']:>7d} {st['rms_error_deg']:>7.2f} {st['p95_error_deg']:>7.2f} "
            f"{st['median_sigma_deg']:>7.2f} {100 * st['within_1sigma_fraction']:>6.1f} "
            f"{100 * st['within_2sigma_fraction']:>6.1f} {100 * st['within_3sigma_fraction']:>6.1f} "
            f"{st['nees']:>8.2f} {tick:>3}")


HEADER = (f"{'':<42} {'n':>7} {'rms':>7} {'p95':>7} {'sig50':>7} {'<1s%':>6} {'<2s%':>6} {'<3s%':>6} "
          f"{'NEES':>8}\n{'':<42} {'':>7} {'deg':>7} {'deg':>7} {'deg':>7}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter flights, 2 seeds (~2 min)")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "heading_consistency.json"))
    ap.add_argument("--seeds", type=int, default=None, help="seeds per case (default 2 quick, 5 full)")
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all three)")
    ap.add_argument("--seed-base", type=int, default=0,
                    help="first seed (seeds seed-base .. seed-base + seeds - 1); 100+: seeds no default was chosen on")
    ap.add_argument("--random-iron", action="store_true",
                    help="hard/soft iron per flight drawn from method C's uncalibrated prior (module docstring)")
    ap.add_argument("--fc-yaw-sigma-deg", type=float, default=None,
                    help="sensitivity: the FC yaw sigma the pipeline assumes (default: SyntheticAhrsParams')")
    args = ap.parse_args(argv)
    from service.config import SPEC
    FC_SIGMA_RAD[0] = math.radians(args.fc_yaw_sigma_deg if args.fc_yaw_sigma_deg is not None
                                   else SPEC["heading"]["fc_yaw_sigma_deg"].default)
    t0 = time.time()
    n_seeds = args.seeds if args.seeds is not None else (2 if args.quick else 5)
    results = {"quick": args.quick, "seeds": n_seeds, "seed_base": args.seed_base, "imu_rate_hz": IMU_HZ, "gap_s": GAP_S,
               "fc_yaw_sigma_deg": math.degrees(FC_SIGMA_RAD[0]), "random_iron": args.random_iron, "cases": {}}
    all_flights = []
    print(HEADER)
    for case in cases(args.quick):
        if args.cases and case["name"] not in args.cases.split(","):
            continue
        flights = [fly(random_iron_overrides(case, seed) if args.random_iron else case, seed, args.fc_yaw_sigma_deg)
                   for seed in range(args.seed_base, args.seed_base + n_seeds)]
        all_flights += flights
        sc = score(flights)
        results["cases"][case["name"]] = {"gap_start_s": case["gap_start_s"], "duration_s": case["duration_s"],
                                          "feed_from_s": case["feed_from_s"], **sc}
        for w in WINDOWS:
            print(_row(f"{case['name']} / {w}", sc["windows"][w]))
        for name, st in sc["sources"].items():
            print(_row(f"  source {name}", st))
        for name, st in sc["inputs"].items():
            print(_row(f"  input {name}", st))
    total = score(all_flights)
    results["all_cases"] = total
    print("-" * 110)
    for w in WINDOWS:
        print(_row(f"all / {w}", total["windows"][w]))
    for name, st in total["sources"].items():
        print(_row(f"  source {name}", st))
    results["run_time_s"] = time.time() - t0
    print(f"run time {results['run_time_s']:.0f} s")
    path = pathlib.Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_safe(results), indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
