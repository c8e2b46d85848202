"""Analytical synthetic flights for the azimuth tests (no simulator: rotations built in closed form).

A flight: rest on the launcher, then a boost along the nose without rotation, then manoeuvre
segments, each a rotation about a fixed sensor axis with a triangular rate profile that starts
and ends at zero. For such a profile the trapezoidal+coning strapdown is exact (fixed axis: no
coning; piecewise-linear rate with sample-aligned breakpoints: trapezoid exact), so an estimator
fed these noiseless samples must reproduce the truth to round-off. The tests in this file check
the generator itself against its closed-form truth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.rotations import dcm_from_euler, dcm_from_quat, quat_from_rotvec, rot_x, rot_y, rot_z
from estimators.strapdown import strapdown_init, strapdown_step

G = 9.80665
E_NED_GAUSS = np.array([0.21111462, 0.01564706, 0.43909658])  # WMM-2025, 48N 11E, 2026.9


@dataclass
class Flight:
    time_s: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    mag_gauss: np.ndarray
    C_nf_sf: np.ndarray          # (N,3,3) truth
    launch_time_s: float
    psi_s_rad: float             # truth yaw of ISF
    C_nf_isf: np.ndarray
    u_sf: np.ndarray             # nose in SF
    e_ned: np.ndarray


def rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    return dcm_from_quat(quat_from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * angle))


def make_flight(*, C_nf_isf: np.ndarray, u_sf: np.ndarray, segments=(), rate_hz: float = 100.0,
                rest_s: float = 3.0, boost_s: float = 1.5, thrust_m_s2: float = 30.0,
                gap_s: float = 0.2, tail_s: float = 1.0, e_ned: np.ndarray = E_NED_GAUSS,
                A: np.ndarray | None = None, b: np.ndarray | None = None,
                gyro_bias: np.ndarray | None = None, mag_noise_gauss: float = 0.0,
                gyro_noise_rad_s: float = 0.0, accel_noise_m_s2: float = 0.0, seed: int = 0) -> Flight:
    """segments: sequence of (axis_sf, angle_rad, duration_s); durations are rounded to an even
    number of samples so the triangle apex falls on a sample."""
    dt = 1.0 / rate_hz
    A = np.eye(3) if A is None else np.asarray(A, float)
    b = np.zeros(3) if b is None else np.asarray(b, float)
    bias = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float)
    rng = np.random.default_rng(seed)
    n_rest = int(round(rest_s * rate_hz))
    n_boost = int(round(boost_s * rate_hz))
    n_gap = int(round(gap_s * rate_hz))
    times, rates, Cs, thrust = [], [], [], []
    C = np.asarray(C_nf_isf, float).copy()
    k = 0

    def push(rate, Cnow, thr):
        nonlocal k
        times.append(k * dt)
        rates.append(rate)
        Cs.append(Cnow.copy())
        thrust.append(thr)
        k += 1

    for _ in range(n_rest):
        push(np.zeros(3), C, 0.0)
    launch_time = k * dt
    for _ in range(n_boost):
        push(np.zeros(3), C, thrust_m_s2)
    for axis, angle, dur in segments:
        for _ in range(n_gap):
            push(np.zeros(3), C, 0.0)
        n = 2 * max(1, int(round(dur * rate_hz / 2)))
        T = n * dt
        peak = 2.0 * angle / T
        ax = np.asarray(axis, float) / np.linalg.norm(axis)
        C0 = C.copy()
        for j in range(n + 1):
            t = j * dt
            ang = peak * t * t / T if t <= T / 2 else angle - peak * (T - t) ** 2 / T
            r = peak * (1.0 - abs(2.0 * t / T - 1.0))
            C = C0 @ rot_about(ax, ang)
            if j > 0:
                push(ax * r, C, 0.0)
    for _ in range(int(round(tail_s * rate_hz))):
        push(np.zeros(3), C, 0.0)
    time_s = np.array(times)
    Cs = np.array(Cs)
    u_sf = np.asarray(u_sf, float) / np.linalg.norm(u_sf)
    g_react_nf = np.array([0.0, 0.0, -G])
    accel = np.einsum("nji,j->ni", Cs, g_react_nf) + np.outer(thrust, u_sf)
    mag = np.einsum("ij,nkj,k->ni", A, Cs, e_ned) + b
    gyro = np.array(rates) + bias
    if mag_noise_gauss:
        mag = mag + rng.normal(0.0, mag_noise_gauss, mag.shape)
    if gyro_noise_rad_s:
        gyro = gyro + rng.normal(0.0, gyro_noise_rad_s, gyro.shape)
    if accel_noise_m_s2:
        accel = accel + rng.normal(0.0, accel_noise_m_s2, accel.shape)
    C_nf_isf = np.asarray(C_nf_isf, float)
    psi = math.atan2(C_nf_isf[1, 0], C_nf_isf[0, 0]) % (2 * math.pi)
    return Flight(time_s, gyro, accel, mag, Cs, launch_time, psi, C_nf_isf, u_sf, np.asarray(e_ned, float))


def launcher_attitude(az: float, elev: float, C_body_from_sensor: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """C_NF<-ISF for a body with its nose at azimuth az, elevation elev (ZYX: yaw az, pitch elev)."""
    return dcm_from_euler(roll, elev, az) @ C_body_from_sensor


MANOEUVRE = [  # a gravity turn with roll and yaw: rotations about several sensor axes
    (np.array([0.0, 1.0, 0.0]), -0.6, 2.0),
    (np.array([1.0, 0.0, 0.0]), 1.2, 2.0),
    (np.array([0.0, 0.0, 1.0]), 0.9, 2.0),
    (np.array([0.3, 1.0, -0.2]), 0.7, 2.0),
    (np.array([1.0, -0.4, 0.3]), -1.0, 2.0),
]


# --- tests of the generator itself ------------------------------------------------------------

def test_generator_gyro_integrates_to_truth():
    """GIVEN the manoeuvre, WHEN its gyro is strapped down from the launch attitude, THEN the
    closed-form attitude is reproduced to round-off (the premise of the exact-recovery tests)."""
    C0 = launcher_attitude(0.7, 0.9, rot_z(0.3) @ rot_x(0.2))
    fl = make_flight(C_nf_isf=C0, u_sf=[1, 0, 0], segments=MANOEUVRE, rest_s=0.5)
    st = strapdown_init(np.array([1.0, 0, 0, 0]))
    i0 = int(np.searchsorted(fl.time_s, fl.launch_time_s))
    worst = 0.0
    for i in range(i0, len(fl.time_s)):
        st, _ = strapdown_step(st, fl.gyro_rad_s[i], fl.time_s[i])
        C_isf_sf = dcm_from_quat(st.q_ref_from_sensor)
        C_true = fl.C_nf_isf.T @ fl.C_nf_sf[i]
        worst = max(worst, float(np.abs(C_isf_sf - C_true).max()))
    assert worst < 1e-9
    # the manoeuvre really turns the sensor (not a degenerate generator)
    assert np.abs(fl.C_nf_sf[-1] - fl.C_nf_sf[0]).max() > 0.5


def test_generator_rest_specific_force_is_gravity_reaction():
    C0 = launcher_attitude(1.0, 0.5, rot_y(0.1))
    fl = make_flight(C_nf_isf=C0, u_sf=[1, 0, 0], rest_s=0.2, boost_s=0.1)
    f_nf = C0 @ fl.accel_m_s2[0]
    np.testing.assert_allclose(f_nf, [0.0, 0.0, -G], atol=1e-12)
