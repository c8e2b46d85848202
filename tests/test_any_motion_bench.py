"""bench/any_motion.py: the error metric on known rotations and the peers' frame conversions."""
from __future__ import annotations

import math
import pathlib
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "bench"))
import any_motion as am  # noqa: E402

D = math.radians


def q_from_scipy(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat()
    return np.array([w, x, y, z])


def q_euler(roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """q_nav_from_body for ZYX Euler angles (NED/FRD)."""
    return q_from_scipy(Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True))


def test_pure_heading_error_is_all_heading():
    # GIVEN a true attitude (banked, pitched) and an estimate turned 10 deg about the vertical
    q_true = q_euler(20.0, -35.0, 30.0)
    q_est = am.qmul(am.qz(D(10.0)), q_true)
    # WHEN scored THEN the heading error is +10 deg, no inclination, total 10 deg
    h, i, t = am.attitude_errors_rad(q_true[None], q_est[None])
    assert math.degrees(h[0]) == pytest.approx(10.0, abs=1e-9)
    assert math.degrees(i[0]) == pytest.approx(0.0, abs=1e-6)
    assert math.degrees(t[0]) == pytest.approx(10.0, abs=1e-9)


def test_pure_tilt_error_is_all_inclination():
    # GIVEN level flight heading 30 deg and an estimate with 5 deg too much roll
    q_true = q_euler(0.0, 0.0, 30.0)
    q_est = q_euler(5.0, 0.0, 30.0)
    h, i, t = am.attitude_errors_rad(q_true[None], q_est[None])
    assert math.degrees(h[0]) == pytest.approx(0.0, abs=1e-9)
    assert math.degrees(i[0]) == pytest.approx(5.0, abs=1e-9)
    assert math.degrees(t[0]) == pytest.approx(5.0, abs=1e-9)


def test_composition_splits_into_heading_and_tilt():
    # GIVEN an estimate = a 7 deg tilt about a horizontal nav axis after a -12 deg heading error
    rng = np.random.default_rng(3)
    q_true = q_from_scipy(Rotation.random(random_state=11))
    axis = np.array([math.cos(0.7), math.sin(0.7), 0.0])
    q_tilt = q_from_scipy(Rotation.from_rotvec(axis * D(7.0)))
    q_est = am.qmul(q_tilt, am.qmul(am.qz(D(-12.0)), q_true))
    h, i, t = am.attitude_errors_rad(q_true[None], q_est[None])
    assert math.degrees(h[0]) == pytest.approx(-12.0, abs=1e-9)
    assert math.degrees(i[0]) == pytest.approx(7.0, abs=1e-9)
    # total: the product of two rotations with perpendicular axes, cos(t/2) = cos(h/2) cos(i/2)
    assert math.cos(t[0] / 2) == pytest.approx(math.cos(D(6.0)) * math.cos(D(3.5)), abs=1e-12)
    # and on random pairs: inclination = angle between the vertical seen in either body frame
    qa = np.array([q_from_scipy(Rotation.random(random_state=s)) for s in range(50)])
    qb = am.qmul(np.array([q_from_scipy(Rotation.from_rotvec(rng.normal(0, 0.5, 3))) for _ in range(50)]), qa)
    _, inc, tot = am.attitude_errors_rad(qa, qb)

    def down_in_body(q):
        return np.array([Rotation.from_quat([*x[1:], x[0]]).inv().apply([0, 0, 1.0]) for x in q])
    ref = np.arccos(np.clip(np.sum(down_in_body(qa) * down_in_body(qb), axis=1), -1, 1))
    np.testing.assert_allclose(inc, ref, atol=1e-7)
    assert np.all(inc <= tot + 1e-12)


def test_peer_frames_identity_maps_to_identity():
    # GIVEN a body level facing north (NED from FRD = identity): in ENU from FLU that is qz(+90 deg),
    # in NWU from FLU the identity
    q_enu = am.qz(D(90.0))
    q_nwu = np.array([1.0, 0.0, 0.0, 0.0])
    for q in (am.q_ned_frd_from_enu_flu(q_enu), am.q_ned_frd_from_nwu_flu(q_nwu)):
        _, _, t = am.attitude_errors_rad(np.array([[1.0, 0, 0, 0]]), q[None])
        assert t[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("peer", ["vqf", "fusion"])
def test_peer_static_attitude_converted_to_ned_frd(peer, monkeypatch):
    # GIVEN an IMU at rest at roll -30, pitch 20, yaw 120 deg (NED/FRD), field 0.2 G north 0.4 G down
    pytest.importorskip(am.PEER_PACKAGES[peer])
    q_true = q_euler(-30.0, 20.0, 120.0)
    C_nb = Rotation.from_quat([*q_true[1:], q_true[0]]).as_matrix()
    f_body = C_nb.T @ np.array([0.0, 0.0, -9.80665])
    m_body = C_nb.T @ np.array([0.2, 0.0, 0.4])

    class Run:  # the fields the runners read (30 s at 100 Hz)
        n = 3000
        gyro_rad_s = np.zeros((n, 3))
        accel_m_s2 = np.tile(f_body, (n, 1))
        mag_gauss = np.tile(m_body, (n, 1))
    monkeypatch.setattr(am, "_declination_rad", lambda run: 0.0)  # the field above is magnetic north
    q = am.RUNNERS[peer](Run)["q"]
    # WHEN converted THEN the final estimate is the true attitude (within 0.5 deg, every axis)
    h, i, t = am.attitude_errors_rad(q_true[None], q[-1][None])
    assert math.degrees(t[0]) < 0.5, (math.degrees(h[0]), math.degrees(i[0]))


def test_rig_segments_and_magnet_disturbances_in_the_simulator():
    from sim.offline import simulate
    # GIVEN a rig scenario: rest, a half roll (upside down) then a pitch to +90, and a magnet
    # attached from 3 s, a magnet nearby for [4, 5) s
    sc = {"scenario": {"duration_s": 8.0}, "site": {"lat_deg": 10.0, "lon_deg": 20.0},
          "launcher": {"type": "rig", "azimuth_deg": 45.0, "rest_s": 1.0},
          "motion": {"segments": [{"duration_s": 2.0, "by_deg": [180.0, 0.0, 0.0]},
                                  {"duration_s": 2.0, "by_deg": [-180.0, 90.0, 0.0]}]},
          "mag": {"disturbances": [{"start_s": 3.0, "hard_iron_gauss": [0.3, 0.0, 0.0]},
                                   {"start_s": 4.0, "end_s": 5.0, "field_ned_gauss": [0.0, 0.5, 0.0]}]}}
    r = simulate(sc, seed=0, imu_rate_hz=100.0)
    t, tr = r.truth.time_s, r.truth
    at = {s: int(np.searchsorted(t, s)) for s in (0.5, 2.0, 3.0, 6.0)}
    # THEN: level facing 45 deg at rest, upside down at the half roll's end, pitch +90 after both
    _, _, e0 = am.attitude_errors_rad(tr.q_nav_from_body[at[0.5]][None], q_euler(0, 0, 45.0)[None])
    _, _, e1 = am.attitude_errors_rad(tr.q_nav_from_body[at[3.0]][None], q_euler(180.0, 0, 45.0)[None])
    _, _, e2 = am.attitude_errors_rad(tr.q_nav_from_body[at[6.0]][None], q_euler(0, 90.0, 45.0)[None])
    assert max(e0[0], e1[0], e2[0]) < 1e-6
    # the gyro sees the half roll: peak rate pi * 180 / (2 * 2) deg/s about body x
    assert math.degrees(np.max(np.abs(tr.omega_nb_body_rad_s[:, 0]))) == pytest.approx(141.4, abs=0.5)
    # the truth field carries the nearby magnet only inside its window
    dB = tr.field_ned_gauss[:, 1] - tr.field_ned_gauss[0, 1]
    inside = (t >= 4.0) & (t < 5.0)
    assert np.allclose(dB[inside], 0.5, atol=1e-6) and np.allclose(dB[~inside], 0.0, atol=1e-6)
    # the attached magnet shifts the reading by its hard iron from 3 s (sensor frame), noise 3 mG
    still = (t > 6.0) & (t < 8.0)
    m_before = simulate({**sc, "mag": {"disturbances": []}}, seed=0, imu_rate_hz=100.0).mag_gauss
    shift = (r.mag_gauss - m_before)[still].mean(axis=0)
    np.testing.assert_allclose(shift, [0.3, 0.0, 0.0], atol=1e-3)
    # a translation segment: the IMU moves by move_m, its accelerometer feels pi^2 d / (2 T^2) at the peak
    mv = {**sc, "motion": {"segments": [{"duration_s": 0.5, "by_deg": [0.0, 0.0, 0.0], "move_m": [0.2, 0.0, 0.0]}]}}
    rm = simulate(mv, seed=0, imu_rate_hz=100.0)
    assert rm.truth.vel_ned_m_s[:, 0].sum() * 0.01 == pytest.approx(0.2, abs=2e-3)
    assert np.max(np.hypot(*rm.truth.f_body_m_s2[:, :2].T)) == pytest.approx(math.pi ** 2 * 0.2 / (2 * 0.25), rel=0.01)
    # and a bad entry is refused with a named error
    with pytest.raises(ValueError, match=r"mag.disturbances\[0\]"):
        simulate({**sc, "mag": {"disturbances": [{"start_s": 1.0}]}}, seed=0)


def test_scenarios_option_rejects_an_unknown_name_and_lists_the_known(capsys):
    with pytest.raises(SystemExit) as e:
        am.main(["--scenarios", "magnet_nearby,nope"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "unknown ['nope']" in err and "magnet_nearby" in err and "hover_spin" in err
