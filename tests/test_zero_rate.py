"""estimators/zero_rate: rest detection and the zero-rate update of method C's gyro biases."""
import math

import numpy as np
import pytest

from estimators.polar_attitude import I_BG, polar_attitude_init_at
from estimators.polar_heading import PolarHeadingState
from estimators.rotations import quat_from_euler
from estimators.zero_rate import (ZeroRateParams, ZeroRateState, attitude_zero_rate_update,
                                  heading_zero_rate_update, rest_step)

D = math.radians
DT = 0.02
G_BODY = np.array([0.0, 0.0, -9.80665])
BIAS = np.array([D(0.10), D(-0.05), D(0.16)])


def feed(rate_of_t, duration_s, seed=0, gyro_noise=D(0.03), accel_noise=0.02, t0=0.0, st=None):
    rng = np.random.default_rng(seed)
    st = ZeroRateState() if st is None else st
    out = []
    for k in range(1, int(round(duration_s / DT)) + 1):
        t = t0 + k * DT
        w = BIAS + np.asarray(rate_of_t(t), float) + rng.normal(0.0, gyro_noise, 3)
        st, r = rest_step(st, t, w, G_BODY + rng.normal(0.0, accel_noise, 3))
        if r is not None:
            out.append((t, r))
    return st, out


def test_given_a_still_imu_then_the_rest_mean_is_the_bias_within_its_sigma():
    # GIVEN a still IMU with a bias, 50 Hz WHEN fed 20 s
    _, out = feed(lambda t: (0, 0, 0), 20.0)
    # THEN the first measurement comes min_rest_s (1.5 s) after the run's first sample (the second:
    # the first one starts the low-pass)
    # and then every chunk_s (0.5 s)
    times = [t for t, _ in out]
    assert times[0] == pytest.approx(2 * DT + 1.5, abs=1e-9)
    assert np.allclose(np.diff(times), 0.5)
    # AND the means scatter about the bias as their stated sigmas say (the run's scatter over
    # sqrt(n), here the noise 0.03 deg/s over sqrt(25), or 76 for the first): 37 x 3 normalised
    # errors of unit variance (the scatter is estimated, so the tails are Student's, not normal)
    z = np.array([(r.mean_gyro_body_rad_s - BIAS) / np.sqrt(r.variance_rad2_s2) for _, r in out])
    assert z.shape == (37, 3)
    assert 0.6 <= float(np.mean(z * z)) <= 1.6 and float(np.max(np.abs(z))) < 4.5, z
    for _, r in out:
        assert np.allclose(np.sqrt(r.variance_rad2_s2), D(0.03) / math.sqrt(r.n_samples), rtol=0.2)


@pytest.mark.parametrize("rate", [(0.0, 0.0, D(3.0)), (D(-2.5), 0.0, 0.0)], ids=["yaw_3deg_s", "roll_2.5deg_s"])
def test_a_steady_slow_turn_is_no_rest(rate):
    # GIVEN a steady turn faster than max_rate_rad_s (2 deg/s) WHEN fed 5 s THEN no measurement
    _, out = feed(lambda t: rate, 5.0)
    assert out == []


def test_motion_restarts_the_rest_run():
    # GIVEN 1.2 s still, a 0.2 s shake of 30 deg/s, still again WHEN fed THEN the first measurement
    # comes min_rest_s after the shake's effect on the low-pass has settled, not before
    def rate(t):
        return (0.0, D(30.0), 0.0) if 1.2 <= t < 1.4 else (0.0, 0.0, 0.0)
    _, out = feed(rate, 6.0)
    assert out and out[0][0] > 1.4 + 1.5


def _heading_state(bias_guess=(0.0, 0.0, 0.0), sigma_b=D(0.2)):
    x = np.array([1.0, 0.0, *bias_guess])
    P = np.diag([D(3.0) ** 2, 7.3e-5 ** 2, sigma_b ** 2, sigma_b ** 2, sigma_b ** 2])
    q = quat_from_euler(D(20.0), D(-10.0), 0.0)
    return PolarHeadingState(initialised=True, time_s=0.0, x=x, P=P, platform=True, q_P_from_body=q)


def test_heading_filter_learns_its_bias_at_rest_and_the_vertical_rate_is_kept_apart():
    # GIVEN the heading filter's platform state, bias unknown (prior 0.2 deg/s), banked 20 deg
    st = _heading_state()
    _, out = feed(lambda t: (0, 0, 0), 6.0, seed=2)
    # WHEN the rest measurements are fused
    for _, r in out:
        st, d = heading_zero_rate_update(st, r)
        assert d.fused
    # THEN its bias is the true one within 0.01 deg/s per axis (Earth rate allowance W = 0.004 deg/s
    # and the noise) and its sigma has come down from 0.2 to below 0.01 deg/s
    assert np.all(np.abs(st.x[2:5] - BIAS) < D(0.01))
    assert np.all(np.sqrt(np.diag(st.P)[2:5]) < D(0.01))
    assert math.sqrt(st.P[1, 1]) <= 7.3e-5 * 1.0001     # the vertical rate is not taken for bias


def test_a_turn_taken_for_a_rest_is_gated_out_once_the_bias_is_known():
    # GIVEN a heading filter that knows its bias to 0.005 deg/s
    st = _heading_state(bias_guess=BIAS, sigma_b=D(0.005))
    # WHEN a 'rest' reports a 1.5 deg/s yaw (below the detector's 2 deg/s: a slow turn)
    _, out = feed(lambda t: (0.0, 0.0, D(1.5)), 3.0)
    assert out
    st2, d = heading_zero_rate_update(st, out[0][1])
    # THEN it is rejected and nothing changes
    assert not d.fused and d.test_ratio > 1.0 and st2 is st


def test_attitude_filter_learns_its_bias_at_rest():
    # GIVEN C's attitude filter levelled at roll 10 deg, bias prior 0.5 deg/s
    st = polar_attitude_init_at(0.0, D(10.0), 0.0, D(1.0))
    _, out = feed(lambda t: (0, 0, 0), 6.0, seed=3)
    for _, r in out:
        st, d = attitude_zero_rate_update(st, r)
        assert d.fused
    # THEN its bias estimate (Earth and transport rates in P are its states too: b + C_BP W) is
    # the true bias within 0.01 deg/s and its sigma well below the prior
    b_plus_w = st.x_hat[0:3]
    assert np.all(np.abs(b_plus_w - BIAS) < D(0.01))
    assert np.all(np.sqrt(np.diag(st.P[I_BG, I_BG])) < D(0.05))


def test_params_are_validated():
    with pytest.raises(ValueError, match="min_rest_s"):
        ZeroRateParams(min_rest_s=0.0)
