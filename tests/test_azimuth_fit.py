"""Analytical tests of the psi_s fits, their covariance and the observability gate (METHODS.md A 5-8)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from estimators import azimuth_fit as af
from estimators.rotations import dcm_from_euler, rot_x, rot_y, rot_z, wrap_pi
from test_azimuth_synth import E_NED_GAUSS, MANOEUVRE, launcher_attitude, make_flight, rot_about

E = E_NED_GAUSS


def fit_data_from_attitudes(C_nf_isf, C_isf_sf_list, A=np.eye(3), b=np.zeros(3), noise=0.0, seed=0, G=None):
    """Samples h = A C_SF<-NF e + b (+ noise) at the given attitudes."""
    rng = np.random.default_rng(seed)
    C_sf_isf = np.array([C.T for C in C_isf_sf_list])
    h = np.einsum("ij,njk,kl,l->ni", A, C_sf_isf, C_nf_isf.T, E) + b
    if noise:
        h = h + rng.normal(0.0, noise, h.shape)
    n = len(h)
    var = np.full(n, max(noise, 1e-3) ** 2)
    return af.FitData(C_sf_isf, h, var, 1.0 / var, G)


def diverse_attitudes(n=60, seed=1, max_angle=1.2):
    rng = np.random.default_rng(seed)
    out = [np.eye(3)]
    for _ in range(n - 1):
        v = rng.normal(size=3)
        out.append(rot_about(v, rng.uniform(0.2, max_angle)))
    return out


def test_C_isf_from_af_matches_zyx_euler():
    """C_NF<-ISF = R3(psi)^T C_AF<-ISF, with C_ISF<-AF = R1(roll) R2(pitch)."""
    roll, pitch, yaw = 0.3, -0.4, 2.2
    C_nf_isf = dcm_from_euler(roll, pitch, yaw)
    np.testing.assert_allclose(af.r3(yaw).T @ af.C_isf_from_af(roll, pitch).T, C_nf_isf, atol=1e-15)


@pytest.mark.parametrize("psi", [0.0, 0.4, 1.7, 3.3, 6.1])
def test_psi_from_one_sample_is_exact(psi):
    """h_AF = R3(psi) e  =>  psi = delta - atan2(h_y, h_x) (eq. 5.3)."""
    h_af = af.r3(psi) @ E
    assert abs(wrap_pi(af.psi_from_sample(h_af, E) - psi)) < 1e-14


def test_closed_form_2d_fit_is_the_least_squares_rotation():
    rng = np.random.default_rng(3)
    psi = 2.0
    h = np.array([af.r3(psi) @ E for _ in range(50)]) + rng.normal(0, 0.02, (50, 3))
    w = rng.uniform(0.5, 2.0, 50)
    psi_cf = af.psi_closed_form(h, E, w)
    grid = np.linspace(psi - 0.2, psi + 0.2, 40001)
    cost = [float(w @ np.sum((h[:, :2] - (af.r3(g) @ E)[:2]) ** 2, axis=1)) for g in grid]
    assert abs(psi_cf - grid[int(np.argmin(cost))]) < 2e-5


def test_known_launch_attitude_gives_exact_azimuth():
    """Nose at azimuth 37 deg, elevation 60 deg, IMU mounted with an arbitrary rotation: the
    azimuth of u from psi_s, roll/pitch of ISF and C_ISF<-SF = I is 37 deg exactly."""
    C_bs = rot_z(0.5) @ rot_y(-0.3) @ rot_x(1.1)   # C_body<-sensor
    C_nf_isf = launcher_attitude(math.radians(37.0), math.radians(60.0), C_bs)
    psi = math.atan2(C_nf_isf[1, 0], C_nf_isf[0, 0])
    roll = math.atan2(C_nf_isf[2, 1], C_nf_isf[2, 2])
    pitch = -math.asin(C_nf_isf[2, 0])
    C_isf_af = af.C_isf_from_af(roll, pitch)
    u_sf = C_bs[0]  # nose in SF
    az, sig, _ = af.direction_azimuth_and_sigma(u_sf, af.r3(psi).T, C_isf_af.T, np.eye(3), np.zeros((3, 0)),
                                                np.zeros((3, 3)), 0.0)
    assert abs(math.degrees(az) - 37.0) < 1e-12
    assert sig == 0.0


@pytest.mark.parametrize("model", ["none", "seed7", "full12"])
def test_fit_recovers_injected_distortion_exactly(model):
    """Noiseless samples: psi_s, scales/soft iron and biases come back to < 1e-9."""
    C_nf_isf = dcm_from_euler(0.2, 0.7, 4.0)
    if model == "none":
        A, b = np.eye(3), np.zeros(3)
    elif model == "seed7":
        A, b = np.diag([1.08, 0.93, 1.15]), np.array([0.12, -0.07, 0.05])
    else:
        A = np.array([[1.10, 0.06, -0.04], [0.03, 0.90, 0.08], [-0.05, 0.02, 1.05]])
        b = np.array([-0.09, 0.15, 0.04])
    data = fit_data_from_attitudes(C_nf_isf, diverse_attitudes(), A, b)
    roll = math.atan2(C_nf_isf[2, 1], C_nf_isf[2, 2])
    pitch = -math.asin(C_nf_isf[2, 0])
    fit = af.fit_psi(data, af.C_isf_from_af(roll, pitch), E, model)
    assert fit.ok
    assert abs(wrap_pi(fit.psi_rad - 4.0)) < 1e-9
    np.testing.assert_allclose(fit.A, A, atol=1e-9)
    np.testing.assert_allclose(fit.b_gauss, b, atol=1e-9)
    assert fit.residual_rms_gauss < 1e-12


def test_seed_k1_kdb1_satisfy_eq_9_6():
    """k1_i h_i = m_i + kdb1_i with k1 = 1/s and kdb1 = b/s."""
    A, b = np.diag([1.08, 0.93, 1.15]), np.array([0.12, -0.07, 0.05])
    k1, kdb1 = af.seed_k1_kdb1(A, b)
    m = np.array([0.1, -0.3, 0.4])
    h = A @ m + b
    np.testing.assert_allclose(k1 * h, m + kdb1, atol=1e-15)


def test_large_hard_iron_still_finds_the_global_minimum():
    """Hard iron twice the Earth field: the 2-D closed form is far off, the profile grid is not."""
    C_nf_isf = dcm_from_euler(0.0, 0.3, 1.0)
    A, b = np.diag([1.0, 1.0, 1.0]), np.array([0.6, -0.8, 0.3])
    data = fit_data_from_attitudes(C_nf_isf, diverse_attitudes(seed=5), A, b)
    fit = af.fit_psi(data, af.C_isf_from_af(0.0, 0.3), E, "seed7")
    assert abs(wrap_pi(fit.psi_rad - 1.0)) < 1e-9


def test_gate_refuses_a_flight_without_orientation_change_and_says_why():
    C_nf_isf = dcm_from_euler(0.0, 0.5, 2.0)
    data = fit_data_from_attitudes(C_nf_isf, [np.eye(3)] * 80, np.diag([1.1, 1.0, 0.9]),
                                   np.array([0.05, 0.0, -0.02]), noise=0.002)
    C_isf_af = af.C_isf_from_af(0.0, 0.5)
    fit = af.fit_psi(data, C_isf_af, E, "seed7")
    div = af.orientation_diversity_rad(data.C_sf_from_isf @ C_isf_af, fit.psi_rad, E)
    assert div < 1e-6
    reason = af.gate_reason(fit, 80, div, math.sqrt(af.psi_variance(fit, np.zeros((2, 2)))), af.GateParams())
    assert reason.startswith("orientation diversity 0.0 deg < 20 deg required")


def test_gate_full12_yaw_only_is_unobservable():
    """Derived: with a full soft-iron matrix and rotations about the vertical only,
    M_i R3(d) M_i^T is the same for every sample, so psi_s trades against A: the Jacobian is
    singular and the gate says so, although the field direction in SF sweeps a wide cone."""
    C_nf_isf = dcm_from_euler(0.4, 0.6, 0.8)                      # tilted sensor at launch
    C_isf_af = af.C_isf_from_af(0.4, 0.6)
    atts = [C_nf_isf.T @ rot_z(a) @ C_nf_isf for a in np.linspace(0.0, 2.5, 60)]  # yaw about down
    data = fit_data_from_attitudes(C_nf_isf, atts, noise=0.001)
    fit = af.fit_psi(data, C_isf_af, E, "full12")
    div = af.orientation_diversity_rad(data.C_sf_from_isf @ C_isf_af, fit.psi_rad, E)
    assert div > math.radians(20)   # diversity alone would pass
    reason = af.gate_reason(fit, 60, div, 0.0, af.GateParams())
    assert reason.startswith("Jacobian condition number")
    # the seed's diagonal model cannot absorb that rotation: observable on the same samples
    fit7 = af.fit_psi(data, C_isf_af, E, "seed7")
    assert fit7.condition_number < af.GateParams().max_condition_number
    assert abs(wrap_pi(fit7.psi_rad - 0.8)) < math.radians(1.0)


def test_gate_seed7_rotation_about_a_sensor_axis_is_unobservable():
    """Rotating about sensor z leaves m_z constant: s_z and b_z cannot be told apart."""
    C_nf_isf = dcm_from_euler(0.4, 0.6, 0.8)
    C_isf_af = af.C_isf_from_af(0.4, 0.6)
    data = fit_data_from_attitudes(C_nf_isf, [rot_z(a) for a in np.linspace(0.0, 2.5, 60)], noise=0.001)
    fit = af.fit_psi(data, C_isf_af, E, "seed7")
    assert af.gate_reason(fit, 60, 1.0, 0.0, af.GateParams()).startswith("Jacobian condition number")


def test_gate_withholds_few_samples_and_bad_fit():
    p = af.GateParams()
    assert af.gate_reason(None, 5, 1.0, 0.0, p) == "5 magnetometer samples < 30 required"
    C_nf_isf = dcm_from_euler(0.1, 0.4, 3.0)
    data = fit_data_from_attitudes(C_nf_isf, diverse_attitudes(), noise=0.0)
    bad = af.FitData(data.C_sf_from_isf, data.h_sf_gauss + np.random.default_rng(0).normal(0, 0.05, data.h_sf_gauss.shape),
                     np.full(len(data.weight), 1e-6), np.full(len(data.weight), 1e6))
    fit = af.fit_psi(bad, af.C_isf_from_af(0.1, 0.4), E, "seed7")
    reason = af.gate_reason(fit, 60, 1.0, 0.0, p)
    assert reason.startswith("normalised residual") and "model does not fit" in reason


@pytest.mark.parametrize("model", ["seed7", "full12"])
def test_psi_covariance_matches_monte_carlo(model):
    """sigma_psi from the Jacobian agrees with the scatter of psi over noise draws (+-20 %)."""
    C_nf_isf = dcm_from_euler(0.1, 0.6, 1.3)
    C_isf_af = af.C_isf_from_af(0.1, 0.6)
    atts = diverse_attitudes(n=50, seed=7)
    A = np.diag([1.05, 0.95, 1.0]) if model == "seed7" else np.array([[1.05, 0.04, 0], [0.02, 0.95, 0.03], [0, -0.03, 1.0]])
    psis, sig = [], []
    for k in range(150):
        data = fit_data_from_attitudes(C_nf_isf, atts, A, np.array([0.05, -0.03, 0.02]), noise=0.004, seed=k)
        fit = af.fit_psi(data, C_isf_af, E, model)
        psis.append(wrap_pi(fit.psi_rad - 1.3))
        sig.append(math.sqrt(fit.cov_white[0, 0]))
    ratio = np.std(psis) / np.sqrt(np.mean(np.square(sig)))
    assert 0.8 < ratio < 1.2, ratio
    assert abs(np.mean(psis)) < 3 * np.std(psis) / math.sqrt(len(psis))


def test_consider_jacobian_matches_finite_differences():
    """dr/d(gyro bias error), dr/d(gyro scale/misalignment) and dr/d(levelling tilt) against
    regenerated, perturbed data (the definition of G as in the estimator: bias columns
    -int C dt, T columns int C[:, i] w_j dt)."""
    from estimators.rotations import dcm_from_quat, skew
    from estimators.strapdown import strapdown_init, strapdown_step
    C_nf_isf = launcher_attitude(0.9, 0.7, rot_z(0.4) @ rot_x(0.3))
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=[1, 0, 0], segments=MANOEUVRE[:3], rest_s=0.1, boost_s=0.5)
    i0 = int(np.searchsorted(fl.time_s, fl.launch_time_s))
    sel = np.arange(0, len(fl.time_s) - i0, 40)

    def propagate(db=np.zeros(3), T=np.zeros((3, 3))):
        st = strapdown_init(np.array([1.0, 0, 0, 0]))
        Cs, Gs, G = [], [], np.zeros((3, 12))
        for i in range(i0, len(fl.time_s)):
            C0, w0 = dcm_from_quat(st.q_ref_from_sensor), st.gyro_prev_rad_s
            st, d = strapdown_step(st, (np.eye(3) + T) @ fl.gyro_rad_s[i] - db, fl.time_s[i])
            C = dcm_from_quat(st.q_ref_from_sensor)
            if d.integrated:
                G = G.copy()
                G[:, :3] -= 0.5 * d.dt_s * (C0 + C)
                G[:, 3:] += 0.5 * d.dt_s * ((C0[:, :, None] * w0).reshape(3, 9) + (C[:, :, None] * st.gyro_prev_rad_s).reshape(3, 9))
            Cs.append(C.T)
            Gs.append(G)
        return np.array(Cs), np.array(Gs)

    psi = fl.psi_s_rad
    roll = math.atan2(C_nf_isf[2, 1], C_nf_isf[2, 2])
    pitch = -math.asin(C_nf_isf[2, 0])
    C_isf_af = af.C_isf_from_af(roll, pitch)
    A = np.diag([1.1, 0.9, 1.0])
    theta = np.concatenate([[psi], np.diag(A), [0.01, 0.02, -0.01]])
    C0, G0 = propagate()
    D = af.consider_jacobian("seed7", theta, C0[sel], C_isf_af, E, G0[sel])
    assert D.shape == (3 * len(sel), 14)
    h = fl.mag_gauss[i0 + sel] @ A.T + theta[4:]

    def resid(C_sf_isf, C_isf_af_):
        m = C_sf_isf @ C_isf_af_ @ (af.r3(psi) @ E)
        return (h - m @ A.T - theta[4:]).reshape(-1)

    r0 = resid(C0[sel], C_isf_af)
    assert np.abs(r0).max() < 1e-10
    eps = 1e-6
    for j in range(12):
        if j < 3:
            db = np.zeros(3)
            db[j] = eps
            Cp, _ = propagate(db=db)
        else:
            T = np.zeros(9)
            T[j - 3] = eps
            Cp, _ = propagate(T=T.reshape(3, 3))
        fd = (resid(Cp[sel], C_isf_af) - r0) / eps
        assert np.abs(fd - D[:, j]).max() < 1e-4 * np.abs(D[:, j]).max() + 1e-9, (j, np.abs(fd - D[:, j]).max())
    for j in range(2):
        beta = np.zeros(3)
        beta[j] = eps
        C_af_isf_hat = (np.eye(3) + skew(beta)) @ C_isf_af.T
        np.testing.assert_allclose((resid(C0[sel], C_af_isf_hat.T) - r0) / eps, D[:, 12 + j], atol=2e-6)
    assert np.abs(D[:, :3]).max() > 1e-2 and np.abs(D[:, 3:12]).max() > 1e-3  # non-trivial sensitivities


def _propagated_with_gyro_errors(db, T):
    """Attitudes and G (as the estimator accumulates it) from a gyro with bias change db and
    scale/misalignment T in flight; plus the flight with its truth."""
    from estimators.rotations import dcm_from_quat
    from estimators.strapdown import strapdown_init, strapdown_step
    C_nf_isf = launcher_attitude(0.9, 0.7, rot_z(0.4) @ rot_x(0.3))
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=[1, 0, 0], segments=MANOEUVRE * 2, rest_s=0.1, boost_s=0.5)
    i0 = int(np.searchsorted(fl.time_s, fl.launch_time_s))
    st = strapdown_init(np.array([1.0, 0, 0, 0]))
    Cs, Gs, G = [], [], np.zeros((3, 12))
    for i in range(i0, len(fl.time_s)):
        C0, w0 = dcm_from_quat(st.q_ref_from_sensor), st.gyro_prev_rad_s
        st, d = strapdown_step(st, (np.eye(3) + T) @ fl.gyro_rad_s[i] + db, fl.time_s[i])
        C = dcm_from_quat(st.q_ref_from_sensor)
        if d.integrated:
            G = G.copy()
            G[:, :3] -= 0.5 * d.dt_s * (C0 + C)
            G[:, 3:] += 0.5 * d.dt_s * ((C0[:, :, None] * w0).reshape(3, 9) + (C[:, :, None] * st.gyro_prev_rad_s).reshape(3, 9))
        Cs.append(C.T)
        Gs.append(G)
    sel = np.arange(0, len(Cs), 10)
    roll = math.atan2(C_nf_isf[2, 1], C_nf_isf[2, 2])
    pitch = -math.asin(C_nf_isf[2, 0])
    return fl, i0, np.array(Cs)[sel], np.array(Gs)[sel], sel, af.C_isf_from_af(roll, pitch)


DB = np.array([2e-5, -1e-5, 1.5e-5])
TG = np.array([[3e-4, -2e-4, 1e-4], [2e-4, -3e-4, 2e-4], [-1e-4, 2.5e-4, 3e-4]])
P_WIDE = np.diag([1e-2] * 3 + [1.0] * 9 + [1e-20] * 2)   # no prior shrinkage; tilt held at its true 0


def test_joint_estimation_recovers_gyro_errors_on_noiseless_data():
    """GIVEN attitudes propagated with a gyro bias change db and a scale/misalignment matrix T,
    undistorted field samples, WHEN the fit estimates c = [-db, vec(T), tilt] jointly with a
    wide prior, THEN c and psi_s come back to first order (|c| ~ 3e-4: to ~2e-6)."""
    fl, i0, C, G, sel, C_isf_af = _propagated_with_gyro_errors(DB, TG)
    h = np.einsum("njk,k->nj", fl.C_nf_sf[i0 + sel].transpose(0, 2, 1), E)
    var = np.full(len(sel), 1e-6)
    data = af.FitData(C, h, var, 1.0 / var, G)
    fit_c = af.fit_psi(data, C_isf_af, E, "none", P_prior=P_WIDE, estimate_errors=False)
    fit = af.fit_psi(data, C_isf_af, E, "none", P_prior=P_WIDE, estimate_errors=True)
    assert abs(wrap_pi(fit_c.psi_rad - fl.psi_s_rad)) > 1e-4             # the errors matter ...
    np.testing.assert_allclose(fit.c_hat[:12], np.concatenate([-DB, TG.reshape(-1)]), atol=2e-6)
    assert abs(wrap_pi(fit.psi_rad - fl.psi_s_rad)) < 2e-6               # ... and are removed
    assert fit.P_psi_c[0, 0] < fit_c.P_psi_c[0, 0]


def test_joint_estimation_with_soft_iron_improves_psi():
    """With the full soft-iron model part of the gyro errors trades against A (weakly
    observable): with the consumer-grade prior the estimate does not recover c, but psi_s is
    better than with the errors only considered, and its sigma is smaller."""
    fl, i0, C, G, sel, C_isf_af = _propagated_with_gyro_errors(10 * DB, 10 * TG)
    A, b = np.array([[1.05, 0.02, 0.0], [0.01, 0.95, 0.03], [0.0, -0.02, 1.1]]), np.array([0.05, -0.03, 0.02])
    h = np.einsum("ij,njk,k->ni", A, fl.C_nf_sf[i0 + sel].transpose(0, 2, 1), E) + b
    var = np.full(len(sel), 1e-6)
    data = af.FitData(C, h, var, 1.0 / var, G)
    P = np.diag([math.radians(0.01) ** 2] * 3 + [3e-3 ** 2] * 9 + [1e-20] * 2)
    fit_c = af.fit_psi(data, C_isf_af, E, "full12", P_prior=P)
    fit = af.fit_psi(data, C_isf_af, E, "full12", P_prior=P, estimate_errors=True)
    err_c = abs(wrap_pi(fit_c.psi_rad - fl.psi_s_rad))
    err = abs(wrap_pi(fit.psi_rad - fl.psi_s_rad))
    assert err < 0.9 * err_c, (math.degrees(err), math.degrees(err_c))
    assert fit.P_psi_c[0, 0] < fit_c.P_psi_c[0, 0]
    assert err < 3.0 * math.sqrt(fit.P_psi_c[0, 0])


def test_equator_sign_ambiguity_is_resolved_by_physics():
    """At the magnetic equator m(psi + pi) = -m(psi), so A -> -A fits equally well; only the
    physical branch (det A > 0) is accepted, for both distortion models."""
    e_eq = np.array([0.30, 0.02, 0.0])
    C_nf_isf = dcm_from_euler(0.1, 0.5, 2.5)
    C_isf_af = af.C_isf_from_af(0.1, 0.5)
    atts = diverse_attitudes(seed=11)
    C_sf_isf = np.array([C.T for C in atts])
    for model, A in (("seed7", np.diag([1.05, 0.95, 1.02])),
                     ("full12", np.array([[1.02, 0.03, 0.0], [0.01, 0.97, 0.02], [0.0, -0.02, 1.03]]))):
        h = np.einsum("ij,njk,kl,l->ni", A, C_sf_isf, C_nf_isf.T, e_eq) + np.array([0.02, -0.01, 0.03])
        var = np.full(len(h), 1e-6)
        fit = af.fit_psi(af.FitData(C_sf_isf, h, var, 1.0 / var), C_isf_af, e_eq, model)
        assert abs(wrap_pi(fit.psi_rad - 2.5)) < 1e-9
        assert np.linalg.det(fit.A) > 0
