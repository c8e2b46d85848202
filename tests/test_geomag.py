"""The WMM wrapper: units, frames, declination, validation (METHODS.md A step 1)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pygeomag import GeoMag

from estimators.geomag import declination_rad, earth_field, earth_field_ned_gauss, field_from_vector


def test_field_is_pygeomag_in_gauss_with_altitude_in_km():
    lat, lon, alt_m, year = 48.1, 11.6, 1500.0, 2026.5
    ref = GeoMag().calculate(glat=lat, glon=lon, alt=alt_m / 1000.0, time=year)
    e = earth_field_ned_gauss(lat, lon, alt_m, year)
    np.testing.assert_allclose(e, np.array([ref.x, ref.y, ref.z]) * 1e-5, rtol=0, atol=1e-12)
    # altitude really is converted: 1500 m differs from 1500 km
    far = GeoMag().calculate(glat=lat, glon=lon, alt=alt_m, time=year)
    assert abs(far.f - ref.f) > 1000.0


def test_declination_and_inclination_follow_from_the_vector():
    f = earth_field(-33.9, 18.4, 0.0, 2027.0)       # Cape Town: declination strongly west
    e = f.e_ned_gauss
    assert abs(f.declination_rad - math.atan2(e[1], e[0])) < 1e-15
    ref = GeoMag().calculate(glat=-33.9, glon=18.4, alt=0.0, time=2027.0)
    assert abs(math.degrees(f.declination_rad) - ref.d) < 1e-9
    assert abs(math.degrees(f.inclination_rad) - ref.i) < 1e-9
    assert f.declination_rad < math.radians(-20.0) and f.inclination_rad < 0.0  # southern hemisphere
    assert 0.0 < f.declination_sigma_rad < math.radians(2.0)
    assert f.model == "WMM-2025"
    assert declination_rad(-33.9, 18.4, 0.0, 2027.0) == f.declination_rad


def test_field_magnitude_is_an_earth_field():
    for lat in (-60.0, 0.0, 45.0, 70.0):
        n = float(np.linalg.norm(earth_field_ned_gauss(lat, 20.0, 0.0, 2026.0)))
        assert 0.2 < n < 0.7


@pytest.mark.parametrize("args,match", [
    ((91.0, 0.0, 0.0, 2026.0), "lat_deg"),
    ((0.0, 400.0, 0.0, 2026.0), "lon_deg"),
    ((0.0, 0.0, -5000.0, 2026.0), "alt_m"),
    ((0.0, 0.0, 0.0, float("nan")), "decimal_year"),
    ((0.0, 0.0, 0.0, 2019.0), "decimal_year"),
])
def test_inputs_are_validated(args, match):
    with pytest.raises(ValueError, match=match):
        earth_field(*args)


def test_configured_field_vector():
    f = field_from_vector(np.array([0.2, -0.02, 0.4]))
    assert f.model == "configured" and abs(f.declination_rad - math.atan2(-0.02, 0.2)) < 1e-15
    with pytest.raises(ValueError, match="horizontal"):
        field_from_vector(np.array([0.0, 0.0, 0.5]))
    with pytest.raises(ValueError, match="Earth field"):
        field_from_vector(np.array([20000.0, 0.0, 40000.0]))   # nT passed by mistake
