"""The simulator's Earth is not the estimators' model (sim/earth.py, DESIGN.md "Tests and
measurements"): IGRF-14 + the WMM-2025 error budget drawn per seed + a crustal field, and a
non-standard atmosphere. The references here are ppigrf and pygeomag called directly, and the
hydrostatic formulas written out independently."""
from __future__ import annotations

import datetime as dt
import math

import numpy as np
import ppigrf
import pytest
from pygeomag import GeoMag

from sim import earth
from sim.offline import simulate
from sim.scenario import load_scenario

ZURICH = (47.3769, 8.5417, 410.0)
YEAR = 2026.89
NO_MAG_ERRORS = {"hard_iron_gauss": [0.0, 0.0, 0.0], "soft_iron": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                 "site_distortion_ned_gauss": [0.0, 0.0, 0.0], "anomalies": []}


def _igrf_direct_nt(lat, lon, alt_m, year=YEAR):
    y0, y1 = dt.datetime(int(year), 1, 1), dt.datetime(int(year) + 1, 1, 1)
    d = y0 + (y1 - y0) * (year - int(year))
    be, bn, bu = ppigrf.igrf(np.atleast_1d(lon), np.atleast_1d(lat), np.atleast_1d(alt_m) / 1000.0, d)
    return np.array([bn[0], be[0], -bu[0]]).T  # (n, 3)


def _wmm_nt(lat, lon, alt_m, year=YEAR):
    r = GeoMag().calculate(glat=lat, glon=lon, alt=alt_m / 1000.0, time=year)
    return np.array([r.x, r.y, r.z]), r


def _earth(seed, **over):
    sc = load_scenario("inclined_rail", over)
    return earth.SimEarth(sc, np.random.default_rng(seed)), sc


def test_main_field_is_igrf14_to_a_hundredth_of_a_nanotesla():
    """GIVEN points spread over 20 km and 0-3 km altitude around Zurich and near 89 N
    WHEN the lattice-interpolated main field is evaluated
    THEN it equals ppigrf's IGRF-14 at each point within 0.01 nT."""
    rng = np.random.default_rng(1)
    mf = earth.MainField(YEAR)
    for lat0, lon0 in ((47.3769, 8.5417), (89.0, 30.0)):
        lat = lat0 + rng.uniform(-0.1, 0.1, 50)
        lon = lon0 + rng.uniform(-0.1, 0.1, 50) / max(math.cos(math.radians(lat0)), 0.05)
        alt = rng.uniform(0.0, 3000.0, 50)
        got = mf.ned_nt(lat, lon, alt)
        want = _igrf_direct_nt(lat, lon, alt)
        assert np.max(np.abs(got - want)) < 0.01


def test_igrf_differs_from_the_estimators_wmm_by_a_main_field_model_difference():
    """IGRF-14 and WMM-2025 are two fits of the same main field: they differ, by tens of nT."""
    igrf = _igrf_direct_nt(*ZURICH)[0]
    wmm, _ = _wmm_nt(*ZURICH)
    diff = float(np.linalg.norm(igrf - wmm))
    assert 1.0 < diff < 100.0, diff


def test_model_error_draws_carry_the_wmm2025_report_sigmas():
    """GIVEN 4000 draws of the error budget at Zurich (no crustal field)
    THEN H (along the horizontal field), D and Z errors have the report's 1-sigma within 5 %
    (4000 draws: the sample sigma's own 1-sigma is 1.1 %) and a zero mean."""
    main = _igrf_direct_nt(*ZURICH)[0]
    h = math.hypot(main[0], main[1])
    rng = np.random.default_rng(7)
    err = np.array([earth.draw_model_error_ned_nt(main, rng) for _ in range(4000)])
    b = main + err
    dec_err_deg = np.degrees(np.arctan2(b[:, 1], b[:, 0]) - math.atan2(main[1], main[0]))
    h_err = np.hypot(b[:, 0], b[:, 1]) - h
    sigma_d = math.hypot(0.26, 5417.0 / h)
    assert np.std(dec_err_deg) == pytest.approx(sigma_d, rel=0.05)
    assert np.std(h_err) == pytest.approx(133.0, rel=0.05)
    assert np.std(err[:, 2]) == pytest.approx(141.0, rel=0.05)
    assert abs(np.mean(dec_err_deg)) < 4 * sigma_d / math.sqrt(4000)
    # near the pole the horizontal field is weak and the declination error is degrees
    assert math.hypot(0.26, 5417.0 / 1500.0) > 3.0


def test_sim_field_differs_from_wmm_by_a_plausible_amount_per_seed():
    """GIVEN the default [earth] (model error on, 50 nT crustal field) at Zurich
    WHEN 40 seeds are drawn
    THEN the field at the launcher differs from the estimators' WMM in every seed, the declination
    difference has the WMM-2025 sigma within 30 % (40 draws), and none is beyond 4.5 sigma."""
    wmm, r = _wmm_nt(*ZURICH)
    wmm_dec = math.degrees(math.atan2(wmm[1], wmm[0]))
    sigma_d = r.calculate_uncertainty().d
    sc = load_scenario("inclined_rail")
    lat0, lon0, alt0 = (math.radians(ZURICH[0]), math.radians(ZURICH[1]), ZURICH[2])
    dec = []
    for seed in range(40):
        e = earth.SimEarth(sc, np.random.default_rng(seed))
        _, total = e.field_ned_gauss([lat0], [lon0], [alt0])
        b = total[0] * earth.NT_PER_GAUSS
        assert np.linalg.norm(b - wmm) > 5.0
        dec.append(math.degrees(math.atan2(b[1], b[0])) - wmm_dec)
    dec = np.array(dec)
    assert np.std(dec) == pytest.approx(sigma_d, rel=0.3), (np.std(dec), sigma_d)
    assert np.max(np.abs(dec)) < 4.5 * sigma_d


def test_without_model_error_and_crust_the_sim_field_is_igrf():
    e, sc = _earth(3, earth={"model_error": False, "crustal_sigma_nt": 0.0})
    lat, lon, alt = 47.38, 8.55, 600.0
    main, total = e.field_ned_gauss([math.radians(lat)], [math.radians(lon)], [alt])
    want = _igrf_direct_nt(lat, lon, alt, year=sc["scenario"]["decimal_year"])[0]
    np.testing.assert_allclose(total[0] * 1e5, want, atol=0.01)
    np.testing.assert_array_equal(main, total)


def test_crustal_field_is_a_potential_field_with_the_stated_amplitude():
    """B = -grad V of a harmonic V: curl-free and divergence-free (finite differences, 1 m), and
    the vertical component's RMS over a 40 km x 40 km area at ground is sigma within 15 % (10 seeds)."""
    sigma, length = 80.0, 1500.0
    rms = []
    for seed in range(10):
        c = earth.CrustalField(sigma, length, np.random.default_rng(seed))
        p = np.random.default_rng(100 + seed).uniform(-20000, 20000, (2000, 3))
        p[:, 2] = 0.0
        rms.append(np.sqrt(np.mean(c.ned_nt(p)[:, 2] ** 2)))
    assert np.mean(rms) == pytest.approx(sigma, rel=0.15)
    c = earth.CrustalField(sigma, length, np.random.default_rng(0))
    x = np.array([[300.0, -700.0, -150.0]])
    step = 1.0
    jac = np.stack([(c.ned_nt(x + step * ax) - c.ned_nt(x - step * ax))[0] / (2 * step)
                    for ax in np.eye(3)], -1)  # jac[i, j] = dB_i / dx_j
    scale = sigma / length
    assert abs(np.trace(jac)) < 1e-4 * scale
    assert np.max(np.abs(jac - jac.T)) < 1e-4 * scale
    # it decays with height: 3 correlation lengths up it is nearly gone
    hi = c.ned_nt(np.column_stack([p[:, :2], np.full(len(p), -3 * length)]))
    assert np.sqrt(np.mean(hi[:, 2] ** 2)) < 0.1 * sigma


def test_atmosphere_is_the_configured_non_standard_one():
    """GIVEN QNH 998 hPa, ISA +12 K, lapse 5.5 K/km
    THEN sea-level pressure is the QNH, and at 1500 m pressure, temperature and density follow
    the hydrostatic dry-air column (written out here) and differ from ISA by what was configured."""
    e, _ = _earth(0, atmosphere={"qnh_hpa": 998.0, "isa_deviation_k": 12.0, "lapse_rate_k_km": 5.5})
    atm = e.atmosphere
    assert float(atm.pressure_pa(0.0)) == pytest.approx(99800.0, abs=1e-6)
    h = 1500.0
    t_s = 288.15 + 12.0
    t_h = t_s - 0.0055 * h
    p_h = 99800.0 * (t_h / t_s) ** (9.80665 / (287.05287 * 0.0055))
    assert float(atm.temperature_k(h)) == pytest.approx(t_h, abs=1e-9)
    assert float(atm.pressure_pa(h)) == pytest.approx(p_h, rel=1e-12)
    assert float(atm.density_kg_m3(h)) == pytest.approx(p_h / (287.05287 * t_h), rel=1e-12)
    isa_p = 101325.0 * ((288.15 - 0.0065 * h) / 288.15) ** (9.80665 / (287.05287 * 0.0065))
    assert float(atm.temperature_k(h)) - (288.15 - 0.0065 * h) == pytest.approx(12.0 + 1.5, abs=1e-9)
    assert isa_p - float(atm.pressure_pa(h)) > 600.0  # 15.3 hPa below ISA at sea level, 6.2 hPa at 1500 m


def test_atmosphere_is_drawn_per_seed_and_reproducible():
    a = [_earth(s)[0].atmosphere for s in (0, 1, 0)]
    assert a[0].qnh_pa == a[2].qnh_pa and a[0].isa_deviation_k == a[2].isa_deviation_k
    assert a[0].qnh_pa != a[1].qnh_pa and a[0].lapse_rate_k_m != a[1].lapse_rate_k_m
    for x in a:
        assert 4.0e-3 <= x.lapse_rate_k_m <= 9.8e-3


def test_setting_one_key_leaves_the_other_draws_unchanged():
    e1, _ = _earth(5)
    e2, _ = _earth(5, atmosphere={"qnh_hpa": 1020.0}, earth={"model_error": False})
    assert e2.atmosphere.qnh_pa == 102000.0 and e1.atmosphere.qnh_pa != 102000.0
    assert e1.atmosphere.isa_deviation_k == e2.atmosphere.isa_deviation_k
    np.testing.assert_array_equal(e1.crust.k, e2.crust.k)
    assert np.all(e2.model_error_ned_nt == 0.0) and np.any(e1.model_error_ned_nt != 0.0)


def test_flown_barometer_and_magnetometer_come_from_the_sim_earth():
    """GIVEN an error-free magnetometer and barometer on the rail (seed 2)
    THEN the static pressure is the drawn atmosphere's (not ISA) and the magnetometer's field is
    the sim Earth's at the launcher, which is not the WMM."""
    over = {"mag": NO_MAG_ERRORS, "imu": {"mag_noise_gauss": 0.0}, "autopilot": {"personality": "px4"},
            "baro": {"noise_pa": 0.0, "bias_pa": 0.0},
            "atmosphere": {"qnh_hpa": 1030.0, "isa_deviation_k": -8.0, "lapse_rate_k_km": 7.0}}
    r = simulate("inclined_rail", seed=2, duration_s=5.0, overrides=over)
    e, _ = _earth(0, atmosphere=over["atmosphere"])
    assert r.press_abs_pa[0] == pytest.approx(float(e.atmosphere.pressure_pa(410.0)), abs=1.0)
    assert r.press_abs_pa[0] - 101325.0 * (1 - 0.0065 * 410.0 / 288.15) ** 5.2559 > 1000.0
    b = r.truth.field_ned_gauss[0] * 1e5
    wmm, _ = _wmm_nt(*ZURICH, year=r.site["decimal_year"])
    assert np.linalg.norm(b - wmm) > 5.0
    np.testing.assert_allclose(r.truth.main_field_ned_gauss[0] * 1e5,
                               _igrf_direct_nt(*ZURICH, year=r.site["decimal_year"])[0], atol=0.05)


def test_bad_earth_keys_are_one_line_errors():
    for over, key in (({"earth": {"model_error": "yes"}}, "earth.model_error"),
                      ({"earth": {"crustal_sigma_nt": -1.0}}, "earth.crustal_sigma_nt"),
                      ({"atmosphere": {"qnh_hpa": 500.0}}, "atmosphere.qnh_hpa"),
                      ({"atmosphere": {"lapse_rate_k_km": 20.0}}, "atmosphere.lapse_rate_k_km"),
                      ({"scenario": {"date": 2040.0}}, "IGRF")):
        with pytest.raises(ValueError, match=key.replace(".", r"\.")):
            sc = load_scenario("inclined_rail", over)
            earth.SimEarth(sc, np.random.default_rng(0))
