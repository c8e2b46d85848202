"""estimators/rotations.py against scipy's Rotation (an independent implementation)."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimators import rotations as r

RNG = np.random.default_rng(7)
EULERS = [(0.0, 0.0, 0.0), (0.3, -0.2, 1.0), (-3.0, 1.5, 6.0), (0.1, -1.5707, 3.1), (2.0, 0.4, -2.5)]


def scipy_dcm(roll, pitch, yaw):
    # intrinsic Z-Y'-X'' = aerospace yaw, pitch, roll; as_matrix maps body -> nav
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


@pytest.mark.parametrize("e", EULERS)
def test_dcm_from_euler_matches_scipy(e):
    np.testing.assert_allclose(r.dcm_from_euler(*e), scipy_dcm(*e), atol=1e-14)


@pytest.mark.parametrize("e", EULERS)
def test_quat_from_euler_matches_scipy(e):
    q = r.quat_from_euler(*e)
    x, y, z, w = Rotation.from_euler("ZYX", [e[2], e[1], e[0]]).as_quat()
    q_ref = np.array([w, x, y, z])
    q_ref = q_ref if q_ref[0] >= 0 else -q_ref
    np.testing.assert_allclose(q, q_ref, atol=1e-14)
    np.testing.assert_allclose(r.dcm_from_quat(q), scipy_dcm(*e), atol=1e-14)


def test_euler_round_trip():
    for _ in range(200):
        roll, yaw = RNG.uniform(-math.pi, math.pi), RNG.uniform(0, 2 * math.pi)
        pitch = RNG.uniform(-1.5, 1.5)
        got = r.euler_from_quat(r.quat_from_euler(roll, pitch, yaw))
        np.testing.assert_allclose(got, (roll, pitch, yaw), atol=1e-10)


def test_quat_mul_composes_like_dcms():
    for _ in range(100):
        a, b = Rotation.random(random_state=RNG), Rotation.random(random_state=RNG)
        qa = np.roll(a.as_quat(), 1)
        qb = np.roll(b.as_quat(), 1)
        np.testing.assert_allclose(r.dcm_from_quat(r.quat_mul(qa, qb)), (a * b).as_matrix(), atol=1e-13)


def test_quat_dcm_round_trip_all_branches():
    for _ in range(500):
        R = Rotation.random(random_state=RNG).as_matrix()
        np.testing.assert_allclose(r.dcm_from_quat(r.quat_from_dcm(R)), R, atol=1e-13)


def test_rotvec_matches_scipy():
    for v in [np.zeros(3), np.array([1e-9, 0, 0]), np.array([0.1, -0.2, 0.3]), np.array([0, 0, 3.0])]:
        q = r.quat_from_rotvec(v)
        np.testing.assert_allclose(r.dcm_from_quat(q), Rotation.from_rotvec(v).as_matrix(), atol=1e-14)
        np.testing.assert_allclose(r.rotvec_from_quat(q), v, atol=1e-12)


def test_frame_rotations_are_transposes():
    a = 0.7
    np.testing.assert_allclose(r.frame_rot_z(a), r.rot_z(a).T)
    # a frame turned by +90 deg about down sees north as -y... i.e. north = [0, -1, 0]
    np.testing.assert_allclose(r.frame_rot_z(math.pi / 2) @ np.array([1.0, 0, 0]), [0, -1, 0], atol=1e-15)


def test_wrap():
    assert r.wrap_2pi(-1e-18) == 0.0
    assert r.wrap_2pi(2 * math.pi) == 0.0
    assert r.wrap_2pi(-math.pi / 2) == pytest.approx(1.5 * math.pi)
    assert r.wrap_pi(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_normalize_rejects_zero_and_nan():
    with pytest.raises(ValueError):
        r.quat_normalize(np.zeros(4))
    with pytest.raises(ValueError):
        r.quat_normalize(np.array([np.nan, 0, 0, 0]))
