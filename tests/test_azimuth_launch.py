"""Flight direction u_SF for the three launch cases and the launch detector (METHODS.md A step 3)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.azimuth_fit import angle_between
from estimators.launch_direction import (BoostParams, LaunchDetectState, boost_direction, boost_init,
                                         boost_step, elevation_rad, launch_detect_step, u_aligned, u_vertical)
from estimators.rotations import rot_x, rot_y, rot_z
from test_azimuth_synth import G, launcher_attitude, rot_about

C_BS = rot_z(-1.0) @ rot_y(0.4) @ rot_x(-0.7)


def test_vertical_case_direction_is_up_from_gravity():
    """Eq. 2.1: nose straight up, any mount: u = f_rest/|f_rest| is the nose in SF."""
    C_nf_sf = launcher_attitude(0.3, math.pi / 2, C_BS)
    f_rest = C_nf_sf.T @ np.array([0.0, 0.0, -G])
    np.testing.assert_allclose(u_vertical(f_rest), C_BS[0], atol=1e-12)
    assert abs(elevation_rad(C_BS[0], f_rest) - math.pi / 2) < 1e-7


def test_aligned_case_direction_is_the_configured_body_x():
    """Eq. 2.3: u = C_SF<-body [1,0,0]."""
    np.testing.assert_allclose(u_aligned(C_BS), C_BS.T @ np.array([1.0, 0.0, 0.0]), atol=1e-15)
    np.testing.assert_allclose(u_aligned(np.eye(3)), [1.0, 0.0, 0.0])


@pytest.mark.parametrize("elev_deg", [30.0, 60.0, 85.0])
def test_inclined_case_removes_gravity_while_the_sensor_turns(elev_deg):
    """Eq. 2.2 improved: a = f - C_SF<-ISF f_rest; the sensor rolls about the nose during boost
    (a spinning rocket), which would smear gravity into a/|a| without the rotation."""
    C_nf_isf = launcher_attitude(2.0, math.radians(elev_deg), C_BS)
    f_rest = C_nf_isf.T @ np.array([0.0, 0.0, -G])
    u = C_BS[0]
    st = boost_init(f_rest, 0.0)
    thrust = 25.0
    for k in range(100):
        t = k * 0.01
        C_isf_sf = rot_about(u, 3.0 * t)               # roll about the nose
        C_nf_sf = C_nf_isf @ C_isf_sf
        f = C_nf_sf.T @ (thrust * (C_nf_isf @ u) + np.array([0.0, 0.0, -G]))
        st = boost_step(st, f, C_isf_sf.T, t)
    u_est, why = boost_direction(st)
    assert why == ""
    assert angle_between(u_est, u) < 1e-12
    # without removing gravity (the seed's plain eq. 2.2) the direction is off by > 1 deg
    naive = f / np.linalg.norm(f)
    assert math.degrees(angle_between(naive, u)) > 1.0
    assert abs(elevation_rad(u_est, f_rest) - math.radians(elev_deg)) < 1e-7


def test_boost_window_closes_and_too_few_samples_are_reported():
    f_rest = np.array([0.0, 0.0, -G])
    st = boost_init(f_rest, 10.0)
    p = BoostParams(window_s=0.5, min_samples=10)
    for k in range(3):
        st = boost_step(st, f_rest + np.array([20.0, 0, 0]), np.eye(3), 10.0 + 0.01 * k, p)
    st = boost_step(st, f_rest + np.array([20.0, 0, 0]), np.eye(3), 10.6, p)
    assert st.done
    u, why = boost_direction(st, p)
    assert u is None and why.startswith("3 of 10 boost samples")


def test_launch_detector_reports_the_start_of_motion():
    st = LaunchDetectState(f_rest_norm_m_s2=G)
    f_rest = np.array([0.0, 0.0, -G])
    t = 0.0
    for _ in range(100):                         # at rest with a little vibration
        st = launch_detect_step(st, f_rest + np.array([0.2, -0.1, 0.0]), t)
        t += 0.01
    assert st.launch_time_s is None
    t_quiet = t - 0.01
    for k in range(30):                          # thrust ramps up over 50 ms, then stays
        st = launch_detect_step(st, f_rest + np.array([min(1.0, (k + 1) / 5) * 40.0, 0, 0]), t)
        t += 0.01
    assert st.launch_time_s is not None
    assert abs(st.launch_time_s - t_quiet) < 1e-12


def test_launch_detector_ignores_a_short_knock():
    st = LaunchDetectState(f_rest_norm_m_s2=G)
    f_rest = np.array([0.0, 0.0, -G])
    for k in range(50):
        knock = np.array([30.0, 0, 0]) if k in (20, 21) else np.zeros(3)
        st = launch_detect_step(st, f_rest + knock, k * 0.01)
    assert st.launch_time_s is None


def test_inclined_direction_ignores_the_pull_up_after_the_thrust():
    """After the thrust ends the airframe pulls up (centripetal acceleration normal to the nose,
    8 m/s^2): the direction is taken from the thrust phase only, so it stays on the nose."""
    C_nf_isf = launcher_attitude(1.0, math.radians(20.0), C_BS)
    f_rest = C_nf_isf.T @ np.array([0.0, 0.0, -G])
    u = C_BS[0]
    normal = np.cross(u, C_BS[1])                   # a direction normal to the nose
    st = boost_init(f_rest, 0.0)
    for k in range(100):
        t = k * 0.01
        a_sf = 60.0 * u if t < 0.4 else -2.0 * u + 8.0 * normal   # thrust, then drag + pull-up
        f = a_sf + f_rest
        st = boost_step(st, f, np.eye(3), t)
    assert st.done
    u_est, why = boost_direction(st)
    assert why == "" and angle_between(u_est, u) < 1e-12
