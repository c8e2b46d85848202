"""Synthetic AHRS (METHODS.md B): KF2 measurement models, reference health, B1, B2 end to end."""
import math

import numpy as np
import pytest

from estimators.ahrs_kf2 import Kf2Params, kf2_euler_and_cov, kf2_init, kf2_predict, kf2_update_mag
from estimators.air_data import air_density_kg_m3, isa_temperature_k
from estimators.reference_health import (ReferenceHealthParams, health_init, health_on_attitude,
                                         health_on_ekf_status, health_trusted)
from estimators.rotations import (dcm_from_euler, dcm_from_quat, quat_from_euler, quat_from_rotvec,
                                  skew)
from estimators.synthetic_ahrs import (AirEvent, FcAttitudeEvent, FcStatusEvent, HeadingEvent,
                                       ImuEvent, SyntheticAhrs, SyntheticAhrsParams,
                                       synthetic_ahrs_init, synthetic_ahrs_step)

FIELD = np.array([0.23, 0.046, 0.394])
D = math.radians


def isa_pressure_pa(h_m):
    return 101325.0 * (1.0 - 0.0065 * h_m / 288.15) ** (9.80665 / (287.05287 * 0.0065))


def wrapd(a):
    return (a + 180.0) % 360.0 - 180.0


# --- KF2 measurement model ------------------------------------------------------------------

def test_kf2_mag_jacobian_matches_finite_difference():
    """z(gamma) = C_true^T B - C_hat^T B with C_true = C_hat exp([gamma x]) ~ [b0 x] gamma."""
    C_hat = dcm_from_euler(0.3, -0.2, 2.0)
    Bn = FIELD / np.linalg.norm(FIELD)
    b0 = C_hat.T @ Bn
    g = np.array([2e-4, -1e-4, 3e-4])
    C_true = C_hat @ dcm_from_quat(quat_from_rotvec(g))
    z = C_true.T @ Bn - b0
    assert np.allclose(z, skew(b0) @ g, atol=1e-7)


def test_kf2_mag_and_air_updates_fix_heading_and_tilt_errors():
    """Level, still; start 10 deg off in heading, 3 deg in roll. The magnetometer alone cannot
    see a rotation about the field vector, so the air-data roll/pitch (here level: 0, 0) pins
    the tilt and the heading follows; sigmas shrink. (Still, a body-fixed magnetometer bias and
    a heading error are inseparable, so the residual-bias states are pinned by a tight prior.)"""
    from estimators.ahrs_kf2 import kf2_update_air
    params = Kf2Params(sigma_mag_bias_init=1e-4, mag_bias_sigma=1e-4)
    true_q = quat_from_euler(0.0, 0.0, D(40.0))
    st = kf2_init(quat_from_euler(D(3.0), 0.0, D(50.0)), params, sigma_tilt_rad=D(5), sigma_heading_rad=D(20))
    m_body = dcm_from_quat(true_q).T @ FIELD
    rng = np.random.default_rng(3)
    for k in range(600):  # 60 s at 10 Hz
        st, _ = kf2_predict(st, rng.normal(0, 1e-4, 3), 0.1 * k + 1e-3 * (k % 2), params)
        st, d = kf2_update_mag(st, m_body + rng.normal(0, 0.002, 3), FIELD, params)
        if k % 10 == 0:
            st, _ = kf2_update_air(st, rng.normal(0, D(0.5)), rng.normal(0, D(0.5)), D(1.0), D(1.0), 0.0, params)
    e, cov = kf2_euler_and_cov(st)
    sig = np.degrees(np.sqrt(np.diag(cov)))
    assert abs(wrapd(math.degrees(e[2]) - 40.0)) < 0.5 and sig[2] < 1.0
    assert abs(math.degrees(e[0])) < 0.3 and abs(math.degrees(e[1])) < 0.3
    assert st.n_mag_fused == 600 and st.n_air_fused == 60
    # a magnetic disturbance (field 40 % too strong) is refused, not fused
    st2, d = kf2_update_mag(st, 1.4 * m_body, FIELD, params)
    assert not d.fused and "disturbance" in d.reason and st2.n_mag_rejected == st.n_mag_rejected + 1


def test_kf2_mag_alone_cannot_see_rotation_about_the_field():
    """Without a tilt reference the heading sigma must NOT collapse (rotation about B is
    unobservable): the filter says so instead of claiming a heading it cannot know."""
    params = Kf2Params(sigma_mag_bias_init=1e-4, mag_bias_sigma=1e-4)
    q = quat_from_euler(0.0, 0.0, D(40.0))
    st = kf2_init(q, params, sigma_tilt_rad=D(5), sigma_heading_rad=D(20))
    m_body = dcm_from_quat(q).T @ FIELD
    for k in range(300):
        st, _ = kf2_predict(st, np.zeros(3), 0.1 * k + 1e-3 * (k % 2), params)
        st, _ = kf2_update_mag(st, m_body, FIELD, params)
    _, cov = kf2_euler_and_cov(st)
    incl = math.atan2(FIELD[2], math.hypot(FIELD[0], FIELD[1]))
    assert math.degrees(math.sqrt(cov[2, 2])) > 0.8 * 5.0 * math.tan(incl) / math.sqrt(2.0)


# --- reference health -----------------------------------------------------------------------

def _health_run(drift_deg_s, n_s=120.0, noise_deg=0.3, seed=0):
    """FC attitude = truth (+ yaw drift after 20 s) + noise; our gyro attitude = truth."""
    params = ReferenceHealthParams()
    rng = np.random.default_rng(seed)
    h = health_on_ekf_status(health_init(), attitude_ok=True, horiz_pos_ok=True)   # a healthy FC's word
    detected = None
    for k in range(int(n_s * 50)):
        t = 0.02 * k
        e = np.array([0.1 * math.sin(0.1 * t), 0.05, 0.02 * t])
        C_gyro = dcm_from_euler(*e)
        drift = D(drift_deg_s) * max(0.0, t - 20.0)
        fc = e + rng.normal(0, D(noise_deg), 3) * np.array([1, 1, 1]) + np.array([0, 0, drift])
        h = health_on_attitude(h, dcm_from_euler(*fc), C_gyro, t, params)
        ok, why = health_trusted(h, t, params)
        if not ok and detected is None and t > 1.0:
            detected = (t, why)
    return detected


def test_health_silent_divergence_detected_and_normal_noise_tolerated():
    assert _health_run(0.0) is None
    t, why = _health_run(0.5)           # 0.5 deg/s silent yaw drift from t = 20 s
    assert "disagrees" in why and 20.0 < t < 40.0


def test_health_signalled_gnss_loss_untrusts_at_once_and_retrust_needs_hold():
    params = ReferenceHealthParams(retrust_hold_s=10.0)
    h = health_on_ekf_status(health_init(), attitude_ok=True, horiz_pos_ok=True)   # a healthy FC's word
    C = dcm_from_euler(0.0, 0.0, 1.0)
    for k in range(100):
        h = health_on_attitude(h, C, C, 0.02 * k, params)
    assert health_trusted(h, 2.0, params) == (True, "")
    h = health_on_ekf_status(h, attitude_ok=True, horiz_pos_ok=False)
    ok, why = health_trusted(h, 2.0, params)
    assert not ok and "GNSS" in why
    for k in range(100, 200):
        h = health_on_attitude(h, C, C, 0.02 * k, params)
    h = health_on_ekf_status(h, attitude_ok=True, horiz_pos_ok=True)
    for k in range(200, 600):   # 8 s good: still in the hold
        h = health_on_attitude(h, C, C, 0.02 * k, params)
    assert health_trusted(h, 12.0, params) == (False, "re-trust hold")
    for k in range(600, 760):
        h = health_on_attitude(h, C, C, 0.02 * k, params)
    assert health_trusted(h, 15.2, params)[0]
    assert not health_trusted(h, 16.0, params)[0]      # stale FC attitude (> 0.5 s)


# --- B1 on synthetic data -------------------------------------------------------------------

def _b1_flight(params, loss_s=60.0, n_s=300.0, seed=1):
    """Level flight at 22 m/s, 300 m, with a 25 deg-bank coordinated turn 150-190 s; gyro
    bias [0.3, -0.2, 0.25] deg/s + noise; FC trusted until loss_s; heading from outside."""
    rng = np.random.default_rng(seed)
    bias = np.radians([0.3, -0.2, 0.25])
    v, h_m, g = 22.0, 300.0, 9.80665
    p_abs = isa_pressure_pa(h_m)
    rho = air_density_kg_m3(p_abs, isa_temperature_k(h_m))
    alpha = D(3.0)
    st = synthetic_ahrs_init(params)
    st, _ = synthetic_ahrs_step(st, FcStatusEvent(0.0, system_status=4, attitude_ok=True, horiz_pos_ok=True), params)
    yaw, errs = 1.0, []
    for k in range(int(n_s * 100)):
        t = 0.01 * k
        bank = D(25.0) if 150.0 <= t < 190.0 else 0.0
        # smooth the bank in over 2 s
        if 150.0 <= t < 152.0:
            bank = D(25.0) * (t - 150.0) / 2.0
        if 188.0 <= t < 190.0:
            bank = D(25.0) * (190.0 - t) / 2.0
        roll = bank
        pitch = alpha * math.cos(roll)
        psi_dot = g * math.tan(bank) / v
        yaw += psi_dot * 0.01
        roll_dot = (D(25.0) / 2.0) * (1 if 150.0 <= t < 152.0 else -1 if 188.0 <= t < 190.0 else 0)
        w_body = np.array([roll_dot - psi_dot * math.sin(pitch),
                           psi_dot * math.cos(pitch) * math.sin(roll),
                           psi_dot * math.cos(pitch) * math.cos(roll)])
        gyro = w_body + bias + rng.normal(0, D(0.05), 3)
        st, out = synthetic_ahrs_step(st, ImuEvent(t, gyro, None), params)
        if k % 2 == 0:
            qc = 0.5 * rho * v * v + rng.normal(0, 1.0)
            st, _ = synthetic_ahrs_step(st, AirEvent(t, p_abs + rng.normal(0, 2.0), qc, 300.0), params)
            st, _ = synthetic_ahrs_step(st, FcAttitudeEvent(t, np.array([roll, pitch, yaw]) + rng.normal(0, D(0.2), 3)), params)
        if k % 10 == 0:
            st, out = synthetic_ahrs_step(st, HeadingEvent(t, yaw, D(1.0)), params)
        if abs(t - loss_s) < 1e-9:
            st, _ = synthetic_ahrs_step(st, FcStatusEvent(t, horiz_pos_ok=False), params)
        if t > loss_s and k % 10 == 0:
            errs.append((t, math.degrees(out.roll_rad - roll), math.degrees(out.pitch_rad - pitch),
                         wrapd(math.degrees(out.heading_rad - yaw)), out))
    return st, errs


def test_b1_holds_roll_pitch_after_reference_loss():
    params = SyntheticAhrsParams(variant="b1")
    st, errs = _b1_flight(params)
    r = np.array([[e[1], e[2], e[3]] for e in errs])
    outs = [e[4] for e in errs]
    assert not any(o.reference_trusted for o in outs)
    assert np.sqrt(np.mean(r[:, 0] ** 2)) < 0.6 and np.abs(r[:, 0]).max() < 2.0
    assert np.sqrt(np.mean(r[:, 1] ** 2)) < 0.6 and np.abs(r[:, 1]).max() < 1.5
    assert np.abs(r[:, 2]).max() < 0.01                 # heading is the external one
    # zero correction learnt while trusted, then frozen: c = -bias within 0.02 deg/s
    assert np.allclose(np.degrees(st.b1.zero_corr_rad_s), [-0.3, 0.2, -0.25], atol=0.02)
    assert any(o.air_correction_active for o in outs)
    assert any(o.air_off_reason == "attitude rate beyond limit" for o in outs)


def test_b1_without_air_data_drifts_more():
    """The air-data correction is what holds B1: with the pitot blocked it drifts."""
    params = SyntheticAhrsParams(variant="b1")
    _, errs = _b1_flight(params, n_s=300.0)
    with_air = np.sqrt(np.mean([e[1] ** 2 + e[2] ** 2 for e in errs]))
    import estimators.synthetic_ahrs as sa
    params_off = SyntheticAhrsParams(variant="b1", b1=sa.B1Params(roll_limit_rad=1e-9, pitch_limit_rad=1e-9))
    _, errs_off = _b1_flight(params_off, n_s=300.0)
    without = np.sqrt(np.mean([e[1] ** 2 + e[2] ** 2 for e in errs_off]))
    assert without > 2.0 * with_air


# --- B2 end to end on the simulator ---------------------------------------------------------

@pytest.fixture(scope="module")
def sim_run():
    from sim.offline import simulate
    return simulate("runway_gnss_denied", seed=3, imu_rate_hz=100.0, duration_s=330.0,
                    overrides={"gnss": {"lost_at_s": 120.0}, "launcher": {"rest_s": 60.0}})


def _run_b2(run, signalled, start_s=0.0, fc=True, wrapper=False):
    from estimators.geomag import earth_field_ned_gauss
    s = run.site
    params = SyntheticAhrsParams(variant="b2", C_body_from_sensor=s["C_body_from_sensor"],
                                 field_nav_gauss=tuple(earth_field_ned_gauss(s["lat_deg"], s["lon_deg"],
                                                                             s["alt_m"], s["decimal_year"])))
    t0 = run.time_s[0] if start_s == 0.0 else start_s
    ev = [(t0, 0, FcStatusEvent(t0, system_status=4, attitude_ok=True, horiz_pos_ok=not (start_s > run.gnss_lost_time_s)))]
    ev += [(t, 1, ImuEvent(t, g, m)) for t, g, m in zip(run.time_s, run.gyro_rad_s, run.mag_gauss)]
    ev += [(t, 2, AirEvent(t, p, q, T)) for t, p, q, T in zip(run.baro_time_s, run.press_abs_pa,
                                                             run.press_diff_pa, run.temperature_k)]
    if fc:
        ev += [(t, 3, FcAttitudeEvent(t, e)) for t, e in zip(run.fc_time_s, run.fc_euler_rad)]
    ev = [x for x in ev if x[0] >= start_s]
    if signalled and run.gnss_lost_time_s >= start_s:
        ev.append((run.gnss_lost_time_s, 0, FcStatusEvent(run.gnss_lost_time_s, horiz_pos_ok=False)))
    ev.sort(key=lambda x: (x[0], x[1]))
    st = synthetic_ahrs_init(params)
    obj = SyntheticAhrs(params)
    rows, k = [], int(np.searchsorted(run.time_s, start_s))
    for _, _, e in ev:
        is_imu = isinstance(e, ImuEvent)
        if wrapper:
            out = obj.step(e, output=is_imu and k % 10 == 0)
            st = obj.state
        else:
            st, out = synthetic_ahrs_step(st, e, params, output=is_imu and k % 10 == 0)
        if is_imu:
            if out is not None:
                tr = run.truth.euler_rad[k]
                rows.append((e.time_s, math.degrees(out.roll_rad - tr[0]), math.degrees(out.pitch_rad - tr[1]),
                             wrapd(math.degrees(out.heading_rad - tr[2])), math.degrees(out.heading_sigma_rad),
                             out.reference_trusted, out.kf1_learning))
            k += 1
    return st, np.array(rows, dtype=float)


def test_b2_after_signalled_loss_meets_accuracy(sim_run):
    st, r = _run_b2(sim_run, signalled=True)
    after = r[r[:, 0] > 120.0]
    before = r[(r[:, 0] > 30.0) & (r[:, 0] < 119.0)]
    assert before[:, 5].all() and not after[:, 5].any()          # trusted until the loss, then not
    assert before[:, 6].all() and not after[:, 6].any()          # KF1 learns only while trusted
    assert np.sqrt(np.mean(after[:, 1] ** 2)) < 1.0
    assert np.sqrt(np.mean(after[:, 2] ** 2)) < 1.5
    assert np.sqrt(np.mean(after[:, 3] ** 2)) < 2.5
    # the heading sigma is not wildly optimistic: |error| within 4 sigma 95 % of the time
    assert np.mean(np.abs(after[:, 3]) < 4.0 * after[:, 4]) > 0.95
    assert st.kf2.n_air_fused > 50 and st.kf2.n_mag_fused > 1000


def test_b2_silent_degradation_is_detected_and_bounded(sim_run):
    st, r = _run_b2(sim_run, signalled=False)
    after = r[r[:, 0] > 120.0]
    lost = after[after[:, 5] == 0]
    assert len(lost) and lost[0, 0] < 170.0                     # detected by the agreement test
    assert not after[after[:, 0] > lost[0, 0] + 1.0, 5].any()    # and never trusted again
    late = r[r[:, 0] > lost[0, 0] + 30.0]
    assert np.sqrt(np.mean(late[:, 3] ** 2)) < 3.0


def test_params_validation():
    with pytest.raises(ValueError, match="variant"):
        SyntheticAhrsParams(variant="b3")
    with pytest.raises(ValueError, match="field_nav_gauss"):
        SyntheticAhrsParams(variant="b2")
    with pytest.raises(ValueError, match="rotation"):
        SyntheticAhrsParams(variant="b1", C_body_from_sensor=np.diag([1.0, 1.0, -1.0]))


def test_params_for_site_uses_the_wmm_field():
    from estimators.geomag import earth_field_ned_gauss
    from estimators.synthetic_ahrs import synthetic_ahrs_params_for_site
    p = synthetic_ahrs_params_for_site(34.05, -117.6, 300.0, 2026.9, variant="b2",
                                       C_body_from_sensor=dcm_from_euler(0.0, 0.0, math.pi))
    assert np.allclose(p.field_nav_gauss, earth_field_ned_gauss(34.05, -117.6, 300.0, 2026.9), atol=0)
    assert np.allclose(np.array(p.C_body_from_sensor), dcm_from_euler(0.0, 0.0, math.pi))
    st = synthetic_ahrs_init(p)
    st, out = synthetic_ahrs_step(st, ImuEvent(0.0, np.zeros(3), np.array([0.2, 0.0, 0.4])), p)
    assert out is not None and not out.valid and math.isnan(out.heading_rad)   # waits for a reference


def test_b2_restart_after_the_loss_starts_from_magnetometer_and_air_data(sim_run):
    """The daemon restarts at 200 s, after the GNSS loss: no trusted reference ever. KF2 starts
    level with the magnetometer heading and converges on the magnetometer and air data."""
    st, r = _run_b2(sim_run, signalled=True, start_s=200.0)
    assert not r[:, 5].any()
    valid = r[np.isfinite(r[:, 1])]
    assert valid[0, 0] < 206.0                                   # started ~5 s after the restart
    # pitch converges slowly (its air-data reference is gusty and weighted weakly, the gyro
    # biases are unknown): worst around 30-70 s after the start, then converging
    mid = valid[(valid[:, 0] > 230.0) & (valid[:, 0] < 270.0)]
    late = valid[valid[:, 0] > 300.0]
    assert np.sqrt(np.mean(late[:, 1] ** 2)) < 0.5 and np.sqrt(np.mean(late[:, 2] ** 2)) < 3.0
    assert np.sqrt(np.mean(late[:, 2] ** 2)) < 0.6 * np.sqrt(np.mean(mid[:, 2] ** 2))
    assert np.sqrt(np.mean(late[:, 3] ** 2)) < 3.0


def test_wrapper_equals_pure_step(sim_run):
    st_a, r_a = _run_b2(sim_run, signalled=True, start_s=280.0)
    st_b, r_b = _run_b2(sim_run, signalled=True, start_s=280.0, wrapper=True)
    assert np.array_equal(r_a, r_b, equal_nan=True)
    assert np.array_equal(st_a.kf2.P, st_b.kf2.P)


def test_kf2_heading_only_mag_measurement_model():
    """z = heading error for a correct tilt; H_beta matches a finite difference; tilt untouched."""
    from estimators.ahrs_kf2 import kf2_update_mag_heading
    params = Kf2Params()
    e_true = (D(10.0), D(-5.0), D(120.0))
    m_body = dcm_from_euler(*e_true).T @ FIELD
    st = kf2_init(quat_from_euler(D(10.0), D(-5.0), D(123.0)), params, sigma_tilt_rad=D(1),
                  sigma_heading_rad=D(10))
    st2, d = kf2_update_mag_heading(st, m_body, FIELD, params)
    assert d.fused and d.innovation[0] == pytest.approx(D(-3.0), abs=1e-9)
    e2, _ = kf2_euler_and_cov(st2)
    assert abs(math.degrees(e2[2]) - 120.0) < abs(123.0 - 120.0) * 0.5
    # roll/pitch move only through their prior correlation with heading (none here): < 0.01 deg
    assert abs(math.degrees(e2[0]) - 10.0) < 0.01 and abs(math.degrees(e2[1]) + 5.0) < 0.01
    # the beta column: z(beta + h e_i) - z(beta) over h against -(x C1 - y C0) / r^2
    C = dcm_from_quat(st.q_nav_from_body)
    norm = np.linalg.norm(FIELD)

    def z_of(beta):
        mh = C @ (m_body / norm - beta)
        return math.atan2(FIELD[1], FIELD[0]) - math.atan2(mh[1], mh[0])
    mh = C @ (m_body / norm)
    x, y = mh[0], mh[1]
    H_beta = -(x * C[1, :] - y * C[0, :]) / (x * x + y * y)
    h = 1e-7
    # measured m = C^T B + beta_hat + dbeta: a true dbeta adds +dbeta to m, i.e. -dbeta to beta_hat
    num = np.array([(z_of(-h * np.eye(3)[i]) - z_of(np.zeros(3))) / h for i in range(3)])
    assert np.allclose(num, H_beta, atol=1e-5)
