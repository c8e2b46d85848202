"""KF1, the 12-state magnetometer error filter (METHODS.md B2, seed eq. 13-16)."""
import json
import math

import numpy as np
import pytest

from estimators.euler_kinematics import body_rates
from estimators.mag_error_kf import (Kf1Params, error_jacobian, error_matrix, kf1_correct_mag,
                                     kf1_from_dict, kf1_init, kf1_sigma, kf1_step, kf1_to_dict)
from estimators.rotations import dcm_from_euler

FIELD_NED_G = np.array([0.19, 0.015, 0.44])           # mid-latitude field, gauss
NORM = float(np.linalg.norm(FIELD_NED_G))
BIAS_G = np.array([0.040, -0.025, 0.018])             # hard iron, gauss
SCALE = np.array([0.03, -0.02, 0.045])
CROSS = np.array([0.015, -0.02, 0.01, 0.025, -0.012, 0.018])  # k_xy k_xz k_yx k_yz k_zx k_zy
X_TRUE = np.r_[BIAS_G / NORM, SCALE, CROSS]


def flight(n, rng, dt=0.1, noise_g=0.002):
    """A trusted-reference flight with wide attitude diversity: (t, m_body, C, omega) tuples."""
    M = error_matrix(X_TRUE)
    for k in range(n):
        t = k * dt
        e = np.array([0.6 * math.sin(0.05 * t), 0.45 * math.sin(0.031 * t + 0.4), 0.21 * t])
        de = np.array([0.03 * math.cos(0.05 * t), 0.45 * 0.031 * math.cos(0.031 * t + 0.4), 0.21])
        C = dcm_from_euler(*e)
        B = C.T @ FIELD_NED_G
        m = M @ B + BIAS_G + rng.normal(0.0, noise_g, 3)
        yield t, m, C, body_rates(e[0], e[1], de)


def test_jacobian_matches_error_model():
    rng = np.random.default_rng(0)
    B = rng.normal(size=3)
    x = rng.normal(scale=0.05, size=12)
    dB = error_matrix(x) @ B + x[:3] - B           # b + diag(s) B + K B
    assert np.allclose(error_jacobian(B) @ x, dB, atol=1e-15)


def test_kf1_recovers_bias_scale_and_cross_coupling():
    rng = np.random.default_rng(42)
    # every sample of the 10 Hz data; R near the data's noise (0.004 normalised), not the seed's 0.1
    params = Kf1Params(min_update_interval_s=0.1, sigma_meas=0.01)
    st = kf1_init(params)
    for t, m, C, w in flight(6000, rng):           # 10 minutes at 10 Hz
        st, _ = kf1_step(st, m, C, FIELD_NED_G, w, t, params)
    err = st.x - X_TRUE
    sig = kf1_sigma(st)
    assert st.n_updates > 5900
    assert np.all(np.abs(err) < 3.5 * sig), (err, sig)
    assert np.all(np.abs(err[:3] * NORM) < 5e-4)     # bias within 0.5 mG (injected 18-40 mG)
    assert np.all(np.abs(err[3:]) < 1.5e-3)          # scale and cross within 0.15 % (injected 1-4.5 %)
    assert np.all(sig < 0.2 * np.array([0.3] * 3 + [0.1] * 9))
    corrected = kf1_correct_mag(st, error_matrix(X_TRUE) @ np.array([0.3, -0.1, 0.35]) + BIAS_G)
    assert np.allclose(corrected, [0.3, -0.1, 0.35], atol=1e-3)


def test_split_run_through_dict_equals_unbroken_run():
    params = Kf1Params()
    data = list(flight(1200, np.random.default_rng(7)))
    st = kf1_init(params)
    for t, m, C, w in data:
        st, _ = kf1_step(st, m, C, FIELD_NED_G, w, t, params)
    st2 = kf1_init(params)
    for t, m, C, w in data[:517]:
        st2, _ = kf1_step(st2, m, C, FIELD_NED_G, w, t, params)
    st2 = kf1_from_dict(json.loads(json.dumps(kf1_to_dict(st2))))
    for t, m, C, w in data[517:]:
        st2, _ = kf1_step(st2, m, C, FIELD_NED_G, w, t, params)
    assert np.array_equal(st.x, st2.x) and np.array_equal(st.P, st2.P)
    assert st.n_updates == st2.n_updates and st.time_s == st2.time_s


def test_gates_reject_outlier_and_high_rate():
    rng = np.random.default_rng(5)
    params = Kf1Params(min_update_interval_s=0.1)
    st = kf1_init(params)
    data = list(flight(600, rng))
    for t, m, C, w in data[:-2]:
        st, _ = kf1_step(st, m, C, FIELD_NED_G, w, t, params)
    t, m, C, w = data[-2]
    st_out, diag = kf1_step(st, m + np.array([0.2, 0.0, 0.0]), C, FIELD_NED_G, w, t, params)
    assert not diag.fused and diag.reason == "chi2 gate" and diag.test_ratio > 1.0
    assert st_out.n_rejected_chi2 == st.n_rejected_chi2 + 1
    assert np.array_equal(st_out.P, st_out.P.T)
    t, m, C, _ = data[-1]
    st_rate, diag = kf1_step(st_out, m, C, FIELD_NED_G, np.array([0.0, 0.0, 0.5]), t, params)
    assert not diag.fused and diag.reason == "rate gate" and st_rate.n_rejected_rate == 1
    assert np.array_equal(st_rate.x, st_out.x)


def test_from_dict_rejects_damaged_input():
    d = kf1_to_dict(kf1_init())
    with pytest.raises(ValueError, match="version"):
        kf1_from_dict({**d, "version": 99})
    with pytest.raises(ValueError, match="shape|expected"):
        kf1_from_dict({**d, "x": d["x"][:11]})
    bad = json.loads(json.dumps(d))
    bad["P"][0][0] = -1.0
    with pytest.raises(ValueError, match="covariance"):
        kf1_from_dict(bad)
    with pytest.raises(ValueError, match="missing"):
        kf1_from_dict({k: v for k, v in d.items() if k != "P"})


def test_updates_are_decimated_to_the_configured_interval():
    params = Kf1Params(min_update_interval_s=1.0)
    st = kf1_init(params)
    reasons = []
    for t, m, C, w in flight(100, np.random.default_rng(2)):   # 10 s at 10 Hz
        st, d = kf1_step(st, m, C, FIELD_NED_G, w, t, params)
        reasons.append(d.reason)
    assert st.n_updates == 10 and reasons.count("decimated") == 90
