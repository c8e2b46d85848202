"""Earth magnetic field for the flight area from the World Magnetic Model (METHODS.md A step 1).

Wraps pygeomag (>= 1.1; its default coefficients are WMM-2025, valid 2025.0 - 2030.0).

    e_NF = [X, Y, Z] = [north, east, down] field, converted nT -> gauss (1 G = 1e5 nT)
    declination delta = atan2(e_E, e_N)          (east positive, as WMM reports it)
    inclination       = atan2(e_D, hypot(e_N, e_E))  (positive down)

Units at this boundary: latitude/longitude in degrees (geodetic, WGS-84), altitude in metres
above the WGS-84 ellipsoid (pygeomag wants km: converted here), decimal year (e.g. 2026.5).
Out-of-range or non-finite inputs raise ``ValueError`` naming the argument.

The field is assumed constant over one flight (method A assumes a flight area of a few tens of
km); the WMM's own 1-sigma declination uncertainty (~0.3-0.5 deg away from the poles) is
returned so an estimator can add it to its heading uncertainty when it wants the absolute
(model-referenced) error rather than the error relative to the model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

NT_PER_GAUSS = 1.0e5
"""1 gauss = 1e5 nT (WMM reports nT)."""
WMM_MIN_ALT_M = -1_000.0
"""WMM validity: from 1 km below the ellipsoid ..."""
WMM_MAX_ALT_M = 850_000.0
"""... to 850 km above it."""


@dataclass(frozen=True)
class EarthField:
    """The geomagnetic reference at one place and date."""
    e_ned_gauss: np.ndarray
    """Field vector [north, east, down] in gauss, shape (3,)."""
    declination_rad: float
    """Angle from true north to the horizontal field, east positive."""
    inclination_rad: float
    """Dip angle, positive when the field points down (northern hemisphere)."""
    declination_sigma_rad: float
    """WMM error model 1-sigma of the declination (nan when the model gives none)."""
    model: str
    """Coefficient set used, e.g. 'WMM-2025'."""


@lru_cache(maxsize=1)
def _geomag():
    from pygeomag import GeoMag  # import here: loading the coefficients costs ~50 ms once
    return GeoMag()


def _validate(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float) -> None:
    for name, v in (("lat_deg", lat_deg), ("lon_deg", lon_deg), ("alt_m", alt_m),
                    ("decimal_year", decimal_year)):
        if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
            raise ValueError(f"{name} must be a finite number, got {v!r}")
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"lat_deg must be in [-90, 90], got {lat_deg}")
    if not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"lon_deg must be in [-180, 360], got {lon_deg}")
    if not WMM_MIN_ALT_M <= alt_m <= WMM_MAX_ALT_M:
        raise ValueError(f"alt_m must be in [{WMM_MIN_ALT_M:.0f}, {WMM_MAX_ALT_M:.0f}] m, got {alt_m}")


def earth_field(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float) -> EarthField:
    """WMM field at a geodetic position (deg, deg, m above WGS-84) and decimal year."""
    _validate(lat_deg, lon_deg, alt_m, decimal_year)
    gm = _geomag()
    try:
        # pygeomag: alt in km; refuses dates outside the coefficient set's 5-year life
        r = gm.calculate(glat=float(lat_deg), glon=float(lon_deg), alt=float(alt_m) / 1000.0,
                         time=float(decimal_year), allow_date_outside_lifespan=False)
    except Exception as exc:  # pygeomag raises a bare Exception for dates out of life
        raise ValueError(f"decimal_year {decimal_year} rejected by the field model: {exc}") from exc
    e = np.array([r.x, r.y, r.z], dtype=float) / NT_PER_GAUSS
    try:
        dec_sigma = math.radians(float(r.calculate_uncertainty().d))
    except Exception:  # no error model for this epoch
        dec_sigma = math.nan
    return EarthField(
        e_ned_gauss=e,
        declination_rad=math.atan2(e[1], e[0]),
        inclination_rad=math.atan2(e[2], math.hypot(e[0], e[1])),
        declination_sigma_rad=dec_sigma,
        model=str(getattr(gm, "_model", None) or "WMM"),
    )


def earth_field_ned_gauss(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float) -> np.ndarray:
    """Field vector [N, E, D] in gauss (see ``earth_field``)."""
    return earth_field(lat_deg, lon_deg, alt_m, decimal_year).e_ned_gauss


def declination_rad(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float) -> float:
    """Declination (rad, east positive) from the WMM."""
    return earth_field(lat_deg, lon_deg, alt_m, decimal_year).declination_rad


def field_from_vector(e_ned_gauss: np.ndarray, declination_sigma_rad: float = math.nan) -> EarthField:
    """An ``EarthField`` from a configured field vector (gauss, NED) instead of the model."""
    e = np.asarray(e_ned_gauss, dtype=float)
    if e.shape != (3,) or not np.all(np.isfinite(e)):
        raise ValueError(f"e_ned_gauss must be 3 finite numbers, got {e_ned_gauss!r}")
    horiz = math.hypot(e[0], e[1])
    if not 0.01 <= float(np.linalg.norm(e)) <= 1.0:
        raise ValueError(f"|e_ned_gauss| = {np.linalg.norm(e):.4f} G is not an Earth field (0.01 .. 1 G)")
    if horiz < 1e-3:
        raise ValueError(f"horizontal field {horiz:.5f} G is too weak to define a heading")
    return EarthField(e.copy(), math.atan2(e[1], e[0]), math.atan2(e[2], horiz),
                      float(declination_sigma_rad), "configured")
