"""The published attitude between two steps of the filters (beyond the seed: an AHRS publishes at
its IMU rate, while method C's filters run at ``filter_rate_hz`` on mean increments).

The last filtered attitude is turned by the gyro increments of the IMU samples since. Each sample
is the mean rate over its interval (as the filters take it), so its increment is a_k = (w_k - b) dt_k,
plus the two-interval coning term (polar_attitude's mechanisation, per IMU sample):

    q_nav_from_body <- q_nav_from_body (x) q(a_k + a_{k-1} x a_k / 12)

b is the attitude filter's gyro bias at the last filter step. The Earth and transport rates
(< 1e-4 rad/s) are left out: over a filter period of 20 ms they turn the attitude by < 2e-6 rad.
Why it matters: held for one 10 ms sample, a solution is 7 deg behind a 700 deg/s spin.

Scalar arithmetic on Python floats (strapdown.py's reason: numpy on 3-vectors costs ~5x more);
the state is a plain tuple-holding dataclass.

Pure: ``output_reset(q_nav_from_body, time_s) -> state`` at a filter step,
``output_step(state, time_s, gyro_body_rad_s, bias_body_rad_s, max_dt_s) -> state`` per IMU sample
(None when the interval is not integrable: the attitude is then not published until the next
filter step).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class OutputState:
    q_nav_from_body: tuple[float, float, float, float]
    """Hamilton [w, x, y, z]."""
    time_s: float
    increment_prev: tuple[float, float, float] | None = None
    """The previous sample's increment a_{k-1} (rad), for the coning term."""


def output_reset(q_nav_from_body, time_s: float,
                 increment_prev: tuple[float, float, float] | None = None) -> OutputState:
    w, x, y, z = (float(v) for v in q_nav_from_body)
    return OutputState((w, x, y, z), float(time_s), increment_prev)


def increment(gyro_body_rad_s, bias_body_rad_s, dt_s: float) -> tuple[float, float, float]:
    """a = (w - b) dt (rad, body axes)."""
    gx, gy, gz = (float(v) for v in gyro_body_rad_s)
    bx, by, bz = (float(v) for v in bias_body_rad_s)
    return (gx - bx) * dt_s, (gy - by) * dt_s, (gz - bz) * dt_s


def output_step(state: OutputState, time_s: float, gyro_body_rad_s, bias_body_rad_s,
                max_dt_s: float) -> OutputState | None:
    dt = time_s - state.time_s
    if not (0.0 < dt <= max_dt_s):
        return None
    ax, ay, az = increment(gyro_body_rad_s, bias_body_rad_s, dt)
    if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az)):
        return None
    px, py, pz = ax, ay, az
    if state.increment_prev is not None:       # + a_prev x a / 12
        ux, uy, uz = state.increment_prev
        px += (uy * az - uz * ay) / 12.0
        py += (uz * ax - ux * az) / 12.0
        pz += (ux * ay - uy * ax) / 12.0
    angle = math.sqrt(px * px + py * py + pz * pz)
    k = 0.5 - angle * angle / 48.0 if angle < 1e-6 else math.sin(0.5 * angle) / angle
    rw, rx, ry, rz = math.cos(0.5 * angle), k * px, k * py, k * pz
    qw, qx, qy, qz = state.q_nav_from_body
    nw = qw * rw - qx * rx - qy * ry - qz * rz
    nx = qw * rx + qx * rw + qy * rz - qz * ry
    ny = qw * ry - qx * rz + qy * rw + qz * rx
    nz = qw * rz + qx * ry - qy * rx + qz * rw
    n = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    return OutputState((nw / n, nx / n, ny / n, nz / n), time_s, (ax, ay, az))
