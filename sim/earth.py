"""The simulated Earth: WGS-84 ellipsoid, normal gravity, Earth rate, ISA atmosphere, WMM field.

Frames: the navigation frame is the local NED frame at the vehicle's geodetic position.
Units: m, s, rad, Pa, K; magnetic field in gauss (WMM gives nT; 1 G = 1e5 nT).
"""
from __future__ import annotations

import functools
import math

import numpy as np

# WGS-84
A_M = 6378137.0
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)
OMEGA_IE_RAD_S = 7.292115e-5
"""Earth rotation rate (WGS-84), rad/s."""
GM_M3_S2 = 3.986004418e14

# Somigliana normal gravity (WGS-84)
_GE = 9.7803253359
_K = 0.00193185265241

# ISA troposphere
P0_PA = 101325.0
T0_K = 288.15
LAPSE_K_M = 0.0065
R_AIR = 287.05287
G0 = 9.80665
NT_PER_GAUSS = 1e5


def radii_m(lat_rad):
    """Meridian (R_M) and prime-vertical (R_N) radii of curvature, m."""
    s2 = np.sin(lat_rad) ** 2
    d = 1.0 - E2 * s2
    r_n = A_M / np.sqrt(d)
    r_m = A_M * (1.0 - E2) / d ** 1.5
    return r_m, r_n


def gravity_m_s2(lat_rad, alt_m):
    """Normal gravity magnitude (Somigliana + free-air gradient), m/s^2, pointing down in NED."""
    s2 = np.sin(lat_rad) ** 2
    g0 = _GE * (1.0 + _K * s2) / np.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 * np.asarray(alt_m) / A_M)


def earth_rate_ned(lat_rad):
    """omega_ie in NED components: Omega [cos L, 0, -sin L], rad/s, shape (..., 3)."""
    lat = np.asarray(lat_rad, float)
    return OMEGA_IE_RAD_S * np.stack([np.cos(lat), np.zeros_like(lat), -np.sin(lat)], -1)


def transport_rate_ned(lat_rad, alt_m, vel_ned_m_s):
    """omega_en in NED: [vE/(R_N+h), -vN/(R_M+h), -vE tan L/(R_N+h)], rad/s."""
    r_m, r_n = radii_m(lat_rad)
    v = np.asarray(vel_ned_m_s, float)
    h = np.asarray(alt_m, float)
    return np.stack([v[..., 1] / (r_n + h), -v[..., 0] / (r_m + h),
                     -v[..., 1] * np.tan(lat_rad) / (r_n + h)], -1)


def isa_pressure_pa(alt_m):
    """ISA static pressure at geometric altitude ``alt_m`` above mean sea level (troposphere)."""
    t = T0_K - LAPSE_K_M * np.asarray(alt_m, float)
    return P0_PA * (t / T0_K) ** (G0 / (R_AIR * LAPSE_K_M))


def isa_temperature_k(alt_m):
    return T0_K - LAPSE_K_M * np.asarray(alt_m, float)


def isa_density_kg_m3(alt_m):
    return isa_pressure_pa(alt_m) / (R_AIR * isa_temperature_k(alt_m))


@functools.lru_cache(maxsize=1)
def _geomag():
    from pygeomag import GeoMag
    return GeoMag()  # WMM-2025 (2025.0-2030.0)


@functools.lru_cache(maxsize=65536)
def _wmm_cached(lat_q: float, lon_q: float, alt_q_m: float, year_q: float) -> tuple[float, float, float]:
    r = _geomag().calculate(glat=lat_q, glon=lon_q, alt=alt_q_m / 1000.0, time=year_q,
                            allow_date_outside_lifespan=True)
    return (r.x / NT_PER_GAUSS, r.y / NT_PER_GAUSS, r.z / NT_PER_GAUSS)


def wmm_field_ned_gauss(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float) -> np.ndarray:
    """WMM main field in NED at a point, gauss. Inputs are quantised (1e-4 deg, 1 m, 1e-3 yr) so
    that repeated calls hit a cache; the field changes by far less than a nT over those steps.
    At the geographic poles the WMM's own NED convention (north along the meridian of ``lon_deg``)
    applies."""
    if not (-90.0 <= lat_deg <= 90.0):
        raise ValueError(f"lat_deg must be in [-90, 90], got {lat_deg}")
    lon = ((lon_deg + 180.0) % 360.0) - 180.0
    return np.array(_wmm_cached(round(lat_deg, 4), round(lon, 4), round(alt_m, 0),
                                round(decimal_year, 3)))


def wmm_along_track(lat_rad: np.ndarray, lon_rad: np.ndarray, alt_m: np.ndarray, time_s: np.ndarray,
                    decimal_year: float, step_s: float = 1.0) -> np.ndarray:
    """WMM field (N, 3) gauss along a trajectory: evaluated every ``step_s`` of flight and
    linearly interpolated (the main field changes by < 1 nT per 100 m)."""
    t = np.asarray(time_s, float)
    if t.size == 0:
        return np.zeros((0, 3))
    t0, t1 = t[0], t[-1]
    n = max(2, int(math.ceil((t1 - t0) / step_s)) + 1)
    tk = np.linspace(t0, t1, n) if t1 > t0 else np.array([t0, t0 + 1.0])
    lat_k = np.interp(tk, t, lat_rad)
    lon_k = np.interp(tk, t, np.unwrap(lon_rad))
    alt_k = np.interp(tk, t, alt_m)
    fk = np.array([wmm_field_ned_gauss(math.degrees(a), math.degrees(b), c, decimal_year)
                   for a, b, c in zip(lat_k, lon_k, alt_k)])
    return np.stack([np.interp(t, tk, fk[:, i]) for i in range(3)], -1)


def geodetic_to_ecef(lat_rad, lon_rad, alt_m):
    r_m, r_n = radii_m(lat_rad)
    cl = np.cos(lat_rad)
    return np.stack([(r_n + alt_m) * cl * np.cos(lon_rad), (r_n + alt_m) * cl * np.sin(lon_rad),
                     (r_n * (1 - E2) + alt_m) * np.sin(lat_rad)], -1)


def ned_offset_m(lat0_rad, lon0_rad, alt0_m, lat_rad, lon_rad, alt_m) -> np.ndarray:
    """NED components (in the launcher's local frame) of the vector launcher -> points, m."""
    p0 = geodetic_to_ecef(lat0_rad, lon0_rad, alt0_m)
    d = geodetic_to_ecef(lat_rad, lon_rad, alt_m) - p0
    sl, cl = math.sin(lat0_rad), math.cos(lat0_rad)
    so, co = math.sin(lon0_rad), math.cos(lon0_rad)
    C_ned_from_ecef = np.array([[-sl * co, -sl * so, cl], [-so, co, 0.0], [-cl * co, -cl * so, -sl]])
    return d @ C_ned_from_ecef.T


def decimal_year_from_date(value) -> float:
    """A decimal year from a float/int, an ISO date string 'YYYY-MM-DD', or a datetime.date."""
    import datetime as _dt
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        try:
            value = _dt.date.fromisoformat(value.strip()[:10])
        except ValueError as exc:
            raise ValueError(f"date must be a decimal year or 'YYYY-MM-DD', got {value!r}") from exc
    if isinstance(value, _dt.datetime):
        value = value.date()
    if isinstance(value, _dt.date):
        start = _dt.date(value.year, 1, 1)
        days = (_dt.date(value.year + 1, 1, 1) - start).days
        return value.year + (value - start).days / days
    raise ValueError(f"date must be a decimal year or 'YYYY-MM-DD', got {value!r}")
