"""The FC's attitude is no reference before the FC's estimator has said its attitude is good.

Found on ArduPlane SITL (bench/ardupilot_sitl.py, compass flight, replayed from the relay's
fc_to_daemon.tlog): ArduPlane publishes ATTITUDE from DCM from boot, before EKF3 runs; the daemon's
first ATTITUDE came 1.1 s before the FC's first EKF_STATUS_REPORT (flags EKF_UNINITIALIZED), and in
those 1.1 s method B trusted DCM's attitude (yaw 12.8 deg off, magnetic; pitch still settling),
started from it and learnt gyro biases from it (+0.87 deg/s pitch, then -0.19 deg/s yaw while it
pulled its heading to the magnetometer's). That bias stayed: B's gyro-only attitude drifted 0.2
deg/s from the FC's good EKF3 attitude, which 13 s after take-off read as "disagrees with gyros",
and B/C took over 2-4 deg off (heading 2.25 deg RMS before the GNSS cut; 0.59 with the FC waited
for; the same tlog started 0.5 s later, after the first status: 0.48, at d538bdf too).

Rule (estimators/reference_health): no estimator status yet -> not trusted; the first status says
good -> trusted at once; it says not good -> trusted after the re-trust hold of good; an FC that
sends none within ``status_wait_s`` of its first ATTITUDE is judged without one (said in the log).
"""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import feed_pipeline, scenario_site  # noqa: E402

from estimators.reference_health import (NO_STATUS_YET, ReferenceHealthParams, health_init,  # noqa: E402
                                         health_on_attitude, health_on_ekf_status, health_status_missing,
                                         health_trusted)
from estimators.rotations import dcm_from_euler  # noqa: E402
from mavlink_io.samples import FcAttitude, FcEkfStatus, FcHeartbeat, ImuSample, PressureSample  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402

SCENARIO = "runway_takeoff"   # at rest until 14 s (engine running from 8 s)
RATE_HZ = 50.0
DURATION_S = 13.0
FIRST_STATUS_S = 1.1          # the FC's first EKF status, after its first ATTITUDE (t = 0)
EKF_OK_S = 4.0                # its EKF says its attitude is good from here
DCM_YAW_OFF_DEG = -12.8       # ArduPlane's DCM before its EKF: magnetic yaw, pitch settling
DCM_PITCH_OFF_DEG = 2.7
DCM_PITCH_TAU_S = 0.8


def _health_params():
    return ReferenceHealthParams(retrust_hold_s=10.0, status_wait_s=5.0)


def _attitudes(h, t0, t1, params, C=dcm_from_euler(0.0, 0.05, 1.0)):
    out = []
    for k in range(int(round(t0 * 50)), int(round(t1 * 50))):
        h = health_on_attitude(h, C, C, 0.02 * k, params)
        out.append(health_trusted(h, 0.02 * k, params))
    return h, out


def test_given_a_late_first_status_when_attitude_arrives_then_it_is_no_reference_until_the_fc_says_good():
    p = _health_params()
    # GIVEN an FC whose attitudes (agreeing with our gyros) come 1.1 s before its first status
    h, before = _attitudes(health_init(), 0.0, FIRST_STATUS_S, p)
    # THEN none of them is trusted, and why is said
    assert before and all(not ok and why == NO_STATUS_YET for ok, why in before)
    # WHEN its first status says its attitude is good THEN it is trusted at once (no loss to re-trust)
    h = health_on_ekf_status(h, attitude_ok=True, horiz_pos_ok=True)
    h, after = _attitudes(h, FIRST_STATUS_S, FIRST_STATUS_S + 0.1, p)
    assert all(ok for ok, _ in after), after


def test_given_a_first_status_saying_not_ok_then_trust_waits_for_good_and_the_hold():
    p = _health_params()
    h, _ = _attitudes(health_init(), 0.0, FIRST_STATUS_S, p)
    h = health_on_ekf_status(h, attitude_ok=False, horiz_pos_ok=False)      # EKF_UNINITIALIZED
    h, mid = _attitudes(h, FIRST_STATUS_S, EKF_OK_S, p)
    assert all(not ok and why == "FC EKF attitude not ok" for ok, why in mid)
    h = health_on_ekf_status(h, attitude_ok=True, horiz_pos_ok=True)
    h, hold = _attitudes(h, EKF_OK_S, EKF_OK_S + 9.9, p)
    assert all(not ok and why == "re-trust hold" for ok, why in hold)
    h, late = _attitudes(h, EKF_OK_S + 9.9, EKF_OK_S + 10.5, p)   # (good from the first check after it)
    assert late[-1] == (True, "")


def test_an_fc_that_sends_no_status_is_judged_without_one_after_the_wait():
    """The documented rule: no status within status_wait_s of the first ATTITUDE -> the FC sends
    none; from then its attitude is trusted on freshness and agreement alone (a divergence still
    untrusts it)."""
    p = _health_params()
    h, first = _attitudes(health_init(), 0.0, 4.98, p)
    assert not any(ok for ok, _ in first) and not health_status_missing(h, p)
    h, then = _attitudes(h, 4.98, 6.0, p)
    assert health_status_missing(h, p) and then[-1] == (True, "")
    # ... a status arriving later is obeyed as any other
    h = health_on_ekf_status(h, attitude_ok=False, horiz_pos_ok=True)
    assert health_trusted(h, 5.99, p) == (False, "FC EKF attitude not ok") and not health_status_missing(h, p)


# --- through the daemon's Pipeline: the SITL case ----------------------------------------------

@pytest.fixture(scope="module")
def run():
    return simulate(scenario=SCENARIO, seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ, duration_s=DURATION_S)


def fly(run, core: str, monkeypatch):
    """The rest before a runway take-off through the Pipeline. The FC: its ATTITUDE from t = 0,
    before its EKF runs DCM's (yaw 12.8 deg off, pitch settling from 2.7 deg off); its first EKF
    status at 1.1 s says not initialised, from 4 s its attitude is good (and its ATTITUDE the
    simulator's FC attitude). Returns per solution (t, heading sources, B trusted, B's gyro bias
    rad/s), B's heading error at the end (rad) and the events."""
    monkeypatch.setenv("AZIMUTHD_CORE", core)
    site = scenario_site(SCENARIO)
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    p = Pipeline(validate({**site, "mavlink": {"imu_rate_hz": RATE_HZ}}))
    items = [(t, 2, ImuSample(t, t, g.copy(), a.copy(), m.copy(), "RAW_IMU", 0))
             for t, g, a, m in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss)]
    items += [(t, 1, PressureSample(t, t, pa, d, k)) for t, pa, d, k in
              zip(run.baro_time_s.tolist(), run.press_abs_pa.tolist(), run.press_diff_pa.tolist(),
                  run.temperature_k.tolist())]
    for t, e in zip(run.fc_time_s.tolist(), run.fc_euler_rad):
        r, pi, y = (float(v) for v in e)
        if t < EKF_OK_S:   # DCM
            y += math.radians(DCM_YAW_OFF_DEG)
            pi += math.radians(DCM_PITCH_OFF_DEG) * math.exp(-t / DCM_PITCH_TAU_S)
        items.append((t, 0, FcAttitude(t, t, r, pi, math.remainder(y, 2 * math.pi), np.zeros(3))))
    items += [(t, -1, FcHeartbeat(t, 1, 1, "ardupilot", 1, 129, 0, 3, False))
              for t in np.arange(0.0, DURATION_S, 1.0).tolist()]
    items += [(t, 3, FcEkfStatus(t, t >= EKF_OK_S, t >= EKF_OK_S, 1024 if t < EKF_OK_S else 831,
                                 "EKF_STATUS_REPORT")) for t in np.arange(FIRST_STATUS_S, DURATION_S, 0.5).tolist()]
    items.sort(key=lambda x: (x[0], x[1]))
    rows, events = [], []
    for sol in feed_pipeline(p, [it for _t, _o, it in items], events, timed_events=True):
        b = p.ahrs_out
        rows.append((sol.time_fc_s, sol.heading_source, b.reference_trusted, np.asarray(b.gyro_bias_rad_s).copy()))
    k = len(run.time_s) - 1
    b_err = math.remainder(p.ahrs_out.heading_rad - run.truth.euler_rad[k][2], 2 * math.pi)
    return rows, b_err, events


@pytest.mark.parametrize("core", ["core", "python"])
def test_given_dcm_before_the_first_ekf_status_then_b_neither_trusts_nor_learns_from_it(run, core, monkeypatch):
    rows, b_err, events = fly(run, core, monkeypatch)
    early = [r for r in rows if r[0] < FIRST_STATUS_S]
    # THEN before the FC's first status its yaw is no heading source and no reference for B
    assert early and not any("fc" in r[1].split("+") for r in early)
    assert not any(r[2] for r in early)
    # ... nor while its EKF says its attitude is not ok
    assert not any(r[2] or "fc" in r[1].split("+") for r in rows if r[0] < EKF_OK_S)
    # ... and B learnt no gyro bias from DCM: per axis its estimate is never further from the
    # simulated gyro's bias than its start (0) is, + 0.05 deg/s (before the fix: B trusted DCM for
    # 1.1 s, its pitch-rate bias went to +0.42 deg/s against a true -0.10), and B's heading is
    # within 4 deg at the end (before: -12.7 deg, DCM's yaw kept; after: 2.2)
    true_bias = np.asarray(run.truth.gyro_bias_end_rad_s, float)
    excess = max(float(np.max(np.abs(r[3] - true_bias) - np.abs(true_bias))) for r in rows)
    assert math.degrees(excess) < 0.05, math.degrees(excess)
    assert abs(math.degrees(b_err)) < 4.0, math.degrees(b_err)
    refs = [(round(t, 2), d) for t, k, d in events if k == "reference"]
    assert not any("trusted: " in d and "NOT" not in d for t, d in refs if t < EKF_OK_S), refs
