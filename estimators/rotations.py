"""Rotations: the one place the project's attitude conventions live.

Conventions (DESIGN.md):
- navigation frame NED, body frame FRD, sensor frame = IMU axes;
- a direction cosine matrix is named by what it does: ``C_nav_from_body @ v_body -> v_nav``;
- quaternions are Hamilton, scalar first ``[w, x, y, z]``, named ``q_a_from_b`` and acting as
  ``v_a = q * v_b * conj(q)``; ``dcm_from_quat(q_a_from_b) == C_a_from_b``;
- Euler angles are aerospace ZYX: ``C_nav_from_body = R_z(yaw) R_y(pitch) R_x(roll)`` where the
  ``R_*`` are active rotations of vectors;
- heading/azimuth in [0, 2pi) inside, degrees only at the edges.

Elementary *frame* rotations (METHODS.md A uses them): ``frame_rot_x(a) = R_x(a).T`` etc., i.e.
``frame_rot_z(psi) @ v_nav`` gives the components of ``v_nav`` in a frame turned by ``psi`` about
down.
"""
from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi


def _floats(v) -> list | tuple:
    """Python floats of a small vector: scalar arithmetic on them is several times faster than
    on numpy scalars (the per-IMU-sample hot path; bench/speed.py)."""
    return v.tolist() if isinstance(v, np.ndarray) else v


def wrap_2pi(angle_rad: float) -> float:
    """Wrap an angle to [0, 2pi)."""
    a = math.fmod(angle_rad, TWO_PI)
    if a < 0.0:
        a += TWO_PI
    # fmod of a value just below 0 can round to exactly 2pi
    return 0.0 if a >= TWO_PI else a


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return wrap_2pi(angle_rad + math.pi) - math.pi


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: skew(a) @ b == cross(a, b)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# --- elementary rotations -------------------------------------------------------------------

def rot_x(a: float) -> np.ndarray:
    """Active rotation of a vector by angle ``a`` about x."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Active rotation of a vector by angle ``a`` about y."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Active rotation of a vector by angle ``a`` about z."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def frame_rot_x(a: float) -> np.ndarray:
    """Frame rotation R1(a): components in a frame turned by ``a`` about x (= rot_x(a).T)."""
    return rot_x(a).T


def frame_rot_y(a: float) -> np.ndarray:
    """Frame rotation R2(a) = rot_y(a).T."""
    return rot_y(a).T


def frame_rot_z(a: float) -> np.ndarray:
    """Frame rotation R3(a) = rot_z(a).T."""
    return rot_z(a).T


# --- Euler (ZYX) ----------------------------------------------------------------------------

def dcm_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """C_nav_from_body from aerospace ZYX Euler angles."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def euler_from_dcm(C_nav_from_body: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad from C_nav_from_body; yaw in [0, 2pi), pitch in [-pi/2, pi/2]."""
    C = C_nav_from_body
    pitch = -math.asin(max(-1.0, min(1.0, C[2, 0])))
    roll = math.atan2(C[2, 1], C[2, 2])
    yaw = wrap_2pi(math.atan2(C[1, 0], C[0, 0]))
    return roll, pitch, yaw


# --- quaternions ----------------------------------------------------------------------------

def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q (scalar first)."""
    pw, px, py, pz = _floats(p)
    qw, qx, qy, qz = _floats(q)
    return np.array([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (= inverse for a unit quaternion): q_b_from_a from q_a_from_b."""
    w, x, y, z = _floats(q)
    return np.array([w, -x, -y, -z])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with non-negative scalar part (one representative of +-q)."""
    w, x, y, z = _floats(q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0.0 or not math.isfinite(n):
        raise ValueError(f"cannot normalise quaternion {q!r}")
    if w < 0.0:
        n = -n
    return np.array([w / n, x / n, y / n, z / n])


def quat_from_rotvec(rotvec_rad: np.ndarray) -> np.ndarray:
    """Quaternion of the rotation by |v| about v/|v| (exact, series near zero)."""
    vx, vy, vz = _floats(rotvec_rad)
    angle = math.sqrt(vx * vx + vy * vy + vz * vz)
    half = 0.5 * angle
    if angle < 1e-6:
        # sin(h)/angle = 1/2 - angle^2/48 + ...
        k = 0.5 - angle * angle / 48.0
        return np.array([math.cos(half), k * vx, k * vy, k * vz])
    k = math.sin(half) / angle
    return np.array([math.cos(half), k * vx, k * vy, k * vz])


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion (shortest rotation)."""
    q = quat_normalize(q)
    v = q[1:]
    s = math.sqrt(float(v @ v))
    if s < 1e-12:
        return 2.0 * v
    angle = 2.0 * math.atan2(s, q[0])
    return v * (angle / s)


def dcm_from_quat(q: np.ndarray) -> np.ndarray:
    """C_a_from_b from q_a_from_b (unit quaternion)."""
    w, x, y, z = _floats(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_dcm(C: np.ndarray) -> np.ndarray:
    """q_a_from_b from C_a_from_b (Shepperd's method, numerically safe for any rotation)."""
    (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = (C.tolist() if isinstance(C, np.ndarray)
                                                          else [list(r) for r in C])
    tr = c00 + c11 + c22
    cand = (tr, c00, c11, c22)
    k = cand.index(max(cand))  # first maximum, as np.argmax
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (c21 - c12) / s, (c02 - c20) / s, (c10 - c01) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + c00 - c11 - c22)
        q = [(c21 - c12) / s, 0.25 * s, (c01 + c10) / s, (c02 + c20) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 - c00 + c11 - c22)
        q = [(c02 - c20) / s, (c01 + c10) / s, 0.25 * s, (c12 + c21) / s]
    else:
        s = 2.0 * math.sqrt(1.0 - c00 - c11 + c22)
        q = [(c10 - c01) / s, (c02 + c20) / s, (c12 + c21) / s, 0.25 * s]
    return quat_normalize(q)


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """q_nav_from_body from ZYX Euler angles."""
    cr, sr = math.cos(0.5 * roll_rad), math.sin(0.5 * roll_rad)
    cp, sp = math.cos(0.5 * pitch_rad), math.sin(0.5 * pitch_rad)
    cy, sy = math.cos(0.5 * yaw_rad), math.sin(0.5 * yaw_rad)
    return quat_normalize(np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]))


def euler_from_quat(q_nav_from_body: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad from q_nav_from_body; yaw in [0, 2pi).

    ``euler_from_dcm(dcm_from_quat(q))`` with only the five DCM elements it reads, computed by the
    same expressions (so the result is bit for bit the same)."""
    w, x, y, z = _floats(q_nav_from_body)
    c20 = 2 * (x * z - w * y)
    pitch = -math.asin(max(-1.0, min(1.0, c20)))
    roll = math.atan2(2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    yaw = wrap_2pi(math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z)))
    return roll, pitch, yaw


def orthonormalize(C: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD), for DCMs that accumulated round-off."""
    u, _, vt = np.linalg.svd(C)
    R = u @ vt
    if np.linalg.det(R) < 0.0:
        u[:, -1] *= -1.0
        R = u @ vt
    return R
