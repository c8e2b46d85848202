"""Euler kinematics (METHODS.md B1, seed eq. 1) against known rotations."""
import math

import numpy as np
import pytest

from estimators.euler_kinematics import (body_rate_matrix, body_rates, euler_integrate,
                                         euler_rate_matrix, euler_rates)
from estimators.rotations import dcm_from_euler, euler_from_dcm, quat_from_rotvec, dcm_from_quat


def test_T_and_W_are_inverse():
    rng = np.random.default_rng(3)
    for _ in range(50):
        r, p = rng.uniform(-math.pi, math.pi), rng.uniform(-1.4, 1.4)
        assert np.allclose(euler_rate_matrix(r, p) @ body_rate_matrix(r, p), np.eye(3), atol=1e-12)


def test_hand_values():
    # level: euler rates = body rates
    assert np.allclose(euler_rates(0.0, 0.0, [0.1, 0.2, 0.3]), [0.1, 0.2, 0.3], atol=1e-15)
    # banked 90 deg right, pitch rate q turns the nose toward the right wing: yaw rate = q
    assert np.allclose(euler_rates(math.pi / 2, 0.0, [0.0, 0.2, 0.0]), [0.0, 0.0, 0.2], atol=1e-15)
    # pitch 45 deg, yaw body rate r=0.1: phi_dot = tan(45) r = 0.1, psi_dot = r / cos 45
    assert np.allclose(euler_rates(0.0, math.pi / 4, [0, 0, 0.1]),
                       [0.1, 0.0, 0.1 * math.sqrt(2.0)], atol=1e-15)
    with pytest.raises(ValueError, match="singular"):
        euler_rates(0.0, math.pi / 2, [0, 0, 0])


def test_integration_matches_constant_rate_rotation():
    """Constant body rate w: C(t) = C0 exp([w x] t) exactly; eq. 1 integrated must follow."""
    C0 = dcm_from_euler(0.3, -0.2, 1.0)
    w = np.array([0.2, -0.15, 0.25])  # rad/s
    dt, n = 0.01, 1000  # 10 s at 100 Hz
    e = np.array(euler_from_dcm(C0))
    for _ in range(n):
        e = euler_integrate(e, w, w, dt)
    C_true = C0 @ dcm_from_quat(quat_from_rotvec(w * dt * n))
    r, p, y = euler_from_dcm(C_true)
    assert e[0] == pytest.approx(r, abs=1e-9)
    assert e[1] == pytest.approx(p, abs=1e-9)
    assert math.remainder(e[2] - y, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_body_rates_from_differentiated_euler_angles():
    """W(euler) @ d(euler)/dt must recover the body rate of a known rotation."""
    C0 = dcm_from_euler(-0.4, 0.3, 2.0)
    w = np.array([-0.1, 0.3, 0.05])
    h = 1e-5

    def eul(t):
        return np.array(euler_from_dcm(C0 @ dcm_from_quat(quat_from_rotvec(w * t))))
    e0, ep, em = eul(1.0), eul(1.0 + h), eul(1.0 - h)
    de = (ep - em) / (2 * h)
    de[2] = math.remainder(ep[2] - em[2], 2 * math.pi) / (2 * h)
    assert np.allclose(body_rates(e0[0], e0[1], de), w, atol=1e-8)


def test_small_body_rotation_maps_to_euler_error_by_T():
    """C_true = C_hat (I + [g x]) -> euler_true - euler_hat = T(euler_hat) g (KF2's H)."""
    e_hat = (0.25, -0.35, 4.0)
    g = np.array([1e-4, -2e-4, 1.5e-4])
    C = dcm_from_euler(*e_hat) @ dcm_from_quat(quat_from_rotvec(g))
    d = np.array(euler_from_dcm(C)) - np.array(e_hat)
    d[2] = math.remainder(d[2], 2 * math.pi)
    assert np.allclose(d, euler_rate_matrix(e_hat[0], e_hat[1]) @ g, atol=1e-7)
