"""Magnetometer deviation compensation (METHODS.md D, US 4,870,602 eq. 1-3)."""
import math

import numpy as np
import pytest

from estimators.mag_deviation import (DeviationParams, DeviationState, coefficient_covariance,
                                      coefficients_dict, corrected_heading, deviation_coverage,
                                      deviation_init, deviation_model, deviation_step,
                                      fit_hard_soft_iron, reference_field_body, regressor)
from estimators.rotations import wrap_pi

FIELD = np.array([0.18, 0.02, 0.42])       # gauss NED
DECL = math.atan2(FIELD[1], FIELD[0])


def manoeuvre(n=3000, seed=0, heading_span=2 * math.pi):
    """Headings swept several times with rolls to +-30 deg and pitches to +-20 deg."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)
    psi = (heading_span * 3 * s) % heading_span
    phi = math.radians(28) * np.sin(2 * np.pi * 7.3 * s) + rng.normal(0, 0.01, n)
    th = math.radians(18) * np.sin(2 * np.pi * 4.1 * s + 0.5) + rng.normal(0, 0.01, n)
    return psi, np.clip(phi, -0.52, 0.52), np.clip(th, -0.34, 0.34)


def inject(coeffs, psi, phi, th, noise, seed=1):
    rng = np.random.default_rng(seed)
    out = []
    for a, b, c in zip(psi, phi, th):
        out.append(reference_field_body(FIELD, a, b, c) + regressor(a, b, c) @ coeffs)
    return np.array(out) + rng.normal(0.0, noise, (len(psi), 3))


def true_coeffs(seed=2):
    rng = np.random.default_rng(seed)
    c = rng.normal(0.0, 0.01, (7, 3))
    c[0] = [0.05, -0.03, 0.02]             # hard-iron-like A_i
    return c


def fit(mag, psi, phi, th, params=DeviationParams()):
    st = deviation_init(params)
    for k in range(len(psi)):
        st, d = deviation_step(st, mag[k], FIELD, psi[k], phi[k], th[k], params)
        assert d.updated
    return st


def test_recovers_injected_coefficients_noiseless():
    c = true_coeffs()
    psi, phi, th = manoeuvre(1500)
    st = fit(inject(c, psi, phi, th, 0.0), psi, phi, th, DeviationParams(init_coeff_sigma_gauss=100.0))
    np.testing.assert_allclose(st.coeffs, c, atol=2e-6)


def test_recovers_injected_coefficients_with_noise_within_their_covariance():
    c = true_coeffs()
    psi, phi, th = manoeuvre(3000)
    st = fit(inject(c, psi, phi, th, 0.001), psi, phi, th)
    err = (st.coeffs - c).T.reshape(-1)          # axis-major, as coefficient_covariance
    sig = np.sqrt(np.diag(coefficient_covariance(st)))
    assert np.all(np.abs(err) < 4.0 * sig)
    assert np.all(sig < 0.003)
    assert np.abs(st.coeffs[0] - c[0]).max() < 3e-4        # the constant terms (hard iron)
    from estimators.mag_deviation import residual_sigma_gauss
    np.testing.assert_allclose(residual_sigma_gauss(st), 0.001, rtol=0.06)
    d = coefficients_dict(st)
    assert d["y"]["A"] == st.coeffs[0, 1]


def test_corrected_heading_at_least_5x_better():
    c = true_coeffs()
    psi, phi, th = manoeuvre(3000)
    mag = inject(c, psi, phi, th, 0.0005)
    st = fit(mag, psi, phi, th)
    from estimators.polar_heading import magnetic_heading
    raw, cor = [], []
    for k in range(0, 3000, 7):
        raw.append(wrap_pi(magnetic_heading(mag[k], phi[k], th[k])[0] + DECL - psi[k]))
        cor.append(wrap_pi(corrected_heading(st, mag[k], phi[k], th[k], DECL)[0] - psi[k]))
    rms_raw = np.sqrt(np.mean(np.square(raw)))
    rms_cor = np.sqrt(np.mean(np.square(cor)))
    assert rms_cor * 5.0 < rms_raw
    assert math.degrees(rms_cor) < 0.5


def test_coverage_reports_the_headings_and_attitudes_seen():
    psi, phi, th = manoeuvre(2000, heading_span=math.pi)       # only headings 0..180 deg
    st = fit(inject(true_coeffs(), psi, phi, th, 0.0), psi, phi, th)
    cov = deviation_coverage(st)
    assert cov.heading_fraction == 0.5
    assert cov.roll_fraction == 1.0 and cov.pitch_fraction == 1.0
    assert cov.overall == 0.5
    psi, phi, th = manoeuvre(2000)
    st = fit(inject(true_coeffs(), psi, phi, th, 0.0), psi, phi, th)
    assert deviation_coverage(st).overall == 1.0


def test_persistence_round_trip_equals_unbroken_run():
    c = true_coeffs()
    psi, phi, th = manoeuvre(600)
    mag = inject(c, psi, phi, th, 0.001)
    a = fit(mag, psi, phi, th)
    b = deviation_init()
    for k in range(300):
        b, _ = deviation_step(b, mag[k], FIELD, psi[k], phi[k], th[k])
    b = DeviationState.from_dict(b.to_dict())
    for k in range(300, 600):
        b, _ = deviation_step(b, mag[k], FIELD, psi[k], phi[k], th[k])
    np.testing.assert_array_equal(a.coeffs, b.coeffs)
    np.testing.assert_array_equal(a.P, b.P)
    np.testing.assert_array_equal(a.heading_counts, b.heading_counts)
    np.testing.assert_allclose(deviation_model(a, 1.0, 0.1, 0.05), deviation_model(b, 1.0, 0.1, 0.05))


def test_outside_limits_and_bad_input():
    st = deviation_init()
    st2, d = deviation_step(st, np.ones(3) * 0.1, FIELD, 0.0, math.radians(40), 0.0)
    assert not d.updated and st2 is st
    st2, d = deviation_step(st, np.array([np.nan, 0, 0]), FIELD, 0.0, 0.0, 0.0)
    assert not d.updated
    with pytest.raises(ValueError, match="forgetting_factor"):
        DeviationParams(forgetting_factor=1.2)


def test_hard_soft_iron_fit_recovers_a_linear_distortion():
    rng = np.random.default_rng(5)
    S = np.eye(3) + rng.normal(0, 0.05, (3, 3))
    b = np.array([0.03, -0.02, 0.01])
    psi, phi, th = manoeuvre(500)
    ref = np.array([reference_field_body(FIELD, *a) for a in zip(psi, phi, th)])
    S_hat, b_hat = fit_hard_soft_iron(ref @ S.T + b, ref)
    np.testing.assert_allclose(S_hat, S, atol=1e-9)
    np.testing.assert_allclose(b_hat, b, atol=1e-9)


def test_extended_model_recovers_cross_terms_the_seed_model_cannot():
    rng = np.random.default_rng(9)
    c = np.vstack([true_coeffs(), rng.normal(0.0, 0.01, (4, 3))])
    psi, phi, th = manoeuvre(2000)
    mag = np.array([reference_field_body(FIELD, a, b, d) + regressor(a, b, d, extended=True) @ c
                    for a, b, d in zip(psi, phi, th)])
    p_ext = DeviationParams(extended=True, init_coeff_sigma_gauss=100.0)
    st = fit(mag, psi, phi, th, p_ext)
    np.testing.assert_allclose(st.coeffs, c, atol=2e-6)
    assert coefficient_covariance(st).shape == (33, 33)
    assert set(coefficients_dict(st)["x"]) == set("ABCDEFGHIJK")
    seed_model = fit(mag, psi, phi, th)
    from estimators.mag_deviation import residual_sigma_gauss
    assert residual_sigma_gauss(seed_model).min() > 1e-3           # cannot follow the cross terms
    assert DeviationState.from_dict(st.to_dict()).coeffs.shape == (11, 3)
