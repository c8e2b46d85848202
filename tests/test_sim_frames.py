"""sim.frames (the simulator's own rotation code) against scipy's Rotation as the reference."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim import frames


def _scipy_q(q_wxyz):
    return Rotation.from_quat(np.roll(q_wxyz, -1, axis=-1))


def test_euler_quat_dcm_match_scipy():
    rng = np.random.default_rng(0)
    e = np.column_stack([rng.uniform(-math.pi, math.pi, 500), rng.uniform(-1.5, 1.5, 500),
                         rng.uniform(-math.pi, math.pi, 500)])
    q = frames.q_from_euler(e[:, 0], e[:, 1], e[:, 2])
    ref = Rotation.from_euler("ZYX", e[:, ::-1])  # intrinsic yaw, pitch, roll == C = Rz Ry Rx
    np.testing.assert_allclose(frames.dcm_from_q(q), ref.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(frames.euler_from_q(q), e, atol=1e-9)
    v = rng.normal(size=(500, 3))
    np.testing.assert_allclose(frames.rotate(q, v), ref.apply(v), atol=1e-12)
    np.testing.assert_allclose(frames.rotate_inv(q, v), ref.inv().apply(v), atol=1e-12)
    p = q[::-1]
    np.testing.assert_allclose(frames.dcm_from_q(frames.qmul(q, p)),
                               (ref * _scipy_q(p)).as_matrix(), atol=1e-12)
    r = rng.normal(size=(500, 3))
    np.testing.assert_allclose(frames.dcm_from_q(frames.q_from_rotvec(r)), Rotation.from_rotvec(r).as_matrix(),
                               atol=1e-12)
    rv = frames.rotvec_from_q(frames.q_from_rotvec(r * 0.3))
    np.testing.assert_allclose(rv, r * 0.3, atol=1e-12)
    for C in ref.as_matrix()[:50]:
        np.testing.assert_allclose(frames.dcm_from_q(frames.q_from_dcm(C)), C, atol=1e-12)


@pytest.mark.parametrize("pitch_deg", [90.0, -90.0])
def test_euler_at_gimbal_lock_keeps_the_rotation(pitch_deg):
    """Nose straight up (a vertical launcher): roll is reported 0 and the rotation is preserved."""
    q = frames.q_from_euler(0.3, math.radians(pitch_deg), math.radians(135.0))
    e = frames.euler_from_q(q)
    assert e[0] == 0.0 and math.degrees(e[1]) == pytest.approx(pitch_deg)
    np.testing.assert_allclose(frames.dcm_from_q(frames.q_from_euler(*e)), frames.dcm_from_q(q), atol=1e-9)
