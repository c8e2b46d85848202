"""Declination from a 9-axis IMU at rest (METHODS.md E, CN105486275)."""
import math

import numpy as np
import pytest

from estimators.declination import (DeclinationParams, RestState, estimate_declination,
                                    rest_accumulate, rest_from_arrays, triad_alignment)
from estimators.rotations import dcm_from_euler, euler_from_dcm, wrap_pi

W = 7.292115e-5
G = 9.80665


def at_rest(lat_deg, roll, pitch, yaw, decl_rad, n=3000, gyro_bias=np.zeros(3), gyro_noise=0.0,
            accel_noise=0.0, mag_noise=0.0, seed=0):
    L = math.radians(lat_deg)
    C = dcm_from_euler(roll, pitch, yaw)
    field = np.array([0.2 * math.cos(decl_rad), 0.2 * math.sin(decl_rad), 0.4])
    rng = np.random.default_rng(seed)
    gyro = C.T @ (W * np.array([math.cos(L), 0.0, -math.sin(L)])) + gyro_bias + rng.normal(0, gyro_noise or 1e-30, (n, 3))
    accel = C.T @ np.array([0.0, 0.0, -G]) + rng.normal(0, accel_noise or 1e-30, (n, 3))
    mag = C.T @ field + rng.normal(0, mag_noise or 1e-30, (n, 3))
    return gyro, accel, mag


NAV = DeclinationParams(gyro_bias_sigma_rad_s=math.radians(0.005 / 3600))


def test_triad_alignment_noiseless_recovers_the_attitude():
    for lat, att in ((45.0, (0.05, -0.03, 2.2)), (-30.0, (-0.2, 0.1, 5.5)), (70.0, (0.0, 0.0, 0.3))):
        C = dcm_from_euler(*att)
        L = math.radians(lat)
        w = C.T @ (W * np.array([math.cos(L), 0.0, -math.sin(L)]))
        f = C.T @ np.array([0.0, 0.0, -G])
        np.testing.assert_allclose(triad_alignment(f, w, L), C, atol=1e-12)


def test_declination_noiseless_equals_injected_and_no_anomaly():
    decl = math.radians(7.5)
    g, a, m = at_rest(45.0, 0.04, -0.02, math.radians(123.0), decl)
    res = estimate_declination(rest_from_arrays(g, a, m), math.radians(45.0), decl, math.radians(0.4), NAV)
    assert res.source == "measured" and res.earth_rate_resolved
    assert abs(res.declination_rad - decl) < 1e-9
    assert abs(wrap_pi(res.true_heading_rad - math.radians(123.0))) < 1e-9
    assert not res.anomaly


def test_anomaly_flagged_when_measured_differs_from_wmm():
    g, a, m = at_rest(45.0, 0.0, 0.0, 1.0, math.radians(12.0))
    res = estimate_declination(rest_from_arrays(g, a, m), math.radians(45.0), math.radians(7.0),
                               math.radians(0.4), NAV)
    assert res.source == "measured" and res.anomaly and res.anomaly_test_ratio > 1.0
    assert "ANOMALY" in res.message


def test_consumer_gyros_fall_back_to_wmm_and_say_why():
    g, a, m = at_rest(45.0, 0.0, 0.0, 1.0, 0.1, gyro_bias=np.radians([0.2, -0.1, 0.3]),
                      gyro_noise=math.radians(0.05))
    res = estimate_declination(rest_from_arrays(g, a, m), math.radians(45.0), 0.12, 0.007,
                               DeclinationParams(gyro_bias_sigma_rad_s=math.radians(0.5)))
    assert res.source == "wmm" and not res.earth_rate_resolved
    assert res.declination_rad == 0.12 and res.sigma_rad == 0.007
    assert "cannot resolve Earth rate" in res.message


def test_near_the_pole_even_good_gyros_fall_back():
    g, a, m = at_rest(89.9, 0.0, 0.0, 1.0, 0.1)
    res = estimate_declination(rest_from_arrays(g, a, m), math.radians(89.9), 0.1, 0.01, NAV)
    assert res.source == "wmm" and "cannot resolve" in res.message


def test_inconsistent_rate_magnitude_falls_back():
    """A bias well above the configured sigma (or motion) makes |w| != W: refuse."""
    g, a, m = at_rest(45.0, 0.0, 0.0, 1.0, 0.1, gyro_bias=np.radians([0.0, 0.0, 0.01]))
    res = estimate_declination(rest_from_arrays(g, a, m), math.radians(45.0), 0.1, 0.01, NAV)
    assert res.source == "wmm" and "inconsistent" in res.message


def test_noisy_tactical_case_within_sigma():
    decl = math.radians(-3.0)
    g, a, m = at_rest(50.0, 0.02, 0.01, 4.0, decl, n=30000, gyro_noise=math.radians(0.003),
                      accel_noise=0.01, mag_noise=0.001, gyro_bias=np.radians([0.3, -0.2, 0.1]) / 3600)
    p = DeclinationParams(gyro_bias_sigma_rad_s=math.radians(0.3 / 3600), max_heading_sigma_rad=math.radians(3))
    res = estimate_declination(rest_from_arrays(g, a, m), math.radians(50.0), decl, 0.006, p)
    assert res.source == "measured"
    assert abs(wrap_pi(res.declination_rad - decl)) < 3.0 * res.sigma_rad
    assert res.sigma_rad < math.radians(3.0)


def test_incremental_equals_batch():
    g, a, m = at_rest(45.0, 0.1, 0.0, 1.0, 0.1, n=200, gyro_noise=1e-4, accel_noise=0.01, mag_noise=1e-3)
    st = RestState()
    for k in range(len(g)):
        st = rest_accumulate(st, g[k], a[k], m[k])
    b = rest_from_arrays(g, a, m)
    np.testing.assert_allclose(st.gyro_mean_rad_s, b.gyro_mean_rad_s, rtol=1e-12)
    np.testing.assert_allclose(st.mag_m2, b.mag_m2, rtol=1e-9)
    assert RestState.from_dict(st.to_dict()).n == 200


def test_too_few_samples_and_validation():
    res = estimate_declination(RestState(), 0.5, 0.1, 0.01)
    assert res.source == "wmm" and "samples" in res.message
    with pytest.raises(ValueError, match="lat_rad"):
        estimate_declination(RestState(), 2.0, 0.1, 0.01)
