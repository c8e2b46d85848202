"""The simulated Earth: WGS-84 ellipsoid, normal gravity, Earth rate, and a magnetic field and an
atmosphere that are NOT the estimators' models (DESIGN.md: every figure includes the model error).

Magnetic field (``SimEarth.field_ned_gauss``), per point:
    B = IGRF-14 main field (ppigrf; the estimators use WMM-2025)
      + b_err  the WMM-2025 error budget drawn once per seed (constant over the flight area)
      + b_crust(N, E, h)  a crustal anomaly potential field drawn per seed (km-scale variation)
The launch-site distortion and local anomalies of [mag] are added by sim.sensors on top.
Atmosphere (``Atmosphere``): a troposphere with its own sea-level pressure (QNH), sea-level
temperature (ISA + deviation) and lapse rate, drawn per seed unless the scenario sets them.

Frames: the navigation frame is the local NED frame at the vehicle's geodetic position.
Units: m, s, rad, Pa, K; magnetic field in gauss (IGRF gives nT; 1 G = 1e5 nT).
"""
from __future__ import annotations

import datetime as _dt
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


# --- magnetic field ---------------------------------------------------------------------------
# WMM-2025 error model, 1 sigma (Chulliat et al., "The US/UK World Magnetic Model for 2025-2030:
# Technical Report", NOAA NCEI / BGS, 2025, table "WMM2025 uncertainty estimates"): the global
# RMS of observed field minus model over 2025-2030, crustal and disturbance fields included.
WMM2025_SIGMA_X_NT = 137.0
WMM2025_SIGMA_Y_NT = 89.0
WMM2025_SIGMA_Z_NT = 141.0
WMM2025_SIGMA_H_NT = 133.0
WMM2025_SIGMA_F_NT = 138.0
WMM2025_SIGMA_I_DEG = 0.20
WMM2025_SIGMA_D0_DEG = 0.26
"""Declination: sigma_D = sqrt(0.26^2 + (5417 / H)^2) deg, H in nT (grows where H is weak)."""
WMM2025_SIGMA_D_H_NT_DEG = 5417.0
IGRF_YEARS = (1900.0, 2030.0)
"""IGRF-14's span (definitive/provisional models 1900-2025, secular variation to 2030)."""
CRUSTAL_MODES = 64
"""Fourier modes of the crustal potential (enough for a Gaussian-looking field per seed)."""
_LATTICE_DEG = 0.02
_LATTICE_ALT_M = 1000.0


def wmm2025_declination_sigma_deg(h_nt: float) -> float:
    """The WMM-2025 report's declination 1-sigma at horizontal intensity ``h_nt`` (nT), deg."""
    return math.hypot(WMM2025_SIGMA_D0_DEG, WMM2025_SIGMA_D_H_NT_DEG / h_nt)


def _datetime_from_decimal_year(year: float) -> _dt.datetime:
    y = int(math.floor(year))
    start = _dt.datetime(y, 1, 1)
    return start + (_dt.datetime(y + 1, 1, 1) - start) * (year - y)


class MainField:
    """IGRF-14 (ppigrf) at geodetic points, NED nT. ppigrf costs ~30 ms a call, so the field is
    evaluated on a lazily filled lattice (0.02 deg x 0.02 deg x 1 km, cached) and interpolated
    trilinearly: the main field's curvature (~B/R^2) makes that error < 0.01 nT."""

    def __init__(self, decimal_year: float):
        if not (IGRF_YEARS[0] <= decimal_year <= IGRF_YEARS[1]):
            raise ValueError(f"scenario.date {decimal_year:.3f} is outside IGRF-14's span "
                             f"{IGRF_YEARS[0]:.0f}-{IGRF_YEARS[1]:.0f}")
        self.date = _datetime_from_decimal_year(decimal_year)
        self._nodes: dict[tuple[int, int, int], np.ndarray] = {}
        self._points: dict[tuple[float, float, float], np.ndarray] = {}

    def point_nt(self, lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
        """IGRF-14 exactly at one point (cached), NED nT."""
        key = (float(lat_deg), float(lon_deg), float(alt_m))
        if key not in self._points:
            self._points[key] = self.at_points_nt(*key)[0]
        return self._points[key]

    def at_points_nt(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        """IGRF-14 exactly (no lattice), shape (n, 3) NED nT; latitudes clamped off the poles."""
        try:
            import ppigrf  # imported on first use: it loads pandas (~0.7 s)
        except ImportError:
            raise SystemExit("azimuthd sim: the simulator's Earth field needs the 'sim' extra: "
                             "pip install 'azimuthd[sim]' (ppigrf, IGRF-14)") from None
        lat = np.clip(np.atleast_1d(np.asarray(lat_deg, float)), -89.999, 89.999)
        lon = np.atleast_1d(np.asarray(lon_deg, float))
        h_km = np.atleast_1d(np.asarray(alt_m, float)) / 1000.0
        be, bn, bu = ppigrf.igrf(lon, lat, h_km, self.date)
        return np.stack([bn[0], be[0], -bu[0]], -1)

    def _corners(self, cells: np.ndarray) -> np.ndarray:
        """Node values (m, 8, 3) for lattice cells (m, 3), computing missing nodes in one call."""
        offs = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        keys = (cells[:, None, :] + offs[None]).reshape(-1, 3)
        missing = sorted({tuple(int(v) for v in k) for k in keys} - self._nodes.keys())
        if missing:
            m = np.array(missing, float)
            vals = self.at_points_nt(m[:, 0] * _LATTICE_DEG, m[:, 1] * _LATTICE_DEG, m[:, 2] * _LATTICE_ALT_M)
            self._nodes.update(zip(missing, vals))
        return np.array([self._nodes[tuple(int(v) for v in k)] for k in keys]).reshape(len(cells), 8, 3)

    def ned_nt(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        """Interpolated IGRF-14, shape (n, 3) NED nT."""
        x = np.stack([np.asarray(lat_deg, float) / _LATTICE_DEG, np.asarray(lon_deg, float) / _LATTICE_DEG,
                      np.asarray(alt_m, float) / _LATTICE_ALT_M], -1).reshape(-1, 3)
        i0 = np.floor(x).astype(np.int64)
        fr = x - i0
        cells, inv = np.unique(i0, axis=0, return_inverse=True)
        node = self._corners(cells)[inv.reshape(-1)]                    # (n, 8, 3)
        w = np.ones((len(x), 8))
        for j, (a, b, c) in enumerate((a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)):
            w[:, j] = ((fr[:, 0] if a else 1 - fr[:, 0]) * (fr[:, 1] if b else 1 - fr[:, 1])
                       * (fr[:, 2] if c else 1 - fr[:, 2]))
        return np.einsum("nj,nji->ni", w, node)


@functools.lru_cache(maxsize=4)
def main_field(decimal_year: float) -> MainField:
    """One lattice per date and process: flights of a bench share the IGRF evaluations."""
    return MainField(decimal_year)


class CrustalField:
    """A per-seed crustal anomaly field: the gradient of a random harmonic potential above the
    sources, so it is curl- and divergence-free like a real one.

        V(N, E, h) = sum_i a_i cos(k_i . [N, E] + phi_i) exp(-|k_i| h)   (h: height above the launcher)
        B = -grad V:  B_N = sum a_i k_iN sin(.) e,  B_E = sum a_i k_iE sin(.) e,  B_D = -sum a_i |k_i| cos(.) e
    (Laplace: d2V/dN2 + d2V/dE2 + d2V/dh2 = (-|k|^2 + |k|^2) V = 0.) With k_i ~ N(0, I / L^2) and
    a_i |k_i| = sigma sqrt(2 / M), at the launcher's height B_D has the covariance
    sigma^2 exp(-d^2 / 2 L^2) and each horizontal component the variance sigma^2 / 2.
    The field is expressed in the launcher's NED frame (at 89 deg N, 5 km east turns the local
    north by 0.5 deg: < 1 nT of a 100 nT anomaly)."""

    def __init__(self, sigma_nt: float, correlation_m: float, rng: np.random.Generator):
        k = rng.standard_normal((CRUSTAL_MODES, 2)) / correlation_m
        phi = rng.uniform(0.0, 2.0 * math.pi, CRUSTAL_MODES)
        self.k, self.phi = k, phi
        self.k_abs = np.maximum(np.linalg.norm(k, axis=1), 1e-12)
        self.amp_nt = sigma_nt * math.sqrt(2.0 / CRUSTAL_MODES)  # a_i |k_i|
        self.on = sigma_nt > 0.0

    def ned_nt(self, ned_m: np.ndarray) -> np.ndarray:
        """Field (n, 3) NED nT at launcher-relative NED positions (n, 3) m."""
        ned = np.asarray(ned_m, float).reshape(-1, 3)
        if not self.on:
            return np.zeros_like(ned)
        arg = ned[:, :2] @ self.k.T + self.phi                       # (n, M)
        decay = np.exp(np.minimum(self.k_abs * ned[:, 2:3], 50.0))    # e^{-|k| h}, h = -D
        s = np.sin(arg) * decay * (self.amp_nt / self.k_abs)
        c = np.cos(arg) * decay * self.amp_nt
        return np.stack([s @ self.k[:, 0], s @ self.k[:, 1], -c.sum(1)], -1)


def draw_model_error_ned_nt(main_ned_nt: np.ndarray, rng: np.random.Generator,
                            crustal_sigma_nt: float = 0.0) -> np.ndarray:
    """One draw of the WMM-2025 error budget at a site, NED nT. Drawn along the horizontal field
    (sigma_H), across it (H sigma_D: the declination error) and down (sigma_Z), so H, D and Z
    carry the report's published 1-sigma exactly; X and Y follow (e.g. ~135 nT at Zurich vs the
    report's 137/89). The crustal field's own variance (sigma^2/2 horizontal, sigma^2 down) is
    taken out so that the two together keep the report's totals."""
    n, e, d = (float(v) for v in main_ned_nt)
    h = math.hypot(n, e)
    dec = math.atan2(e, n)
    s_across = h * math.radians(wmm2025_declination_sigma_deg(h))
    c2 = crustal_sigma_nt ** 2
    s_along = math.sqrt(max(WMM2025_SIGMA_H_NT ** 2 - c2 / 2.0, 0.0))
    s_across = math.sqrt(max(s_across ** 2 - c2 / 2.0, 0.0))
    s_down = math.sqrt(max(WMM2025_SIGMA_Z_NT ** 2 - c2, 0.0))
    z = rng.standard_normal(3)
    along, across = z[0] * s_along, z[1] * s_across
    return np.array([along * math.cos(dec) - across * math.sin(dec),
                     along * math.sin(dec) + across * math.cos(dec), z[2] * s_down])


# --- atmosphere --------------------------------------------------------------------------------
# Per-seed draws when the scenario does not set a value (the simulator's own assumptions, chosen
# to span ordinary flying weather; they are not measured figures):
QNH_SIGMA_HPA = 10.0
ISA_DEVIATION_SIGMA_K = 10.0
LAPSE_RATE_SIGMA_K_KM = 1.0
LAPSE_RATE_RANGE_K_KM = (4.0, 9.8)  # between a moist and the dry adiabatic lapse rate


class Atmosphere:
    """A humidity-free troposphere that is not ISA: sea-level pressure p_s (QNH), sea-level
    temperature T_s = 288.15 K + dT, lapse rate L. Hydrostatic with g0 and dry air:
        T(h) = T_s - L h,   p(h) = p_s (T(h) / T_s)^(g0 / (R L)),   rho = p / (R T)
    (h: altitude above mean sea level, taken as geopotential: < 0.1 % below 5 km)."""

    def __init__(self, qnh_pa: float, isa_deviation_k: float, lapse_rate_k_m: float):
        self.qnh_pa, self.isa_deviation_k, self.lapse_rate_k_m = qnh_pa, isa_deviation_k, lapse_rate_k_m
        self.t_sea_k = T0_K + isa_deviation_k

    def temperature_k(self, alt_m):
        return self.t_sea_k - self.lapse_rate_k_m * np.asarray(alt_m, float)

    def pressure_pa(self, alt_m):
        ratio = self.temperature_k(alt_m) / self.t_sea_k
        return self.qnh_pa * ratio ** (G0 / (R_AIR * self.lapse_rate_k_m))

    def density_kg_m3(self, alt_m):
        return self.pressure_pa(alt_m) / (R_AIR * self.temperature_k(alt_m))


def draw_atmosphere(section: dict, rng: np.random.Generator) -> Atmosphere:
    """The scenario's [atmosphere]; a key left unset (None) is drawn (always three draws, in a
    fixed order, so setting one key leaves the others' draws unchanged)."""
    z = rng.standard_normal(3)
    qnh_hpa = section["qnh_hpa"] if section["qnh_hpa"] is not None else 1013.25 + QNH_SIGMA_HPA * z[0]
    dev_k = section["isa_deviation_k"] if section["isa_deviation_k"] is not None \
        else ISA_DEVIATION_SIGMA_K * z[1]
    lapse = section["lapse_rate_k_km"] if section["lapse_rate_k_km"] is not None \
        else float(np.clip(LAPSE_K_M * 1000.0 + LAPSE_RATE_SIGMA_K_KM * z[2], *LAPSE_RATE_RANGE_K_KM))
    return Atmosphere(qnh_hpa * 100.0, dev_k, lapse / 1000.0)


# --- the simulated Earth -----------------------------------------------------------------------
class SimEarth:
    """The field and atmosphere of one simulated flight, drawn once from ``rng`` (fixed order:
    model error, crustal field, atmosphere) and then deterministic at every point."""

    def __init__(self, scenario: dict, rng: np.random.Generator):
        S, E = scenario["site"], scenario["earth"]
        self.lat0_rad, self.lon0_rad = math.radians(S["lat_deg"]), math.radians(S["lon_deg"])
        self.alt0_m = float(S["alt_m"])
        self.main = main_field(scenario["scenario"]["decimal_year"])
        site_main = self.main.point_nt(S["lat_deg"], S["lon_deg"], self.alt0_m)
        err = draw_model_error_ned_nt(site_main, rng, E["crustal_sigma_nt"])  # drawn even when off
        self.model_error_ned_nt = err if E["model_error"] else np.zeros(3)
        self.crust = CrustalField(E["crustal_sigma_nt"], E["crustal_correlation_m"], rng)
        self.atmosphere = draw_atmosphere(scenario["atmosphere"], rng)

    def field_ned_gauss(self, lat_rad, lon_rad, alt_m) -> tuple[np.ndarray, np.ndarray]:
        """(IGRF main field, main + model error + crustal field), each (n, 3) NED gauss."""
        lat, lon, alt = (np.atleast_1d(np.asarray(v, float)) for v in (lat_rad, lon_rad, alt_m))
        main = self.main.ned_nt(np.degrees(lat), np.degrees(lon), alt)
        total = main + self.model_error_ned_nt
        if self.crust.on:
            total = total + self.crust.ned_nt(ned_offset_m(self.lat0_rad, self.lon0_rad, self.alt0_m,
                                                           lat, lon, alt))
        return main / NT_PER_GAUSS, total / NT_PER_GAUSS
