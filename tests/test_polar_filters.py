"""Polar cascade (METHODS.md C): attitude filter independent of latitude, heading filter honest
when the horizontal field is too weak. Synthetic data built here from analytic Euler angles."""
import math

import numpy as np
import pytest

from estimators.polar_attitude import (PolarAttitudeParams, PolarAttitudeState, polar_attitude_estimate,
                                       polar_attitude_init, polar_attitude_step, roll_pitch_jacobian)
from estimators.polar_heading import (HeadingInputs, PolarHeadingParams, PolarHeadingState,
                                      magnetic_heading, polar_heading_estimate, polar_heading_init,
                                      polar_heading_step)
from estimators.rotations import (dcm_from_euler, dcm_from_quat, euler_from_dcm, quat_from_euler,
                                  quat_from_rotvec, quat_mul, wrap_pi)

W = 7.292115e-5
G = 9.81


def _euler(t):
    ramp = np.clip(t / 20.0 - 0.5, 0.0, 1.0)
    roll = np.radians(20.0) * np.sin(2 * np.pi * t / 40.0) * ramp
    pitch = np.radians(8.0) * np.sin(2 * np.pi * t / 70.0 + 0.3) * ramp
    u = (t - 30.0) % 60.0
    x = np.clip(u / 15.0, 0.0, 1.0)
    nturn = np.floor(np.clip(t - 30.0, 0.0, None) / 60.0)
    yaw = np.radians(30.0) + np.radians(90.0) * (nturn + np.where(t > 30.0, x * x * (3 - 2 * x), 0.0))
    return roll, pitch, yaw


def _dcm(r, p, y):
    return np.array([dcm_from_euler(a, b, c) for a, b, c in zip(r, p, y)])


def synth(lat_deg, duration_s=180.0, rate_hz=100.0, gyro_bias=(0.0, 0.0, 0.0), field_ned=None,
          mag_noise=0.0, seed=0):
    """Body rates from analytic ZYX Euler angles; gyro = w_nb + C_bn w_ie; accel = -C_bn g."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    h = 1e-4
    r, p, y = _euler(t)
    rp, pp, yp = _euler(t + h)
    rm, pm, ym = _euler(t - h)
    rd, pd, yd = (rp - rm) / (2 * h), (pp - pm) / (2 * h), (yp - ym) / (2 * h)
    w_nb = np.stack([rd - yd * np.sin(p), pd * np.cos(r) + yd * np.cos(p) * np.sin(r),
                     -pd * np.sin(r) + yd * np.cos(p) * np.cos(r)], 1)
    C = _dcm(r, p, y)
    L = math.radians(lat_deg)
    w_ie = W * np.array([math.cos(L), 0.0, -math.sin(L)])
    gyro = w_nb + np.einsum("nji,j->ni", C, w_ie) + np.asarray(gyro_bias)
    accel = np.einsum("nji,j->ni", C, np.array([0.0, 0.0, -G]))
    mag = None
    if field_ned is not None:
        rng = np.random.default_rng(seed)
        mag = np.einsum("nji,j->ni", C, np.asarray(field_ned)) + rng.normal(0.0, mag_noise, (len(t), 3)) \
            if mag_noise > 0 else np.einsum("nji,j->ni", C, np.asarray(field_ned))
    return t, gyro, accel, mag, np.stack([r, p, y], 1)


def run_attitude(t, gyro, accel, params, **init):
    st = polar_attitude_init(params, **init)
    idx, out = [], []
    for k in range(len(t)):
        st, d = polar_attitude_step(st, t[k], gyro[k], accel[k], params)
        if d.updated:
            e = polar_attitude_estimate(st)
            idx.append(k)
            out.append((e.roll_rad, e.pitch_rad))
    return st, np.array(idx), np.array(out)


PARAMS = PolarAttitudeParams(gravity_m_s2=G)


def test_roll_pitch_at_89_9_equal_those_at_45_on_the_same_manoeuvre():
    res = {}
    for lat in (45.0, 89.9):
        t, gyro, accel, _, truth = synth(lat)
        _, idx, rp = run_attitude(t, gyro, accel, PARAMS)
        res[lat] = (idx, rp, truth)
    (i45, rp45, truth), (i90, rp90, _) = res[45.0], res[89.9]
    np.testing.assert_array_equal(i45, i90)
    err45 = np.degrees(rp45 - truth[i45, :2])
    err90 = np.degrees(rp90 - truth[i90, :2])
    # both accurate on a manoeuvre with 90-deg turns and +-20 deg of roll ...
    assert np.abs(err45).max() < 0.2 and np.abs(err90).max() < 0.2
    # ... and the same at 45 deg and at 89.9 deg (only the Earth rate in the gyros differs)
    assert np.abs(np.degrees(rp45 - rp90)).max() < 0.15
    assert np.sqrt(np.mean(np.degrees(rp45 - rp90) ** 2)) < 0.06


def test_attitude_filter_estimates_a_gyro_bias_and_keeps_level():
    """GIVEN gyro biases of 0.3/-0.2/0.1 deg/s, a prior with only the vertical one (as levelling
    at rest gives it to ~0.01 deg/s: the horizontal ones are what the filter must find)."""
    bias = np.radians([0.3, -0.2, 0.1])
    t, gyro, accel, _, truth = synth(60.0, duration_s=120.0, gyro_bias=bias)
    st, idx, rp = run_attitude(t, gyro, accel, PARAMS, gyro_bias_rad_s=np.array([0.0, 0.0, bias[2]]),
                               gyro_bias_sigma_rad_s=math.radians(0.5))
    err = np.degrees(rp - truth[idx, :2])
    assert np.abs(err[t[idx] > 20.0]).max() < 0.3
    # horizontal biases observed through the tilt they cause while the body turns
    np.testing.assert_allclose(st.x_hat[0:2], bias[0:2], atol=np.radians(0.02))


def test_attitude_save_restore_equals_unbroken_run():
    t, gyro, accel, _, _ = synth(45.0, duration_s=20.0)
    a = polar_attitude_init()
    for k in range(len(t)):
        a, _ = polar_attitude_step(a, t[k], gyro[k], accel[k], PARAMS)
    b = polar_attitude_init()
    for k in range(len(t) // 2):
        b, _ = polar_attitude_step(b, t[k], gyro[k], accel[k], PARAMS)
    b = PolarAttitudeState.from_dict(b.to_dict())
    for k in range(len(t) // 2, len(t)):
        b, _ = polar_attitude_step(b, t[k], gyro[k], accel[k], PARAMS)
    np.testing.assert_array_equal(a.q_P_from_body, b.q_P_from_body)
    np.testing.assert_array_equal(a.P, b.P)


def test_roll_pitch_jacobian_matches_finite_differences():
    q = quat_from_euler(0.4, -0.3, 1.1)
    J = roll_pitch_jacobian(q)
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        rp = [euler_from_dcm(dcm_from_quat(quat_mul(q, quat_from_rotvec(s * e))))[:2] for s in (1, -1)]
        num = (np.array(rp[0]) - np.array(rp[1])) / (2 * h)
        np.testing.assert_allclose(J[:, i], num, atol=1e-6)


def test_error_dynamics_of_the_attitude_block():
    """eps' = -w x eps: a body-frame error eps0 on C_PB is carried as R^T eps0 by the rotation."""
    C0 = dcm_from_euler(0.2, 0.1, 0.5)
    eps0 = np.array([1e-4, -2e-4, 3e-4])
    w = np.array([0.3, -0.5, 0.8])
    T = 0.5
    R = dcm_from_quat(quat_from_rotvec(w * T))          # body rotation over T
    skew = lambda v: np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    C_true = C0 @ (np.eye(3) + skew(eps0)) @ R
    C_hat = C0 @ R
    E = C_hat.T @ C_true - np.eye(3)
    eps_T = np.array([E[2, 1], E[0, 2], E[1, 0]])
    np.testing.assert_allclose(eps_T, R.T @ eps0, atol=1e-8)


def test_params_validation():
    with pytest.raises(ValueError, match="update_period_s"):
        PolarAttitudeParams(update_period_s=0.0)
    with pytest.raises(ValueError, match="min_horizontal_field_gauss"):
        PolarHeadingParams(min_horizontal_field_gauss=-1.0)


def test_magnetic_heading_analytic():
    field = np.array([0.2, 0.0, 0.4])      # magnetic north, dip down
    for roll, pitch, yaw in ((0.0, 0.0, 0.7), (0.3, -0.2, 2.5), (-0.5, 0.4, 5.9)):
        m = dcm_from_euler(roll, pitch, yaw).T @ field
        psi, H = magnetic_heading(m, roll, pitch)
        assert abs(wrap_pi(psi - yaw)) < 1e-12
        assert abs(H - 0.2) < 1e-12


def _run_cascade(lat_deg, field_ned, decl, duration_s, init=None, ph=PolarHeadingParams(), seed=3):
    t, gyro, accel, mag, truth = synth(lat_deg, duration_s=duration_s, field_ned=field_ned,
                                       mag_noise=0.002, seed=seed)
    sa = polar_attitude_init()
    sh = polar_heading_init(*init, params=ph) if init else polar_heading_init()
    est, rows = None, []
    for k in range(len(t)):
        sa, d = polar_attitude_step(sa, t[k], gyro[k], accel[k], PARAMS)
        if d.updated:
            est = polar_attitude_estimate(sa)
        if est is None:
            continue
        sh, dh = polar_heading_step(sh, HeadingInputs(t[k], gyro[k], est.roll_rad, est.pitch_rad,
                                                      est.cov_roll_pitch_rad2, mag[k], decl, 0.0,
                                                      mag_residual_sigma_gauss=0.0), ph)  # no iron
        he = polar_heading_estimate(sh)
        rows.append((k, he.heading_rad, he.variance_rad2, he.source_available, est.roll_rad))
    r = np.array(rows)
    return r, truth


def test_heading_filter_tracks_true_heading_with_a_strong_field():
    decl = math.radians(4.0)
    field = 0.23 * np.array([math.cos(decl), math.sin(decl), 0.0]) + np.array([0, 0, 0.41])
    r, truth = _run_cascade(45.0, field, decl, 120.0)
    k = r[:, 0].astype(int)
    err = np.array([wrap_pi(a) for a in r[:, 1] - truth[k, 2]])
    assert np.all(r[:, 3] == 1.0)
    assert math.degrees(np.sqrt(np.mean(err ** 2))) < 0.3
    assert np.all(np.abs(err) < 3.0 * np.sqrt(r[:, 2]))       # the variance is not optimistic
    assert math.degrees(np.sqrt(r[-1, 2])) < 2.0               # ... nor useless


def test_weak_horizontal_field_heading_unavailable_variance_grows_roll_pitch_continue():
    decl = 0.3
    field = 0.018 * np.array([math.cos(decl), math.sin(decl), 0.0]) + np.array([0, 0, 0.57])
    r, truth = _run_cascade(89.9, field, decl, 90.0, init=(math.radians(30.0), math.radians(2.0)))
    k = r[:, 0].astype(int)
    assert not np.any(r[:, 3] == 1.0)                    # source never available
    assert np.all(np.diff(r[:, 2]) >= -1e-15)           # variance only grows
    assert r[-1, 2] > r[0, 2]
    err = np.array([wrap_pi(a) for a in r[:, 1] - truth[k, 2]])
    assert np.all(np.abs(err) < 3.0 * np.sqrt(r[:, 2]) + 1e-3)  # honest (noiseless gyros)
    assert np.abs(np.degrees(r[:, 4] - truth[k, 0])).max() < 0.2


def test_heading_save_restore_equals_unbroken_run():
    decl = 0.05
    field = np.array([0.2, 0.01, 0.4])
    t, gyro, accel, mag, truth = synth(45.0, duration_s=5.0, field_ned=field)
    inputs = [HeadingInputs(t[k], gyro[k], truth[k, 0], truth[k, 1], np.eye(2) * 1e-5, mag[k], decl, 0.0)
              for k in range(len(t))]
    a = polar_heading_init()
    for u in inputs:
        a, _ = polar_heading_step(a, u)
    b = polar_heading_init()
    for u in inputs[:200]:
        b, _ = polar_heading_step(b, u)
    b = PolarHeadingState.from_dict(b.to_dict())
    for u in inputs[200:]:
        b, _ = polar_heading_step(b, u)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
    assert a.r_uncal_rad2 == b.r_uncal_rad2 > 0.0      # the uncalibrated consider term survives
    assert polar_heading_estimate(a) == polar_heading_estimate(b)


def test_horizontal_field_threshold_is_configurable():
    decl = 0.3
    field = 0.018 * np.array([math.cos(decl), math.sin(decl), 0.0]) + np.array([0, 0, 0.57])
    r, truth = _run_cascade(89.9, field, decl, 40.0, ph=PolarHeadingParams(min_horizontal_field_gauss=0.01))
    assert np.all(r[:, 3] == 1.0)                        # 0.018 G now counts as a source
    k = r[:, 0].astype(int)
    err = np.array([wrap_pi(a) for a in r[:, 1] - truth[k, 2]])
    assert np.all(np.abs(err) < 3.0 * np.sqrt(r[:, 2]))  # Z/H = 32: a large but honest sigma


def test_class_wrapper_equals_pure_steps():
    from estimators.polar_attitude import PolarAttitudeFilter
    t, gyro, accel, _, _ = synth(45.0, duration_s=5.0)
    f = PolarAttitudeFilter(PARAMS)
    s = polar_attitude_init(PARAMS)
    for k in range(len(t)):
        f.step(t[k], gyro[k], accel[k])
        s, _ = polar_attitude_step(s, t[k], gyro[k], accel[k], PARAMS)
    np.testing.assert_array_equal(f.state.P, s.P)
    assert f.estimate().roll_rad == polar_attitude_estimate(s).roll_rad


def test_disturbed_source_is_gated_then_reset_with_the_jump_reported():
    """GIVEN a heading source that jumps by 40 deg and stays there (e.g. a new magnetic
    disturbance), THEN the filter rejects it, and re-initialises after reset_after_s."""
    field = np.array([0.2, 0.0, 0.4])
    t, gyro, accel, mag, truth = synth(45.0, duration_s=40.0, field_ned=field)
    rot = dcm_from_euler(0.0, 0.0, math.radians(-40.0))        # body field turned: heading +40
    ph = PolarHeadingParams(reset_after_s=5.0)
    st = polar_heading_init()
    resets, rejected = [], 0
    for k in range(len(t)):
        m = mag[k] if t[k] < 20.0 else dcm_from_euler(truth[k, 0], truth[k, 1], truth[k, 2]).T @ (rot @ field)
        st, d = polar_heading_step(st, HeadingInputs(t[k], gyro[k], truth[k, 0], truth[k, 1], np.eye(2) * 1e-6,
                                                     m, 0.0, 0.0), ph)
        rejected += d.measured and not d.fused
        if d.reset:
            resets.append((t[k], d.reset_jump_rad))
    assert rejected > 0 and len(resets) == 1
    t_reset, jump = resets[0]
    assert 25.0 <= t_reset <= 25.5
    assert abs(math.degrees(jump) - 40.0) < 1.0


def test_consider_floor_bounds_the_reported_variance():
    field = np.array([0.2, 0.0, 0.4])
    t, gyro, accel, mag, truth = synth(45.0, duration_s=20.0, field_ned=field)
    out = {}
    for frac in (0.0, 1.0):
        ph = PolarHeadingParams(consider_floor_fraction=frac, mag_heading_floor_rad=math.radians(5.0))
        st = polar_heading_init()
        for k in range(len(t)):
            st, _ = polar_heading_step(st, HeadingInputs(t[k], gyro[k], truth[k, 0], truth[k, 1],
                                                         np.eye(2) * 1e-5, mag[k], 0.0, 0.0, 0.0), ph)
        out[frac] = (polar_heading_estimate(st).variance_rad2, st)
    var0, st0 = out[0.0]
    var1, st1 = out[1.0]
    np.testing.assert_array_equal(st0.P, st1.P)             # the gain is not affected
    assert var0 == st0.P[0, 0]
    assert var1 == st1.r_corr_avg_rad2 > var0
    assert abs(st1.r_corr_avg_rad2 - math.radians(5.0) ** 2) < 0.05 * math.radians(5.0) ** 2
    with pytest.raises(ValueError, match="consider_floor_fraction"):
        PolarHeadingParams(consider_floor_fraction=1.5)
