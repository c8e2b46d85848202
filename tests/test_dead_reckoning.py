"""estimators/dead_reckoning.py: mean on the ellipsoid, Jacobians, honest covariance growth."""
import math

import numpy as np
import pytest

from estimators.dead_reckoning import (DrInputs, DrParams, dr_init, dr_predict_covariance, dr_step,
                                       error_jacobians, horizontal_airspeed_m_s, transition,
                                       wind_estimate_sigma_m_s, wind_estimate_step, WindEstState)
from estimators.geodesy import meridian_arc_m, vincenty_inverse, WGS84_A_M

D = math.radians


def fly(state, heading_rad, tas, wind=(0.0, 0.0), dt=0.1, n=100, heading_sigma=D(1.0), tas_sigma=1.0,
        wind_sigma=1.0, params=DrParams(), alt=None):
    for _ in range(n):
        inp = DrInputs(state.time_s + dt, heading_rad, heading_sigma, tas, tas_sigma, wind, wind_sigma, alt_m=alt)
        state, diag = dr_step(state, inp, params)
    return state, diag


def test_north_along_a_meridian_matches_the_meridian_arc():
    # GIVEN 20 m/s true north from the equator for 500 s at h = 0, no wind
    s0 = dr_init(0.0, 0.0, D(10.0), 0.0, 1.0, D(1.0), 1.0, 1.0)
    s, _ = fly(s0, 0.0, 20.0, n=5000)
    # THEN the latitude reached is the one whose meridian arc is 10 km
    assert meridian_arc_m(s.lat_rad) == pytest.approx(10000.0, abs=1e-3)
    assert s.lon_rad == pytest.approx(D(10.0), abs=1e-15)
    assert s.distance_m == pytest.approx(10000.0, abs=1e-6)


def test_east_along_the_equator_and_with_wind():
    s0 = dr_init(0.0, 0.0, 0.0, 0.0, 1.0, D(1.0), 1.0, 1.0)
    # 15 m/s air east + 5 m/s wind east = 20 m/s for 100 s: 2000 m of equator = a dlon
    s, _ = fly(s0, D(90.0), 15.0, wind=(0.0, 5.0), n=1000)
    assert s.lon_rad * WGS84_A_M == pytest.approx(2000.0, abs=1e-6)
    assert s.lat_rad == pytest.approx(0.0, abs=1e-15)
    assert s.v_ground_ne_m_s == pytest.approx((0.0, 20.0), abs=1e-12)


def test_diagonal_track_matches_vincenty_at_mid_latitude():
    s0 = dr_init(0.0, D(52.0), D(4.0), 120.0, 1.0, D(1.0), 1.0, 1.0)
    s, _ = fly(s0, D(37.0), 25.0, n=4000, dt=0.1, alt=120.0)  # 10 km on a rhumb line
    dist, az, _ = vincenty_inverse(D(52.0), D(4.0), s.lat_rad, s.lon_rad)
    # a 10 km rhumb line differs from the geodesic by < 1 cm; the height 120 m scales by (R+h)/R
    assert dist == pytest.approx(10000.0 * 6.371e6 / (6.371e6 + 120.0), abs=0.05)
    assert math.degrees(az) == pytest.approx(37.0, abs=0.05)


def test_climb_uses_the_horizontal_airspeed():
    assert horizontal_airspeed_m_s(20.0, 12.0) == pytest.approx(16.0)
    assert horizontal_airspeed_m_s(0.0, 3.0) == 0.0


def test_jacobians_match_finite_differences():
    psi, V = D(123.0), 21.0

    def v(psi_, V_):
        return np.array([V_ * math.cos(psi_), V_ * math.sin(psi_)])
    J_psi, J_V = error_jacobians(psi, V)
    h = 1e-7
    assert J_psi == pytest.approx((v(psi + h, V) - v(psi - h, V)) / (2 * h), abs=1e-6)
    assert J_V == pytest.approx((v(psi, V + h) - v(psi, V - h)) / (2 * h), abs=1e-6)


def test_heading_bias_grows_the_cross_track_sigma_linearly():
    # GIVEN a heading error that is a bias over the flight (tau >> t), nothing else
    params = DrParams(tau_heading_s=1e7, tau_airspeed_s=1e7, tau_wind_s=1e7, sideslip_sigma_rad=0.0)
    sig = D(2.0)
    s0 = dr_init(0.0, D(45.0), 0.0, 0.0, 0.0, sig, 0.0, 0.0)
    s, diag = fly(s0, 0.0, 20.0, n=1000, heading_sigma=sig, tas_sigma=0.0, wind_sigma=0.0, params=params)
    # THEN the east (cross-track) sigma is V sigma_psi t (linear in t, not sqrt), north ~ 0
    assert math.sqrt(s.P[1, 1]) == pytest.approx(20.0 * sig * 100.0, rel=1e-3)
    assert math.sqrt(s.P[0, 0]) < 1e-3 * math.sqrt(s.P[1, 1])
    assert diag.sigma_pos_major_m == pytest.approx(20.0 * sig * 100.0, rel=1e-3)


def test_wind_bias_grows_sigma_linearly():
    params = DrParams(tau_wind_s=1e7, sideslip_sigma_rad=0.0)
    s0 = dr_init(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.5)
    s, _ = fly(s0, 0.0, 20.0, n=600, heading_sigma=0.0, tas_sigma=0.0, wind_sigma=1.5, params=params)
    assert math.sqrt(s.P[0, 0]) == pytest.approx(1.5 * 60.0, rel=1e-3)
    assert math.sqrt(s.P[1, 1]) == pytest.approx(1.5 * 60.0, rel=1e-3)


def test_covariance_is_consistent_with_monte_carlo():
    # GIVEN Gauss-Markov heading, airspeed and wind errors with the model's own statistics
    params = DrParams(tau_heading_s=60.0, tau_airspeed_s=30.0, tau_wind_s=300.0, sideslip_sigma_rad=0.0)
    s_psi, s_V, s_w = D(3.0), 1.5, 2.0
    dt, n, runs = 0.5, 240, 400
    rng = np.random.default_rng(5)
    psi0, V = D(60.0), 22.0
    errs = np.zeros((runs, 2))
    for r in range(runs):
        e_psi, e_V = s_psi * rng.standard_normal(), s_V * rng.standard_normal()
        e_w = s_w * rng.standard_normal(2)
        p_true = np.zeros(2)
        for _ in range(n):
            a_psi, a_V, a_w = (math.exp(-dt / params.tau_heading_s), math.exp(-dt / params.tau_airspeed_s),
                               math.exp(-dt / params.tau_wind_s))
            e_psi = a_psi * e_psi + s_psi * math.sqrt(1 - a_psi ** 2) * rng.standard_normal()
            e_V = a_V * e_V + s_V * math.sqrt(1 - a_V ** 2) * rng.standard_normal()
            e_w = a_w * e_w + s_w * math.sqrt(1 - a_w ** 2) * rng.standard_normal(2)
            psi_t, V_t = psi0 + e_psi, V + e_V
            p_true += dt * (np.array([V_t * math.cos(psi_t), V_t * math.sin(psi_t)]) + e_w)
        errs[r] = p_true - dt * n * V * np.array([math.cos(psi0), math.sin(psi0)])
    s0 = dr_init(0.0, D(30.0), 0.0, 0.0, 0.0, s_psi, s_V, s_w)
    s, _ = fly(s0, psi0, V, n=n, dt=dt, heading_sigma=s_psi, tas_sigma=s_V, wind_sigma=s_w, params=params)
    P = s.P[0:2, 0:2]
    nees = np.mean(np.einsum("ri,ij,rj->r", errs, np.linalg.inv(P), errs))
    # THEN the normalised error (chi-square, 2 dof) averages 2: neither optimistic nor pessimistic
    assert nees == pytest.approx(2.0, abs=0.3)


def test_unknown_heading_grows_the_unknown_radius_and_holds_the_mean():
    s0 = dr_init(0.0, D(10.0), D(20.0), 100.0, 5.0, D(1.0), 1.0, 1.0)
    params = DrParams(max_airspeed_m_s=35.0)
    s = s0
    for k in range(50):
        s, diag = dr_step(s, DrInputs(s.time_s + 0.2, None, None, 22.0, 1.0, (3.0, 4.0), 1.0), params)
    assert (s.lat_rad, s.lon_rad) == (s0.lat_rad, s0.lon_rad)
    assert not diag.moved
    assert s.unknown_radius_m == pytest.approx((35.0 + 5.0 + 3.0) * 10.0, rel=1e-9)


def test_predicted_covariance_equals_stepping():
    params = DrParams()
    s0 = dr_init(0.0, D(45.0), 0.0, 0.0, 5.0, D(2.0), 1.0, 1.0)
    s, _ = fly(s0, D(200.0), 20.0, n=300, heading_sigma=D(2.0), params=params)
    pk = dr_predict_covariance(s.P, D(200.0), 20.0, (math.hypot(D(2.0), params.sideslip_sigma_rad), 1.0, 1.0),
                               np.array([0.0, 10.0, 20.0]), params)
    s2, _ = fly(s, D(200.0), 20.0, n=200, dt=0.1, heading_sigma=D(2.0), params=params)
    assert pk[0] == pytest.approx(s.P[0:2, 0:2], rel=1e-12)
    # 1 s vs 0.1 s steps (second-order discretisation): within 3e-3 of the largest variance
    assert pk[2] == pytest.approx(s2.P[0:2, 0:2], abs=3e-3 * float(np.max(np.diag(s2.P[0:2, 0:2]))))


def test_transition_is_second_order_accurate():
    expm = pytest.importorskip("scipy.linalg").expm
    params = DrParams()
    F = (transition(D(30.0), 20.0, 1e-7, params)[0] - np.eye(6)) / 1e-7
    err = [np.max(np.abs(transition(D(30.0), 20.0, h, params)[0] - expm(F * h))) for h in (0.5, 0.25)]
    assert err[0] < 3e-5                           # 5e-6 relative on the largest entry (~5 m/rad)
    assert err[0] / err[1] == pytest.approx(8.0, rel=0.05)  # local error O(dt^3)


def test_wind_estimate_recovers_wind_and_honest_sigma():
    rng = np.random.default_rng(2)
    st = WindEstState()
    true_w = np.array([3.0, -4.0])
    for k in range(600):
        psi = D(10.0) + 0.5 * math.sin(k / 50)
        vg = 20.0 * np.array([math.cos(psi), math.sin(psi)]) + true_w + 0.3 * rng.standard_normal(2)
        if k == 0:
            vg = vg + 10.0    # a wild first sample (still on the launcher) must not dominate
        st = wind_estimate_step(st, k * 0.2, tuple(vg), psi, 20.0)
    assert st.wind_ne_m_s == pytest.approx(tuple(true_w), abs=0.1)
    assert st.duration_s == pytest.approx(60.0)
    sig = wind_estimate_sigma_m_s(st, D(1.0), 20.0, 0.1)
    assert sig == pytest.approx(math.hypot(20.0 * D(1.0), 0.3 / math.sqrt(60.0 / 5.0)), rel=0.1)


def test_wind_estimate_first_samples_are_a_plain_mean():
    st = WindEstState()
    for k, w in enumerate((10.0, 0.0, 2.0)):
        st = wind_estimate_step(st, k * 0.2, (20.0 + w, 0.0), 0.0, 20.0)
    assert st.wind_ne_m_s[0] == pytest.approx(4.0, abs=1e-12)
    assert st.var_ne_m2_s2[0] == pytest.approx(np.var([10.0, 0.0, 2.0]), abs=1e-12)


def test_inputs_validated():
    s0 = dr_init(0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="heading_sigma_rad"):
        dr_step(s0, DrInputs(1.0, 0.3, None, 20.0, 1.0, (0.0, 0.0), 1.0))
    with pytest.raises(ValueError, match="must not go back"):
        dr_step(s0, DrInputs(-1.0, 0.3, 0.1, 20.0, 1.0, (0.0, 0.0), 1.0))
    with pytest.raises(ValueError, match="wind_ne_m_s"):
        dr_step(s0, DrInputs(1.0, 0.3, 0.1, 20.0, 1.0, (math.nan, 0.0), 1.0))
    with pytest.raises(ValueError, match="pole"):
        dr_init(0.0, D(90.0), 0.0, 0.0, 1.0, 0.0, 1.0, 1.0)
