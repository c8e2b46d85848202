"""Method C's published heading variance covers the magnetometer errors nobody has calibrated
(estimators/polar_heading.py, module docstring: the consider term r_uncal)."""
import math

import numpy as np
import pytest

from estimators.polar_heading import (HeadingInputs, PolarHeadingParams, magnetic_heading, polar_heading_estimate,
                                      polar_heading_init, polar_heading_step, uncalibrated_heading_var)
from estimators.rotations import dcm_from_euler, wrap_pi

FIELD_NED_GAUSS = np.array([0.21, 0.01, 0.43])      # mid-latitude: H 0.21 G, dip 64 deg


def _turning_flight(hard_iron_gauss, residual_sigma_gauss, roll_rad=0.0, duration_s=60.0, rate_hz=50.0,
                    yaw_rate_rad_s=math.radians(6.0), seed=4):
    """A constant-rate turn (one full circle in 60 s) at a constant roll, exact gyros and attitude,
    a magnetometer with noise and the given hard iron; returns (error rad, published sigma rad)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    yaw = 0.3 + yaw_rate_rad_s * t
    # body rates of a turn at constant roll (ZYX: w = [0, sin(phi), cos(phi)] * yaw_rate)
    gyro = np.array([0.0, math.sin(roll_rad), math.cos(roll_rad)]) * yaw_rate_rad_s
    st = polar_heading_init()
    err, sig = [], []
    for k in range(len(t)):
        C_nb = dcm_from_euler(roll_rad, 0.0, yaw[k])
        mag = C_nb.T @ FIELD_NED_GAUSS + hard_iron_gauss + rng.normal(0.0, 0.002, 3)
        st, _ = polar_heading_step(st, HeadingInputs(t[k], gyro, roll_rad, 0.0, np.eye(2) * 1e-6, mag, 0.0, 0.0,
                                                     residual_sigma_gauss))
        e = polar_heading_estimate(st)
        err.append(wrap_pi(e.heading_rad - yaw[k]))
        sig.append(math.sqrt(e.variance_rad2))
    return np.array(err), np.array(sig)


def test_uncalibrated_hard_iron_is_inside_the_published_sigma():
    """GIVEN an uncompensated magnetometer with 0.013 G of horizontal hard iron (a one-cycle
    deviation of up to 3.5 deg) in a full-circle turn, WHEN nobody says it is compensated, THEN the
    published sigma covers the error (it did not: a 1.6 deg sigma, 64 % within 3 sigma, NEES 6.7)."""
    err, sig = _turning_flight(np.array([0.009, -0.009, 0.01]), None)
    r = np.abs(err) / sig
    assert np.degrees(np.abs(err)).max() > 2.5              # the deviation is there ...
    assert np.mean(r <= 3.0) == 1.0                          # ... and covered
    assert 0.2 <= np.mean(r * r) <= 2.0                      # without being useless:
    # the published sigma is the consider term of the prior plus a converged filter P (was "< 5 deg",
    # which the 1-deg soft-iron prior of session 5 makes 5.2 deg: 4.9 deg of it is the prior)
    m = FIELD_NED_GAUSS
    prior = math.sqrt(uncalibrated_heading_var(m, math.hypot(m[0], m[1]), None, PolarHeadingParams()))
    assert np.median(sig) <= 1.1 * prior


def test_compensated_magnetometer_keeps_the_filter_sigma():
    """GIVEN the same flight with a clean magnetometer declared compensated to its noise level,
    THEN the consider term is 0 and the published variance is the filter's own P."""
    err, sig = _turning_flight(np.zeros(3), 0.002)
    assert np.degrees(sig[-1]) < 1.5
    assert np.mean(np.abs(err) <= 3.0 * sig) == 1.0
    # exact: residual below the white noise already in R -> no term
    m = np.array([0.2, 0.05, 0.4])
    assert uncalibrated_heading_var(m, 0.2, 0.002) == 0.0


def test_uncalibrated_var_formula_matches_monte_carlo():
    """r_uncal = (s_h^2 + s_s^2 |m|^2) / H^2 (linearised) against the heading errors of random
    hard- and soft-iron draws, at a tilted attitude (4000 draws, seeded: sampling error ~2 %)."""
    p = PolarHeadingParams(uncalibrated_hard_iron_gauss=0.01, uncalibrated_soft_iron=0.01)
    roll, pitch, yaw = 0.35, -0.2, 2.1
    m_true = dcm_from_euler(roll, pitch, yaw).T @ FIELD_NED_GAUSS
    psi0, H = magnetic_heading(m_true, roll, pitch)
    rng = np.random.default_rng(11)
    n = 4000
    b = rng.normal(0.0, p.uncalibrated_hard_iron_gauss, (n, 3))
    S = rng.normal(0.0, p.uncalibrated_soft_iron, (n, 3, 3))
    d = np.array([wrap_pi(magnetic_heading(m_true + S[i] @ m_true + b[i], roll, pitch)[0] - psi0)
                  for i in range(n)])
    var_mc = float(np.mean(d * d))
    var_model = uncalibrated_heading_var(m_true, H, None, p)
    assert abs(var_mc / var_model - 1.0) < 0.06
    # a compensated magnetometer: the residual above the white noise, same 1/H^2 sensitivity
    assert math.isclose(uncalibrated_heading_var(m_true, H, 0.005, p),
                        (0.005 ** 2 - p.mag_noise_gauss ** 2) / H ** 2, rel_tol=1e-12)


def test_consider_term_grows_towards_the_magnetic_pole_and_validates():
    m_mid = np.array([0.21, 0.0, 0.43])
    m_pol = np.array([0.05, 0.0, 0.57])
    p = PolarHeadingParams()
    v_mid = uncalibrated_heading_var(m_mid, 0.21, None, p)
    v_pol = uncalibrated_heading_var(m_pol, 0.05, None, p)
    assert math.isclose(math.degrees(math.sqrt(v_mid)), math.degrees(math.sqrt(
        (0.016 ** 2 + 0.0175 ** 2 * (0.21 ** 2 + 0.43 ** 2)) / 0.21 ** 2)), rel_tol=1e-12)
    assert v_pol > 15.0 * v_mid
    with pytest.raises(ValueError, match="mag_residual_sigma_gauss"):
        uncalibrated_heading_var(m_mid, 0.21, -0.001, p)
    with pytest.raises(ValueError, match="uncalibrated_hard_iron_gauss"):
        PolarHeadingParams(uncalibrated_hard_iron_gauss=-0.01)
    # 0 switches the term off (a magnetometer calibrated by other means)
    assert uncalibrated_heading_var(m_mid, 0.21, None, PolarHeadingParams(uncalibrated_hard_iron_gauss=0.0,
                                                                           uncalibrated_soft_iron=0.0)) == 0.0


def test_soft_iron_term_is_the_heading_error_of_a_misaligned_magnetometer():
    """GIVEN a magnetometer whose axes are turned against the IMU's by a small rotation r with iid
    per-axis sigma s (what an ellipsoid calibration cannot see), WHEN the heading is levelled with
    the IMU's attitude, THEN its variance is the soft-iron term s^2 |m|^2 / H^2 of r_uncal (the
    equivalence the ``uncalibrated_soft_iron`` default rests on; 4000 seeded draws, ~2 % sampling
    error)."""
    from estimators.rotations import dcm_from_quat, quat_from_rotvec
    s = math.radians(1.0)
    p = PolarHeadingParams(uncalibrated_hard_iron_gauss=0.0, uncalibrated_soft_iron=s)
    roll, pitch, yaw = -0.3, 0.25, 4.0
    m_true = dcm_from_euler(roll, pitch, yaw).T @ FIELD_NED_GAUSS
    psi0, H = magnetic_heading(m_true, roll, pitch)
    rng = np.random.default_rng(12)
    d = np.array([wrap_pi(magnetic_heading(dcm_from_quat(quat_from_rotvec(r)) @ m_true, roll, pitch)[0] - psi0)
                  for r in rng.normal(0.0, s, (4000, 3))])
    assert abs(float(np.mean(d * d)) / uncalibrated_heading_var(m_true, H, None, p) - 1.0) < 0.06


def test_pipeline_takes_the_soft_iron_and_the_floor_from_the_config():
    """[heading] uncalibrated_soft_iron and mag_heading_floor_deg reach method C's params (soft iron
    0: a magnetometer compensated and aligned, as bench/polar_accuracy.py's flights have it); the
    defaults are the documented 1 deg of misalignment and PolarHeadingParams' 1 deg floor."""
    from service.config import SPEC, validate
    from service.pipeline import Pipeline
    site = {"lat_deg": 47.4, "lon_deg": 8.5, "decimal_year": 2026.9}
    params = Pipeline(validate({"site": site, "heading": {"uncalibrated_soft_iron": 0.0,
                                                          "mag_heading_floor_deg": 0.5}})).polar_hdg_params
    assert params.uncalibrated_soft_iron == 0.0
    assert params.mag_heading_floor_rad == pytest.approx(math.radians(0.5), rel=1e-12)
    assert PolarHeadingParams().mag_heading_floor_rad == pytest.approx(
        math.radians(SPEC["heading"]["mag_heading_floor_deg"].default), rel=1e-12)
    assert validate({"site": site})["heading"]["uncalibrated_soft_iron"] == 0.0175
    assert PolarHeadingParams().uncalibrated_soft_iron == SPEC["heading"]["uncalibrated_soft_iron"].default
