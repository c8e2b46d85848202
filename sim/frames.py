"""Rotation helpers of the simulator (its own code: sim/ shares no math with estimators/).

Conventions are the project's (DESIGN.md): Hamilton quaternions, scalar first ``[w, x, y, z]``,
``q_a_from_b`` acts as ``v_a = q v_b q*``; ``C_a_from_b`` maps b-components to a-components;
Euler angles are aerospace ZYX: ``C_nav_from_body = Rz(yaw) Ry(pitch) Rx(roll)`` (active
rotations). Every function here is vectorised over a leading axis: quaternions ``(..., 4)``,
vectors ``(..., 3)``, angles ``(...)``.
"""
from __future__ import annotations

import numpy as np


def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p*q, broadcast over leading axes."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], axis=-1)


def qconj(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion)."""
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def qnormalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, float)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def q_axis(axis: int, angle_rad: np.ndarray) -> np.ndarray:
    """Quaternion of an active rotation by ``angle_rad`` about body axis 0=x, 1=y, 2=z."""
    a = np.asarray(angle_rad, float) * 0.5
    q = np.zeros(a.shape + (4,))
    q[..., 0] = np.cos(a)
    q[..., 1 + axis] = np.sin(a)
    return q


def q_from_euler(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """q_nav_from_body for ZYX Euler angles: q = qz(yaw) qy(pitch) qx(roll)."""
    return qmul(qmul(q_axis(2, yaw_rad), q_axis(1, pitch_rad)), q_axis(0, roll_rad))


def euler_from_q(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles [roll, pitch, yaw] (rad, yaw in (-pi, pi]) of q_nav_from_body.

    At pitch = +-90 deg (a vertical launcher) roll and yaw are not separable: roll is reported
    as 0 and the whole rotation about the vertical goes into yaw.
    """
    q = qnormalize(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    s = np.clip(2.0 * (w * y - x * z), -1.0, 1.0)
    pitch = np.arcsin(s)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    gimbal = np.abs(s) > 1.0 - 1e-12
    if np.any(gimbal):
        # C = Rz(yaw) Ry(+-90) Rx(roll): C01 = -sin(yaw -+ roll), C11 = cos(yaw -+ roll)
        yaw_g = np.arctan2(-2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z))
        roll = np.where(gimbal, 0.0, roll)
        yaw = np.where(gimbal, yaw_g, yaw)
    return np.stack([roll, pitch, yaw], axis=-1)


def dcm_from_q(q: np.ndarray) -> np.ndarray:
    """C_a_from_b (..., 3, 3) of q_a_from_b."""
    w, x, y, z = np.moveaxis(qnormalize(q), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def q_from_dcm(C: np.ndarray) -> np.ndarray:
    """q_a_from_b of a single C_a_from_b (3, 3), Shepperd's method."""
    C = np.asarray(C, float)
    tr = np.trace(C)
    cands = [tr, C[0, 0], C[1, 1], C[2, 2]]
    i = int(np.argmax(cands))
    if i == 0:
        w = 0.5 * np.sqrt(1.0 + tr)
        q = [w, (C[2, 1] - C[1, 2]) / (4 * w), (C[0, 2] - C[2, 0]) / (4 * w), (C[1, 0] - C[0, 1]) / (4 * w)]
    elif i == 1:
        x = 0.5 * np.sqrt(1.0 + 2 * C[0, 0] - tr)
        q = [(C[2, 1] - C[1, 2]) / (4 * x), x, (C[0, 1] + C[1, 0]) / (4 * x), (C[0, 2] + C[2, 0]) / (4 * x)]
    elif i == 2:
        y = 0.5 * np.sqrt(1.0 + 2 * C[1, 1] - tr)
        q = [(C[0, 2] - C[2, 0]) / (4 * y), (C[0, 1] + C[1, 0]) / (4 * y), y, (C[1, 2] + C[2, 1]) / (4 * y)]
    else:
        z = 0.5 * np.sqrt(1.0 + 2 * C[2, 2] - tr)
        q = [(C[1, 0] - C[0, 1]) / (4 * z), (C[0, 2] + C[2, 0]) / (4 * z), (C[1, 2] + C[2, 1]) / (4 * z), z]
    q = np.array(q)
    return q * (1.0 if q[0] >= 0 else -1.0)


def rotvec_from_q(q: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a unit quaternion, shortest way round."""
    q = qnormalize(q)
    q = q * np.where(q[..., :1] < 0.0, -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    # angle/s -> 2 as s -> 0
    scale = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)
    return v * scale[..., None]


def q_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation vector (rad)."""
    v = np.asarray(v, float)
    a = np.linalg.norm(v, axis=-1)
    half = 0.5 * a
    k = np.where(a > 1e-12, np.sin(half) / np.where(a > 1e-12, a, 1.0), 0.5)
    return np.concatenate([np.cos(half)[..., None], v * k[..., None]], axis=-1)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v_a = q_a_from_b v_b q*, vectorised."""
    return np.einsum("...ij,...j->...i", dcm_from_q(q), np.asarray(v, float))


def rotate_inv(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v_b = q_a_from_b* v_a q, vectorised."""
    return np.einsum("...ji,...j->...i", dcm_from_q(q), np.asarray(v, float))


def dcm_from_euler_deg(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """C_a_from_b (3, 3) of ZYX Euler angles in degrees (configuration edge)."""
    r = np.radians([roll_deg, pitch_deg, yaw_deg])
    return dcm_from_q(q_from_euler(r[0], r[1], r[2]))
