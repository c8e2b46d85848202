"""Offline simulator: truth consistency, sensor models, determinism, scenarios, speed.

The checks use their own small integrators and pygeomag directly: sim/ is the truth, and these
tests are what makes it trustworthy (never estimators/)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from sim.offline import simulate
from sim.scenario import available_scenarios, load_scenario

ZERO_IMU = {k: 0.0 for k in (
    "gyro_noise_density_rad_s_rthz", "gyro_turn_on_bias_sigma_rad_s", "gyro_bias_walk_rad_s_rts",
    "gyro_scale_sigma", "gyro_misalign_sigma_rad", "accel_noise_density_m_s2_rthz",
    "accel_turn_on_bias_sigma_m_s2", "accel_bias_walk_m_s2_rts", "accel_scale_sigma",
    "accel_misalign_sigma_rad", "mag_noise_gauss")}
ZERO_MAG = {"hard_iron_gauss": [0.0, 0.0, 0.0], "soft_iron": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
            "site_distortion_ned_gauss": [0.0, 0.0, 0.0], "anomalies": []}
OMEGA_E = 7.292115e-5


# --- the tests' own rotation helpers (independent of sim.frames) -------------------------
def _qmul(p, q):
    w1, x1, y1, z1 = p
    w2, x2, y2, z2 = q
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _dcm(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _exp(v):
    a = np.linalg.norm(v)
    if a < 1e-15:
        return np.array([1.0, *(0.5 * v)])
    return np.array([math.cos(a / 2), *(math.sin(a / 2) / a * v)])


def _angle_deg(q1, q2):
    d = _qmul(np.array([q1[0], -q1[1], -q1[2], -q1[3]]), q2)
    return math.degrees(2 * math.atan2(np.linalg.norm(d[1:]), abs(d[0])))


@pytest.fixture(scope="module")
def ideal_run():
    """Inclined-rail flight, every sensor error zero, PX4 personality (float32, no RAW_IMU rounding)."""
    return simulate("inclined_rail", seed=3, duration_s=200.0, imu_rate_hz=200.0,
                    overrides={"imu": dict(ZERO_IMU, mount_euler_deg=[2.0, -3.0, 30.0]), "mag": ZERO_MAG,
                               "autopilot": {"personality": "px4"},
                               "baro": {"noise_pa": 0.0, "temperature_noise_k": 0.0},
                               "airspeed": {"noise_pa": 0.0},
                               "earth": {"model_error": False, "crustal_sigma_nt": 0.0}})


def _strapdown_worst_deg(r, t0_s: float, t1_s: float) -> float:
    """Integrate the gyro (minus the nav-frame rate, own formula) from the true sensor attitude at
    t0 to t1 with the exact exponential; return the worst attitude error against the truth."""
    tr = r.truth
    i0 = int(np.searchsorted(r.time_s, t0_s))
    i1 = int(np.searchsorted(r.time_s, t1_s))
    q = tr.q_nav_from_sensor[i0].copy()
    worst = 0.0
    dt = r.time_s[1] - r.time_s[0]
    for k in range(i0 + 1, i1 + 1):
        lat, v, h = tr.lat_rad[k], tr.vel_ned_m_s[k], tr.alt_m[k]
        rn = 6378137.0 / math.sqrt(1 - 0.00669438 * math.sin(lat) ** 2) + h
        w_in = np.array([OMEGA_E * math.cos(lat) + v[1] / rn, -v[0] / rn,
                         -OMEGA_E * math.sin(lat) - v[1] * math.tan(lat) / rn])
        w_ns = r.gyro_rad_s[k] - _dcm(q).T @ w_in
        q = _qmul(q, _exp(w_ns * dt))
        worst = max(worst, _angle_deg(q, tr.q_nav_from_sensor[k]))
    return worst


def test_strapdown_of_error_free_gyro_reproduces_truth_attitude(ideal_run):
    """GIVEN an error-free gyro (sensor frame, 30 deg yaw mount) WHEN its rate minus the nav-frame
    rate (Earth + transport, own formula) is integrated from the true attitude at 110 s through
    60 s of level flight and turns (up to 45 deg bank) THEN the attitude matches the truth to
    < 0.05 deg."""
    tr = ideal_run.truth
    sel = (tr.time_s > 110) & (tr.time_s < 170)
    assert np.any(np.abs(tr.euler_rad[sel, 0]) > math.radians(25))  # it did manoeuvre
    assert _strapdown_worst_deg(ideal_run, 110.0, 170.0) < 0.05


def test_strapdown_at_89_deg_north_includes_the_large_transport_rate():
    """At 89 deg N the transport rate vE tan(L) / R reaches ~2e-4 rad/s (> Earth rate): the gyro
    truth must carry it, or 60 s of turns would drift by ~0.5 deg."""
    r = simulate("polar_89", seed=2, duration_s=200.0,
                 overrides={"imu": ZERO_IMU, "mag": ZERO_MAG, "autopilot": {"personality": "px4"}})
    v_e = np.abs(r.truth.vel_ned_m_s[:, 1]).max()
    assert v_e * math.tan(math.radians(89.0)) / 6.4e6 > 1.5e-4
    assert _strapdown_worst_deg(r, 100.0, 160.0) < 0.05


def test_specific_force_integrates_to_the_true_velocity(ideal_run):
    """v_k = v_{k-1} + (C_nav_from_body f + g - coriolis) dt reproduces truth velocity over the
    boost and 60 s of flight to < 0.05 m/s (accelerometer output, mounting undone)."""
    r, tr = ideal_run, ideal_run.truth
    C_bs = r.site["C_body_from_sensor"]
    i0 = int(np.searchsorted(r.time_s, 59.0))
    i1 = int(np.searchsorted(r.time_s, 130.0))
    v = tr.vel_ned_m_s[i0].copy()
    dt = r.time_s[1] - r.time_s[0]
    err = 0.0
    for k in range(i0 + 1, i1 + 1):
        qm = tr.q_nav_from_body[k - 1] + tr.q_nav_from_body[k]
        f_nav = _dcm(qm) @ (C_bs @ r.accel_m_s2[k])
        lat = tr.lat_rad[k]
        w_ie = OMEGA_E * np.array([math.cos(lat), 0.0, -math.sin(lat)])
        v = v + (f_nav + np.array([0, 0, tr.gravity_m_s2[k]]) - np.cross(2 * w_ie, v)) * dt
        err = max(err, float(np.linalg.norm(v - tr.vel_ned_m_s[k])))
    assert tr.vel_ned_m_s[i1] @ tr.vel_ned_m_s[i1] > 15.0 ** 2
    assert err < 0.05


def test_error_free_magnetometer_is_igrf_rotated_by_true_attitude(ideal_run):
    """With every error zero (no WMM error draw, no crustal field), mag = C_sensor_from_nav * IGRF-14
    (ppigrf called here directly; the estimators' WMM is not the simulator's field)."""
    import datetime as dt

    import ppigrf
    r, tr = ideal_run, ideal_run.truth
    yr = r.site["decimal_year"]
    y0, y1 = dt.datetime(int(yr), 1, 1), dt.datetime(int(yr) + 1, 1, 1)
    for k in (0, 15000, 30000, 39999):
        be, bn, bu = ppigrf.igrf(math.degrees(tr.lon_rad[k]), math.degrees(tr.lat_rad[k]), tr.alt_m[k] / 1000.0,
                                 y0 + (y1 - y0) * (yr - int(yr)))
        b_ned = np.array([bn[0], be[0], -bu[0]]).ravel() / 1e5
        expect = _dcm(tr.q_nav_from_sensor[k]).T @ b_ned
        assert np.max(np.abs(r.mag_gauss[k] - expect)) < 2e-6  # float32 + field lattice interpolation


def test_at_rest_on_the_rail_accel_and_gyro_see_gravity_and_earth_rate(ideal_run):
    r, tr = ideal_run, ideal_run.truth
    el = math.radians(15.0)
    g = tr.gravity_m_s2[0]
    C_bs = r.site["C_body_from_sensor"]
    f_body = C_bs @ r.accel_m_s2[100]
    np.testing.assert_allclose(f_body, [g * math.sin(el), 0.0, -g * math.cos(el)], atol=1e-5)
    lat = tr.lat_rad[0]
    w_ned = OMEGA_E * np.array([math.cos(lat), 0.0, -math.sin(lat)])
    expect_s = _dcm(tr.q_nav_from_sensor[100]).T @ w_ned
    np.testing.assert_allclose(r.gyro_rad_s[100], expect_s, atol=1e-10)
    assert np.all(tr.phase[:100] == "rest") and tr.launch_time_s == pytest.approx(60.0)


def test_coordinated_turn_bank_matches_turn_rate(ideal_run):
    """In a steady turn, tan(bank) = V psi_dot / g (airspeed V, heading rate from the truth)."""
    tr = ideal_run.truth
    roll = tr.euler_rad[:, 0]
    idx = np.where((np.abs(roll) > math.radians(20)) & (tr.phase == "turn"))[0]
    assert idx.size > 400
    yaw = np.unwrap(tr.euler_rad[:, 2])
    dt = 0.005
    ok = 0
    for k in idx[::200]:
        psi_dot = (yaw[k + 1] - yaw[k - 1]) / (2 * dt)
        pred = math.atan(tr.airspeed_m_s[k] * psi_dot / tr.gravity_m_s2[k])
        # alpha tilts the body yaw slightly off the velocity-frame heading: allow 2.5 deg
        ok += abs(math.degrees(pred - roll[k])) < 2.5
    assert ok >= 0.9 * len(idx[::200])


def test_raw_imu_quantisation_and_configured_errors_consumer():
    """ArduPilot personality: decoded RAW_IMU is the truth plus the configured error within its
    statistics: at rest, gyro mean - truth = turn-on bias (+-3 sigma of the mean), std = noise."""
    sc = load_scenario("inclined_rail")
    bias = [0.01, -0.02, 0.005]
    r = simulate("inclined_rail", seed=11, duration_s=50.0,
                 overrides={"imu": {"gyro_bias_rad_s": bias, "gyro_scale": [0, 0, 0],
                                    "gyro_misalignment": [[0, 0, 0]] * 3, "gyro_bias_walk_rad_s_rts": 0.0}})
    assert sc["launcher"]["rest_s"] > 50
    q = r.gyro_rad_s * 1000.0
    np.testing.assert_allclose(q, np.rint(q), atol=1e-9)  # mrad/s integers
    a_mg = r.accel_m_s2 / 9.80665 * 1000.0
    np.testing.assert_allclose(a_mg, np.rint(a_mg), atol=1e-6)
    tr = r.truth
    C_sb = r.site["C_body_from_sensor"].T
    w_true = tr.omega_body_rad_s @ C_sb.T
    res = r.gyro_rad_s - w_true
    sigma = 0.005 * math.pi / 180 * math.sqrt(200.0)
    sig_total = math.sqrt(sigma ** 2 + 1e-6 / 12)  # noise + quantisation (1 mrad/s LSB)
    n = len(res)
    np.testing.assert_allclose(res.mean(0), bias, atol=4 * sig_total / math.sqrt(n))
    np.testing.assert_allclose(res.std(0), sig_total, rtol=0.05)


def test_deterministic_by_seed():
    a = simulate("vertical_launch", seed=5, duration_s=70.0)
    b = simulate("vertical_launch", seed=5, duration_s=70.0)
    c = simulate("vertical_launch", seed=6, duration_s=70.0)
    for k in ("gyro_rad_s", "accel_m_s2", "mag_gauss", "press_abs_pa", "fc_euler_rad"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert not np.array_equal(a.gyro_rad_s, c.gyro_rad_s)


def test_vertical_launch_stands_nose_up_then_pitches_over():
    r = simulate("vertical_launch", seed=0, duration_s=100.0)
    tr = r.truth
    assert math.degrees(tr.euler_rad[10, 1]) == pytest.approx(90.0, abs=1e-6)
    boost = tr.phase == "boost"
    assert boost.sum() == pytest.approx(0.5 * 200, abs=1)
    # boost acceleration along the body x axis: 80 m/s^2 + gravity along -x (nose up)
    f_x = tr.f_body_m_s2[boost, 0]
    assert np.median(f_x) == pytest.approx(80.0 + tr.gravity_m_s2[0], abs=0.05)
    later = np.searchsorted(r.time_s, 90.0)
    assert abs(math.degrees(tr.euler_rad[later, 1])) < 25.0
    # pitched over toward the launcher azimuth (135 deg), with the wind drift
    d_n, d_e = np.degrees(tr.lat_rad[later] - tr.lat_rad[0]), np.degrees(tr.lon_rad[later] - tr.lon_rad[0])
    course = math.degrees(math.atan2(d_e * math.cos(tr.lat_rad[0]), d_n)) % 360
    assert 110.0 < course < 160.0


def test_shipped_scenarios_and_polar_flight():
    assert {"inclined_rail", "vertical_launch", "runway_gnss_denied", "polar_89"} <= set(available_scenarios())
    r = simulate("polar_89", seed=1, duration_s=200.0)
    assert np.all(np.abs(np.degrees(r.truth.lat_rad) - 89.0) < 0.2)
    assert np.all(np.isfinite(r.gyro_rad_s)) and np.all(np.isfinite(r.mag_gauss))
    g = simulate("runway_gnss_denied", seed=1, duration_s=200.0)
    assert g.gnss_lost_time_s == 180.0
    assert "ground_roll" in set(g.truth.phase)


def test_gnss_loss_degrades_the_fc_attitude():
    r = simulate("runway_gnss_denied", seed=2, duration_s=500.0, imu_rate_hz=100.0)
    yaw_err = np.degrees(np.angle(np.exp(1j * (r.fc_euler_rad[:, 2] - np.interp(
        r.fc_time_s, r.truth.time_s, np.unwrap(r.truth.euler_rad[:, 2]))))))
    before = np.abs(yaw_err[r.fc_time_s < 170]).max()
    after = np.abs(yaw_err[r.fc_time_s > 450]).min()
    assert before < 5.0 and after > 10.0  # 0.05 deg/s for 270 s = 13.5 deg drift


def test_overrides_validate_with_clear_errors():
    with pytest.raises(ValueError, match="launcher.type"):
        load_scenario("inclined_rail", {"launcher": {"type": "trebuchet"}})
    with pytest.raises(ValueError, match="unknown key"):
        load_scenario("inclined_rail", {"mag": {"hard_iron": [0, 0, 0]}})
    with pytest.raises(ValueError, match="lat_deg"):
        load_scenario({"scenario": {"duration_s": 10.0}})
    with pytest.raises(ValueError, match="imu_grade"):
        simulate("inclined_rail", imu_grade="navigation", duration_s=1.0)


def test_ten_minute_flight_at_200_hz_is_fast():
    t0 = time.process_time()
    r = simulate("inclined_rail", seed=0, imu_rate_hz=200.0, duration_s=600.0)
    cpu = time.process_time() - t0
    assert len(r.time_s) == 120000
    assert cpu < 6.0


def test_chunked_generation_equals_one_run(monkeypatch):
    """The engine carries its state across chunks (truth differencing, bias walks, gusts, FC
    error): 0.37 s chunks (the live autopilot uses 0.1 s) give the same flight as 20 s chunks. The
    field model is evaluated per chunk on a 1 s grid, so the magnetometer may differ by < 1 nT."""
    import sim.offline as off
    over = {"autopilot": {"personality": "px4"}, "wind": {"gust_sigma_m_s": 1.0}}
    a = off.simulate("inclined_rail", seed=9, duration_s=75.0, overrides=over)
    monkeypatch.setattr(off, "CHUNK_S", 0.37)
    b = off.simulate("inclined_rail", seed=9, duration_s=75.0, overrides=over)
    for k in ("gyro_rad_s", "accel_m_s2", "press_abs_pa", "press_diff_pa", "fc_euler_rad"):
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=0, atol=1e-5, err_msg=k)
    np.testing.assert_allclose(a.truth.q_nav_from_body, b.truth.q_nav_from_body, atol=1e-12)
    np.testing.assert_allclose(a.mag_gauss, b.mag_gauss, atol=1e-5)
    assert np.abs(a.truth.f_body_m_s2).max() > 30.0  # the boost is inside
