"""Method C's attitude filter through any attitude, and its re-levelling at rest (issue 18, item 1).

Synthetic IMU generated here from a chosen body-rate history: the truth q_nav_from_body is
integrated exactly (rotation vector per 1 ms sub-step), the filter gets the 20 ms means of the
rate and of the specific force C_body_from_nav [0, 0, -g] (+ a chosen acceleration), as the
daemon feeds it at filter_rate_hz = 50, with seeded white noise.

Errors are judged on the tilt: the angle between the true and the estimated down direction in
the body, against 3 x the larger sigma of the attitude covariance across that direction
(eigenvalue of the tilt block), so pitch +-90 deg (where roll is undefined) is judged too.
"""
import math

import numpy as np
import pytest

from estimators.polar_attitude import (I_ATT, PolarAttitudeParams, polar_attitude_estimate,
                                       polar_attitude_init_at, polar_attitude_step)
from estimators.rotations import dcm_from_quat, euler_from_dcm, quat_from_rotvec, quat_mul, wrap_pi

G = 9.80665
RATE_HZ = 50.0
SUB = 20                        # 1 ms truth sub-steps per 20 ms filter sample
D2R = math.radians


def imu(rate_of_t, duration_s, accel_of_t=lambda t: np.zeros(3), q0=None, seed=0,
        gyro_noise_rad_s=D2R(0.05), accel_noise_m_s2=0.03):
    """Samples (t, gyro_body_rad_s, accel_body_m_s2, q_nav_from_body_true) at RATE_HZ."""
    rng = np.random.default_rng(seed)
    q = np.array([1.0, 0.0, 0.0, 0.0]) if q0 is None else np.asarray(q0, float)
    h = 1.0 / (RATE_HZ * SUB)
    out = []
    for k in range(1, int(round(duration_s * RATE_HZ)) + 1):
        w_sum, f_sum = np.zeros(3), np.zeros(3)
        for j in range(SUB):
            t = (k - 1) / RATE_HZ + (j + 0.5) * h
            w = np.asarray(rate_of_t(t), float)
            q = quat_mul(q, quat_from_rotvec(w * h))
            C_body_from_nav = dcm_from_quat(q).T
            f_sum += C_body_from_nav @ (np.asarray(accel_of_t(t), float) - np.array([0.0, 0.0, G]))
            w_sum += w
        out.append((k / RATE_HZ, w_sum / SUB + rng.normal(0.0, gyro_noise_rad_s, 3),
                    f_sum / SUB + rng.normal(0.0, accel_noise_m_s2, 3), q.copy()))
    return out


def tilt_error_and_sigma(st, q_true):
    """(angle between true and estimated down in body, sigma of the tilt: sqrt of the largest
    eigenvalue of the attitude covariance projected across the estimated down direction)."""
    d_true = dcm_from_quat(q_true)[2, :]
    d_hat = dcm_from_quat(st.q_P_from_body)[2, :]
    err = math.atan2(float(np.linalg.norm(np.cross(d_true, d_hat))), float(d_true @ d_hat))
    Pr = np.eye(3) - np.outer(d_hat, d_hat)
    lam = np.linalg.eigvalsh(Pr @ st.P[I_ATT, I_ATT] @ Pr)
    return err, math.sqrt(max(lam[-1], 0.0))


def run(samples, st, params=PolarAttitudeParams()):
    rows = []   # (t, tilt error, tilt sigma, diag, state)
    for t, w, f, q in samples:
        st, d = polar_attitude_step(st, t, w, f, params)
        e, s = tilt_error_and_sigma(st, q)
        rows.append((t, e, s, d, st, q))
    return st, rows


def smooth_pulse(t, t0, t1):
    """0 outside [t0, t1], sin^2 bump inside: a rate that starts and stops smoothly."""
    if t < t0 or t > t1:
        return 0.0
    return math.sin(math.pi * (t - t0) / (t1 - t0)) ** 2


def upside_down(t):        # roll +180 deg over 2 s, hold 2 s, roll back
    return [D2R(180.0) * (smooth_pulse(t, 1.0, 3.0) - smooth_pulse(t, 5.0, 7.0)), 0.0, 0.0]


def pitch_90(t):           # pitch +90 deg over 2 s (nose straight up), hold 2 s, back
    return [0.0, D2R(90.0) * (smooth_pulse(t, 1.0, 3.0) - smooth_pulse(t, 5.0, 7.0)), 0.0]


def spin_500(t):           # 500 deg/s about a tilted, wobbling axis for ~3 s (coning), then still
    a = smooth_pulse(t, 1.0, 4.0) ** 0.25
    u = np.array([math.sin(3.0 * t), math.cos(2.3 * t), 1.5])
    return D2R(500.0) * a * u / np.linalg.norm(u)


def hand_shake(t):         # hand accelerations during the motion (nav frame, m/s^2): not gravity
    if 1.0 <= t <= 7.0:
        return [6.0 * math.sin(9.0 * t), 5.0 * math.cos(7.0 * t), 4.0 * math.sin(11.0 * t)]
    return [0.0, 0.0, 0.0]


REST_S = 5.0


@pytest.mark.parametrize("rate_of_t", [upside_down, pitch_90, spin_500], ids=["upside_down", "pitch_90", "spin_500"])
def test_any_attitude_returns_within_3_sigma_at_rest_and_the_sigma_covers_the_tumble(rate_of_t):
    # GIVEN a level, still vehicle whose filter starts level, then the motion (with hand
    # accelerations up to 9 m/s^2 on top) and REST_S s at rest, level, at the end
    samples = imu(rate_of_t, 8.0 + REST_S, accel_of_t=hand_shake, seed=1)
    st = polar_attitude_init_at(0.0, 0.0, 0.0, D2R(1.0))
    # WHEN the filter is fed at 50 Hz
    st, rows = run(samples, st)
    # THEN its tilt error never exceeds 3 sigma, through the tumble included (no overconfidence)
    worst = max(e / s for _, e, s, *_ in rows)
    assert worst <= 3.0, f"tilt error reached {worst:.2f} sigma"
    # AND at the end of the rest roll and pitch are each within 3 sigma and within 1 deg
    est = polar_attitude_estimate(st)
    r_true, p_true, _ = euler_from_dcm(dcm_from_quat(rows[-1][5]))
    sr, sp = np.sqrt(np.diag(est.cov_roll_pitch_rad2))
    assert abs(est.roll_rad - r_true) <= 3.0 * sr and abs(est.pitch_rad - p_true) <= 3.0 * sp
    assert math.degrees(rows[-1][1]) < 1.0
    # AND the last 2 s of the rest were fused, not gated (the filter follows the accelerometer)
    tail = [r[3] for r in rows if r[0] > rows[-1][0] - 2.0 and r[3].updated]
    assert tail and all(d.fused for d in tail)


def test_a_40_deg_tilt_error_at_rest_is_re_levelled_with_an_honest_sigma():
    # GIVEN a filter that believes roll +40 deg with a 1 deg sigma while the vehicle lies flat
    # and still (the issue-18 replay: every update rejected by the gate, for ever)
    samples = imu(lambda t: [0.0, 0.0, 0.0], 4.0, seed=2)
    st = polar_attitude_init_at(0.0, D2R(40.0), 0.0, D2R(1.0))
    yaw0 = euler_from_dcm(dcm_from_quat(st.q_P_from_body))[2]
    # WHEN it is fed at rest
    st, rows = run(samples, st)
    # THEN it is gated out for relevel_rest_s (1 s) and then re-levelled, once, with the reason
    p = PolarAttitudeParams()
    relev = [r for r in rows if r[3].relevelled]
    assert len(relev) == 1 and st.n_relevels == 1
    t_rel, e_rel, s_rel, d_rel, *_ = relev[0]
    gated_before = [r for r in rows if r[0] < t_rel and r[3].updated]
    assert gated_before and all(not r[3].fused and r[3].test_ratio > 1.0 for r in gated_before)
    assert p.relevel_rest_s <= t_rel <= p.relevel_rest_s + 0.1
    assert d_rel.reason.startswith("re-levelled at rest") and math.degrees(d_rel.relevel_rad) == pytest.approx(40.0, abs=0.5)
    # AND right after it the tilt is within 3 sigma, the sigma is the derived 2.7 deg (not the
    # 1 deg that was wrong), and P's azimuth (what the heading filter carries) did not move
    assert e_rel <= 3.0 * s_rel and math.degrees(s_rel) == pytest.approx(2.72, abs=0.05)
    assert abs(wrap_pi(euler_from_dcm(dcm_from_quat(rows[-1][4].q_P_from_body))[2] - yaw0)) < D2R(0.2)
    # AND the updates fuse again and bring the tilt under 0.5 deg within the rest
    after = [r for r in rows if r[0] > t_rel and r[3].updated]
    assert after and all(r[3].fused for r in after)
    assert math.degrees(rows[-1][1]) < 0.5 and rows[-1][1] <= 3.0 * rows[-1][2]


def test_upside_down_tilt_error_is_re_levelled():
    # GIVEN a filter that believes it is upside down (roll 180 deg) while the vehicle lies flat:
    # the estimated and measured down directions are opposite (no unique rotation axis)
    samples = imu(lambda t: [0.0, 0.0, 0.0], 3.0, seed=3)
    st = polar_attitude_init_at(0.0, D2R(180.0), 0.0, D2R(1.0))
    # WHEN it is fed at rest THEN it is re-levelled within 1.1 s (updates of 3 samples, 60 ms)
    # and ends within 0.5 deg
    st, rows = run(samples, st)
    t_rel = next(r[0] for r in rows if r[3].relevelled)
    assert t_rel <= 1.1 and math.degrees(rows[-1][1]) < 0.5


def test_a_sustained_acceleration_is_not_taken_for_a_tilt():
    # GIVEN a level, still vehicle accelerating 2 m/s^2 along body y for 3 s (a rail launch or
    # a take-off run without rotation): |f| - g = 0.2 m/s^2, beyond the 0.1 rest tolerance,
    # and gated out update after update
    samples = imu(lambda t: [0.0, 0.0, 0.0], 6.0,
                  accel_of_t=lambda t: [0.0, 2.0 if 1.0 <= t < 4.0 else 0.0, 0.0], seed=4)
    st = polar_attitude_init_at(0.0, 0.0, 0.0, D2R(1.0))
    # WHEN the filter is fed at 50 Hz
    st, rows = run(samples, st)
    # THEN it is gated out and never re-levels (which would tilt it by atan(2/g) = 11.5 deg)
    assert any(r[3].updated and r[3].test_ratio > 1.0 for r in rows if 1.0 < r[0] < 4.0)
    assert st.n_relevels == 0 and not any(r[3].relevelled for r in rows)
    assert max(e / s for _, e, s, *_ in rows) <= 3.0 and math.degrees(rows[-1][1]) < 0.2


def _yaw_rate_ramp(t):     # rate about body x (roll) rising linearly: 20 -> 60 deg/s over 2 s
    return [D2R(20.0 + 20.0 * t), 0.0, 0.0]


@pytest.mark.parametrize("hole_s", [0.2, 0.4])
def test_a_hole_of_lost_samples_is_bridged_on_the_rates_around_it(hole_s):
    """GIVEN a roll at a linearly rising rate, 50 Hz samples, noise-free, with ``hole_s`` of
    samples lost (shorter than max_dt_s), no specific-force update in the window
    WHEN the filter steps over the hole
    THEN the roll across the hole is integrated (rate linear between the samples around it: exact
    for this rate up to the sample means) and the attitude variance grows by the bridge variance;
    a gap longer than max_dt_s is not integrated but widens the covariance instead."""
    p = PolarAttitudeParams(update_period_s=100.0, gyro_bias_init_sigma_rad_s=D2R(0.01))
    samples = imu(_yaw_rate_ramp, 2.0, gyro_noise_rad_s=0.0, accel_noise_m_s2=0.0)
    st0 = polar_attitude_init_at(0.0, 0.0, 0.0, D2R(1.0), p)
    lost = {k for k, (t, *_rest) in enumerate(samples) if 1.0 < t < 1.0 + hole_s - 1e-9}
    def roll_err_deg(st, q):   # estimated - true roll
        return math.degrees(wrap_pi(euler_from_dcm(dcm_from_quat(st.q_P_from_body))[0] - euler_from_dcm(dcm_from_quat(q))[0]))

    st, errs = st0, []
    for k, (t, w, f, q) in enumerate(samples):
        if k in lost:
            continue
        before = st
        st, d = polar_attitude_step(st, t, w, f, p)
        errs.append(roll_err_deg(st, q))
        if k - 1 in lost:   # the sample right after the hole
            h = t - before.time_s - 1.0 / RATE_HZ     # the hole: the interval less this sample's own
            assert h == pytest.approx(hole_s - 1.0 / RATE_HZ)
            grew = st.P[0, 0] - before.P[0, 0]
            step = float(np.max(np.abs(w - before.gyro_prev_rad_s))) * h
            assert grew == pytest.approx(p.gap_rate_walk_rad_s2_rt_hz ** 2 * h ** 3 / 12 + step ** 2 / 12, rel=1e-9)
            # the roll across the hole (the first sample only restarts the increments: errs[0] is
            # the 0.4 deg of its own interval, carried unchanged)
            assert abs(errs[-1] - errs[0]) < 0.01, f"roll across the hole off by {errs[-1] - errs[0]:.3f} deg"
    assert abs(errs[-1] - errs[0]) < 0.01
    # a gap beyond max_dt_s: not integrated, the covariance widened by the unseen rate
    st_gap, d = polar_attitude_step(st, st.time_s + 0.6, samples[-1][1], samples[-1][2], p)
    assert "not integrated" in d.reason
    assert np.allclose(st_gap.q_P_from_body, st.q_P_from_body)
    assert st_gap.P[0, 0] - st.P[0, 0] >= (p.unseen_rate_sigma_rad_s * 0.6) ** 2 - 1e-12
