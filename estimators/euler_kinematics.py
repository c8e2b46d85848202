"""Euler-angle kinematics (METHODS.md B1; seed AU756340B2 eq. 1 and the INS-rate equation).

ZYX Euler angles (roll phi, pitch theta, yaw psi; ``C_nav_from_body = R_z(psi) R_y(theta)
R_x(phi)``, see rotations.py) and body rates omega = [p, q, r] (rad/s, FRD body axes):

    phi_dot   = p + tan(theta) (q sin(phi) + r cos(phi))
    theta_dot = q cos(phi) - r sin(phi)                        (eq. 1)
    psi_dot   = (q sin(phi) + r cos(phi)) / cos(theta)

i.e. euler_dot = T(phi, theta) omega with

    T = [[1, sin(phi) tan(theta), cos(phi) tan(theta)],
         [0, cos(phi),            -sin(phi)          ],
         [0, sin(phi)/cos(theta), cos(phi)/cos(theta)]]

and its inverse W = T^-1 (the seed's "rates implied by the INS Euler angles"):

    p = phi_dot - psi_dot sin(theta)
    q = theta_dot cos(phi) + psi_dot cos(theta) sin(phi)
    r = -theta_dot sin(phi) + psi_dot cos(theta) cos(phi)

The same T maps a small rotation gamma of the body frame (C_true = C_hat (I + [gamma x])) to
the Euler-angle error: delta_euler = T gamma (used as measurement matrix by KF2).
Singular at |theta| = 90 deg (the Euler representation, not the vehicle).
"""
from __future__ import annotations

import math

import numpy as np

PITCH_SINGULAR_MARGIN_RAD = 1e-6


def _check_pitch(pitch_rad: float) -> None:
    if abs(abs(pitch_rad) - 0.5 * math.pi) < PITCH_SINGULAR_MARGIN_RAD:
        raise ValueError(f"Euler kinematics singular at pitch {pitch_rad!r} rad (|pitch| = 90 deg)")


def euler_rate_matrix(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """T(phi, theta): euler_dot = T @ omega_body (and delta_euler = T @ gamma_body)."""
    _check_pitch(pitch_rad)
    sp, cp = math.sin(roll_rad), math.cos(roll_rad)
    tt, ct = math.tan(pitch_rad), math.cos(pitch_rad)
    return np.array([[1.0, sp * tt, cp * tt], [0.0, cp, -sp], [0.0, sp / ct, cp / ct]])


def euler_rate_matrix_reported(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """T for REPORTING an Euler covariance (T P_gamma T^T), defined at any pitch: within the
    singular margin the pitch is taken at twice the margin from 90 deg, so roll and heading sigma
    are the limit from outside it (tan(90 deg - 2e-6 rad) = 5e5 times the body-frame sigma where
    P does not correlate them): not separable there, and their sigma says so, continuously with
    the pitch just outside. Never a measurement Jacobian (those stay singular and say so)."""
    bound = 0.5 * math.pi - 2.0 * PITCH_SINGULAR_MARGIN_RAD
    return euler_rate_matrix(roll_rad, math.copysign(min(abs(pitch_rad), bound), pitch_rad))


def body_rate_matrix(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """W(phi, theta) = T^-1: omega_body = W @ euler_dot (defined at any pitch)."""
    sp, cp = math.sin(roll_rad), math.cos(roll_rad)
    st, ct = math.sin(pitch_rad), math.cos(pitch_rad)
    return np.array([[1.0, 0.0, -st], [0.0, cp, ct * sp], [0.0, -sp, ct * cp]])


def euler_rates(roll_rad: float, pitch_rad: float, omega_body_rad_s) -> np.ndarray:
    """[phi_dot, theta_dot, psi_dot] (rad/s) from body rates [p, q, r] (eq. 1)."""
    p, q, r = (float(v) for v in omega_body_rad_s)
    _check_pitch(pitch_rad)
    sp, cp = math.sin(roll_rad), math.cos(roll_rad)
    a = q * sp + r * cp
    return np.array([p + math.tan(pitch_rad) * a, q * cp - r * sp, a / math.cos(pitch_rad)])


def body_rates(roll_rad: float, pitch_rad: float, euler_dot_rad_s) -> np.ndarray:
    """[p, q, r] (rad/s) implied by Euler angles and their rates (inverse of eq. 1)."""
    return body_rate_matrix(roll_rad, pitch_rad) @ np.asarray(euler_dot_rad_s, dtype=float)


def euler_integrate(euler_rad, omega0_body_rad_s, omega1_body_rad_s, dt_s: float) -> np.ndarray:
    """Integrate eq. 1 over dt with the rate linear between two samples (classical RK4).

    ``euler_rad`` = [roll, pitch, yaw]; returns the new angles, yaw unwrapped (caller wraps).
    """
    e = np.asarray(euler_rad, dtype=float)
    w0 = np.asarray(omega0_body_rad_s, dtype=float)
    w1 = np.asarray(omega1_body_rad_s, dtype=float)
    wm = 0.5 * (w0 + w1)
    k1 = euler_rates(e[0], e[1], w0)
    e2 = e + 0.5 * dt_s * k1
    k2 = euler_rates(e2[0], e2[1], wm)
    e3 = e + 0.5 * dt_s * k2
    k3 = euler_rates(e3[0], e3[1], wm)
    e4 = e + dt_s * k3
    k4 = euler_rates(e4[0], e4[1], w1)
    return e + dt_s / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
