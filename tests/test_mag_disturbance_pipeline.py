"""Issue 18's magnet tests through the daemon's Pipeline on the simulator's IMU (sim.offline: its
own Earth field and sensor errors), IMU samples only (a hand-held IMU: no FC, no air data).
Truth only scores."""
import math

import numpy as np
import pytest

from mavlink_io.samples import ImuSample
from service.config import validate
from service.pipeline import Pipeline
from sim.offline import simulate

IMU_HZ = 50.0


def _pipeline(run) -> Pipeline:
    s = run.site
    return Pipeline(validate({
        "site": {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"],
                 "decimal_year": s["decimal_year"]},
        "launch": {"case": "aligned", "vehicle": "hand"}, "heading": {"use_fc_yaw": False},
        "azimuth": {"solve_in_background": False}, "mavlink": {"imu_rate_hz": IMU_HZ}}))


def _fly(run):
    """(time, magnetometer status, heading valid, heading sigma deg, heading error deg, C's own
    magnetometer innovation deg and test ratio from its aiding record) per solution, and the
    Pipeline's events; the error is the twist of the published attitude about the vertical."""
    p = _pipeline(run)
    rows = []
    for k, t in enumerate(run.time_s.tolist()):
        sol = p.on_imu(ImuSample(t, t, run.gyro_rad_s[k].copy(), run.accel_m_s2[k].copy(),
                                 run.mag_gauss[k].copy(), "RAW_IMU", 0))
        if sol is None or sol.q_nav_from_body is None:
            continue
        qt, qe = run.truth.q_nav_from_body[k], np.asarray(sol.q_nav_from_body)
        # q_err = q_est (x) conj(q_true): its twist about the vertical
        w = qe[0] * qt[0] + qe[1] * qt[1] + qe[2] * qt[2] + qe[3] * qt[3]
        z = -qe[0] * qt[3] - qe[1] * qt[2] + qe[2] * qt[1] + qe[3] * qt[0]
        err = math.degrees(math.remainder(2.0 * math.atan2(z, w), 2 * math.pi))
        rec = p.aiding.get("heading_filter")
        rows.append((t, sol.flags.get("magnetometer", ""), bool(sol.heading_valid),
                     math.degrees(sol.heading_sigma_rad) if sol.heading_sigma_rad else math.nan, err,
                     math.degrees(rec.source_innovation_rad) if rec is not None else math.nan,
                     rec.source_test_ratio if rec is not None else math.nan))
    return rows, list(p.events)


@pytest.fixture(scope="module")
def nearby():
    # any_motion_magnet_nearby, shortened: the magnet from 16 s to 24 s while the body turns and rests
    run = simulate("any_motion_magnet_nearby", seed=3, imu_rate_hz=IMU_HZ, duration_s=32.0,
                   overrides={"mag": {"disturbances": [{"start_s": 16.0, "end_s": 24.0,
                                                        "field_ned_gauss": [0.22, -0.18, 0.10]}]}})
    return _fly(run)


def test_given_a_magnet_brought_close_when_the_field_norm_departs_then_rejected_and_the_sigma_grows(nearby):
    rows, events = nearby
    before = [r for r in rows if 12.0 <= r[0] < 16.0]
    during = [r for r in rows if 16.5 <= r[0] < 24.0]
    assert all(r[1] == "usable" for r in before)
    # THEN the heading source says rejected, with the reason named: at once against the recent
    # undisturbed field, then (its 2 s median) against the model too
    assert all(r[1].startswith(("rejected: magnetic disturbance: field", "rejected: field norm")) for r in during), \
        {r[1][:60] for r in during}
    assert any(k == "magnetic_disturbance" and d.startswith("rejected (magnetic disturbance: field") and
               "vs the recent undisturbed" in d for k, d in events)
    assert any(k == "magnetometer" and d.startswith("rejected (field norm") and "vs the model's" in d for k, d in events)
    first = next(r[0] for r in rows if r[0] >= 16.0 and r[1] != "usable")
    assert first - 16.0 < 0.3
    # ... the heading coasts on the gyros (still published) and its sigma grows all along
    assert all(r[2] for r in during)
    sig = np.array([r[3] for r in during])
    assert np.all(np.diff(sig) >= 0.0) and sig[-1] > sig[0]
    # ... and it stays honest: every error within 3 sigma, before, during and after
    assert all(abs(r[4]) <= 3.0 * r[3] for r in rows if r[0] >= 12.0)


def test_when_the_magnet_is_taken_away_then_the_magnetometer_is_used_again_within_1_s(nearby):
    rows, _ = nearby
    back = next(r[0] for r in rows if r[0] >= 24.0 and r[1] == "usable")
    assert back - 24.0 < 1.0
    assert all(r[1] == "usable" for r in rows if r[0] > back)
    # the heading comes back to what the undisturbed magnetometer gave before the magnet (seed 3's
    # site has a 3-4 deg field-model error: within its sigma, and not the magnet's doing)
    before = abs(next(r[4] for r in reversed(rows) if r[0] < 16.0))
    assert max(abs(r[4]) for r in rows if r[0] > rows[-1][0] - 3.0) <= before + 0.5


def _measurements(rows, lo: float, hi: float):
    """C's magnetometer heading measurements (innovation deg, test ratio, the published heading's
    error deg) between lo and hi, one per measurement (a record repeats it until the next)."""
    out, prev = [], None
    for r in rows:
        if lo <= r[0] < hi and math.isfinite(r[5]) and r[5] != prev:
            out.append((r[5], r[6], r[4]))
        prev = r[5]
    return out


def test_given_a_magnet_attached_when_the_body_turns_then_learnt_again_and_used():
    # any_motion_magnet_attached, shortened: a new hard iron of 0.29 G from 14 s while the body turns
    run = simulate("any_motion_magnet_attached", seed=3, imu_rate_hz=IMU_HZ, duration_s=46.0,
                   overrides={"mag": {"disturbances": [{"start_s": 14.0, "hard_iron_gauss": [0.18, -0.20, 0.12]}]}})
    rows, events = _fly(run)
    assert any(k == "magnetic_disturbance" and d.startswith("hard iron changed") for k, d in events)
    relearning = [r for r in rows if r[1].startswith("rejected: re-learning its hard iron")]
    assert relearning and all(r[2] for r in relearning)          # coasting meanwhile, not lost
    # learnt again within a stated time: usable for good from at most 30 s after the magnet came
    # (measured 25.1 s on these slow rotations with pauses: the change is confirmed by three 30 deg
    # turns inconsistent with the old hard iron (15 s here), then learnt once the body has turned
    # about its z axis too (10 s); rejected meanwhile by the field tests, never fused)
    last_bad = max(r[0] for r in rows if r[0] >= 14.0 and r[1] != "usable")
    assert last_bad - 14.0 < 30.0, last_bad - 14.0
    assert rows[-1][0] - last_bad > 5.0                            # the run shows the 5 s after it
    # THEN C's magnetometer is fused again, not rejected for good: every heading measurement in the
    # 5 s after the relearn passes C's own gate (measured 50 of 50)
    after_meas = _measurements(rows, last_bad, last_bad + 5.0)
    assert len(after_meas) >= 45 and all(m[1] <= 1.0 for m in after_meas)
    # ... the relearnt hard iron is right: the measured heading's error against truth (published
    # error + C's innovation) is no larger than with the airframe's own hard iron before the magnet
    # (measured -1.1 deg mean after vs -2.6 before: both the tilt error times tan(dip), not the
    # magnet), and its innovations point back towards truth (+3.0 deg mean against a -4.0 deg error)
    before_meas = _measurements(rows, 6.0, 14.0)
    meas_err_before = abs(np.mean([m[2] + m[0] for m in before_meas]))
    meas_err_after = abs(np.mean([m[2] + m[0] for m in after_meas]))
    assert meas_err_after <= meas_err_before
    assert np.mean([m[0] * m[2] for m in after_meas]) < 0.0
    # ... the heading error stays within the pre-magnet error + 1 deg (the 25 s coast on the gyros
    # costs 0.9 deg at most here: -3.2 deg before the magnet (the tilt error through the dip), -4.1
    # worst after) and within 2 published sigma (measured 1.4), and the sigma shrinks back below
    # its coast value (3.4 -> 3.0 deg)
    err_before = abs(next(r[4] for r in reversed(rows) if r[0] < 14.0))
    after = [r for r in rows if r[0] > last_bad]
    assert max(abs(r[4]) for r in after) <= err_before + 1.0
    assert all(abs(r[4]) <= 2.0 * r[3] for r in after)
    coast_sigma = next(r[3] for r in reversed(rows) if r[0] <= last_bad)
    assert after[-1][3] < coast_sigma
    # ... and every error within 3 sigma from before the magnet to the end
    assert all(abs(r[4]) <= 3.0 * r[3] for r in rows if r[0] >= 12.0)
