"""Ellipsoidal geometry for the geofence: WGS-84 frames, geodesics, distance to a polygon's edges.

Pure (numpy only). Angles in radians inside, lengths in metres, heights above the WGS-84 ellipsoid.

What is here and how exact it is:

* ``radii_m(lat)``: meridian radius M = a(1-e^2)/W^3 and prime-vertical radius N = a/W,
  W = sqrt(1 - e^2 sin^2 lat). Dead reckoning integrates lat_dot = v_N/(M+h),
  lon_dot = v_E/((N+h) cos lat) with them (exact for the ellipsoid).
* ``geodetic_to_ecef`` / ``ecef_to_geodetic`` (Bowring's iteration, converges to < 1e-12 rad in
  three passes for |h| < 100 km).
* ``vincenty_inverse`` / ``vincenty_direct``: geodesics on the ellipsoid (Vincenty 1975), the
  reference for distances and azimuths (0.1 mm; the inverse is iterated to 1e-13 rad and reports
  non-convergence for nearly antipodal points as ValueError).
* ``meridian_arc_m(lat)``: the analytic meridian arc from the equator (Helmert's series in n,
  truncated after n^4: error < 0.1 mm), for analytic test cases.
* ``LocalGnomonic``: the plane the fence is measured in. Points are mapped to ENU at a tangent
  point T (exact, via ECEF), then projected centrally from the centre of the sphere of radius
  R = sqrt(M N) (Gauss's mean radius at T) that osculates the ellipsoid at T:
      (x_E, y_N) = (e, n) * R / (R + u)
  On that sphere this is the gnomonic projection: every great circle is a straight line, and the
  distance from T to a point or to a line at planar distance rho is exactly R atan(rho / R).
  On the ellipsoid, geodesics near T are straight up to O(e^2 (L/R)^2) (L: distance to the edge's
  vertices). Measured (tests/test_geodesy.py): ranges to points 20 km away agree with Vincenty to
  0.1 mm (14 mm at 100 km); the distance to the equator from 11 km north agrees with the analytic
  meridian arc to 0.5 mm when the edge's vertices are 22 km away, 6 mm when they are 111 km away.
  Projecting the fence about the vehicle's position each update therefore gives the distance
  from the vehicle to every fence edge (a geodesic between two vertices) on the ellipsoid. No
  longitude wrap, no pole problem; vertices must be within 2000 km of T (ValueError otherwise).
* ``signed_distance_polygon``: planar signed distance of points to a simple polygon (positive
  inside), nearest-edge unit normal, and inside test (even-odd crossing rule) — used in the
  gnomonic plane.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)

MAX_PROJECTION_RANGE_M = 2.0e6
"""Fence vertices further than this from the projection point are refused (gnomonic blows up at 90 deg)."""


def radii_m(lat_rad: float) -> tuple[float, float]:
    """(M, N): meridian and prime-vertical radii of curvature at a geodetic latitude (m)."""
    s = math.sin(lat_rad)
    w2 = 1.0 - WGS84_E2 * s * s
    w = math.sqrt(w2)
    return WGS84_A_M * (1.0 - WGS84_E2) / (w2 * w), WGS84_A_M / w


def geodetic_to_ecef(lat_rad, lon_rad, h_m):
    """ECEF coordinates (m) of geodetic points; accepts scalars or arrays (broadcast), returns (..., 3)."""
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    h = np.asarray(h_m, dtype=float)
    s, c = np.sin(lat), np.cos(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * s * s)
    x = (n + h) * c * np.cos(lon)
    y = (n + h) * c * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * s
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(xyz_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat_rad, lon_rad, h_m) of ECEF points (..., 3) by Bowring's iteration (3 passes)."""
    p_xyz = np.asarray(xyz_m, dtype=float)
    x, y, z = p_xyz[..., 0], p_xyz[..., 1], p_xyz[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    beta = np.arctan2(z * WGS84_A_M, p * WGS84_B_M)  # parametric latitude, first guess
    lat = beta
    for _ in range(3):
        lat = np.arctan2(z + WGS84_EP2 * WGS84_B_M * np.sin(beta) ** 3,
                         p - WGS84_E2 * WGS84_A_M * np.cos(beta) ** 3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    s = np.sin(lat)
    # h from the component along the normal (well conditioned at every latitude): p cos + z sin - a W
    h = p * np.cos(lat) + z * s - WGS84_A_M * np.sqrt(1.0 - WGS84_E2 * s * s)
    return lat, lon, h


def C_enu_from_ecef(lat_rad: float, lon_rad: float) -> np.ndarray:
    """Rotation taking ECEF vectors to the local East-North-Up frame at (lat, lon)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    return np.array([[-so, co, 0.0],
                     [-sl * co, -sl * so, cl],
                     [cl * co, cl * so, sl]])


def meridian_arc_m(lat_rad: float) -> float:
    """Meridian arc length from the equator to ``lat_rad`` (m), Helmert's series in n = f/(2-f)."""
    n = WGS84_F / (2.0 - WGS84_F)
    n2 = n * n
    a0 = WGS84_A_M / (1.0 + n) * (1.0 + n2 / 4.0 + n2 * n2 / 64.0)
    phi = lat_rad
    return a0 * (phi
                 - (3.0 * n / 2.0 - 9.0 * n2 * n / 16.0) * math.sin(2 * phi)
                 + (15.0 * n2 / 16.0 - 15.0 * n2 * n2 / 32.0) * math.sin(4 * phi)
                 - (35.0 * n2 * n / 48.0) * math.sin(6 * phi)
                 + (315.0 * n2 * n2 / 512.0) * math.sin(8 * phi))


def vincenty_inverse(lat1_rad: float, lon1_rad: float, lat2_rad: float, lon2_rad: float,
                     tol_rad: float = 1e-13, max_iter: int = 200) -> tuple[float, float, float]:
    """Geodesic distance (m), initial and final azimuth (rad, [0, 2pi)) from point 1 to point 2.

    Vincenty (1975) inverse; ValueError when it does not converge (nearly antipodal points)."""
    a, b, f = WGS84_A_M, WGS84_B_M, WGS84_F
    L = math.remainder(lon2_rad - lon1_rad, 2 * math.pi)
    U1 = math.atan((1 - f) * math.tan(lat1_rad))
    U2 = math.atan((1 - f) * math.tan(lat2_rad))
    sU1, cU1, sU2, cU2 = math.sin(U1), math.cos(U1), math.sin(U2), math.cos(U2)
    lam = L
    for _ in range(max_iter):
        sl, cl = math.sin(lam), math.cos(lam)
        s_sig = math.hypot(cU2 * sl, cU1 * sU2 - sU1 * cU2 * cl)
        if s_sig == 0.0:
            return 0.0, 0.0, 0.0  # coincident points
        c_sig = sU1 * sU2 + cU1 * cU2 * cl
        sig = math.atan2(s_sig, c_sig)
        s_alpha = cU1 * cU2 * sl / s_sig
        c2_alpha = 1.0 - s_alpha * s_alpha
        c2sm = c_sig - 2.0 * sU1 * sU2 / c2_alpha if c2_alpha != 0.0 else 0.0  # equatorial line
        C = f / 16.0 * c2_alpha * (4.0 + f * (4.0 - 3.0 * c2_alpha))
        lam_prev = lam
        lam = L + (1 - C) * f * s_alpha * (sig + C * s_sig * (c2sm + C * c_sig * (-1 + 2 * c2sm * c2sm)))
        if abs(lam - lam_prev) < tol_rad:
            break
    else:
        raise ValueError("vincenty_inverse did not converge (nearly antipodal points): "
                         f"({math.degrees(lat1_rad)}, {math.degrees(lon1_rad)}) -> "
                         f"({math.degrees(lat2_rad)}, {math.degrees(lon2_rad)})")
    u2 = c2_alpha * (a * a - b * b) / (b * b)
    A = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)))
    B = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)))
    d_sig = B * s_sig * (c2sm + B / 4 * (c_sig * (-1 + 2 * c2sm * c2sm)
                                        - B / 6 * c2sm * (-3 + 4 * s_sig * s_sig) * (-3 + 4 * c2sm * c2sm)))
    s = b * A * (sig - d_sig)
    az1 = math.atan2(cU2 * math.sin(lam), cU1 * sU2 - sU1 * cU2 * math.cos(lam)) % (2 * math.pi)
    az2 = math.atan2(cU1 * math.sin(lam), -sU1 * cU2 + cU1 * sU2 * math.cos(lam)) % (2 * math.pi)
    return s, az1, az2


def vincenty_direct(lat1_rad: float, lon1_rad: float, az1_rad: float, s_m: float,
                    tol_rad: float = 1e-13) -> tuple[float, float]:
    """End point (lat, lon) of the geodesic from point 1 with initial azimuth az1 and length s (m)."""
    a, b, f = WGS84_A_M, WGS84_B_M, WGS84_F
    s_a1, c_a1 = math.sin(az1_rad), math.cos(az1_rad)
    tU1 = (1 - f) * math.tan(lat1_rad)
    cU1 = 1.0 / math.sqrt(1 + tU1 * tU1)
    sU1 = tU1 * cU1
    sig1 = math.atan2(tU1, c_a1)
    s_alpha = cU1 * s_a1
    c2_alpha = 1 - s_alpha * s_alpha
    u2 = c2_alpha * (a * a - b * b) / (b * b)
    A = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)))
    B = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)))
    sig = s_m / (b * A)
    for _ in range(200):
        c2sm = math.cos(2 * sig1 + sig)
        s_sig, c_sig = math.sin(sig), math.cos(sig)
        d_sig = B * s_sig * (c2sm + B / 4 * (c_sig * (-1 + 2 * c2sm * c2sm)
                                            - B / 6 * c2sm * (-3 + 4 * s_sig * s_sig) * (-3 + 4 * c2sm * c2sm)))
        sig_new = s_m / (b * A) + d_sig
        if abs(sig_new - sig) < tol_rad:
            sig = sig_new
            break
        sig = sig_new
    s_sig, c_sig = math.sin(sig), math.cos(sig)
    c2sm = math.cos(2 * sig1 + sig)
    tmp = sU1 * s_sig - cU1 * c_sig * c_a1
    lat2 = math.atan2(sU1 * c_sig + cU1 * s_sig * c_a1, (1 - f) * math.hypot(s_alpha, tmp))
    lam = math.atan2(s_sig * s_a1, cU1 * c_sig - sU1 * s_sig * c_a1)
    C = f / 16 * c2_alpha * (4 + f * (4 - 3 * c2_alpha))
    L = lam - (1 - C) * f * s_alpha * (sig + C * s_sig * (c2sm + C * c_sig * (-1 + 2 * c2sm * c2sm)))
    return lat2, math.remainder(lon1_rad + L, 2 * math.pi)


@dataclass(frozen=True)
class LocalGnomonic:
    """The gnomonic plane at a tangent point (see the module docstring). x = east, y = north (m)."""
    lat0_rad: float
    lon0_rad: float

    def __post_init__(self):
        if not (math.isfinite(self.lat0_rad) and math.isfinite(self.lon0_rad)
                and abs(self.lat0_rad) <= math.pi / 2):
            raise ValueError(f"tangent point must be finite with |lat| <= pi/2, got "
                             f"({self.lat0_rad!r}, {self.lon0_rad!r})")
        M, N = radii_m(self.lat0_rad)
        object.__setattr__(self, "radius_m", math.sqrt(M * N))
        object.__setattr__(self, "_C", C_enu_from_ecef(self.lat0_rad, self.lon0_rad))
        object.__setattr__(self, "_o", geodetic_to_ecef(self.lat0_rad, self.lon0_rad, 0.0))

    def forward(self, lat_rad, lon_rad) -> np.ndarray:
        """(..., 2) plane coordinates [east, north] (m) of surface points (height 0)."""
        enu = (geodetic_to_ecef(lat_rad, lon_rad, 0.0) - self._o) @ self._C.T
        R = self.radius_m
        den = R + enu[..., 2]
        rng = np.hypot(enu[..., 0], enu[..., 1])
        if np.any(den <= 0.3 * R) or np.any(rng > MAX_PROJECTION_RANGE_M):
            raise ValueError(f"point(s) more than {MAX_PROJECTION_RANGE_M / 1000:.0f} km from the "
                             "projection point: a fence must be local")
        return enu[..., :2] * (R / den)[..., None]

    def plane_to_surface_distance_m(self, rho_m):
        """Distance on the osculating sphere from the tangent point to a point or line at planar
        distance rho from it: R atan(rho / R) (rho may be negative: the sign is kept)."""
        return self.radius_m * np.arctan(np.asarray(rho_m, dtype=float) / self.radius_m)


def _segment_arrays(verts: np.ndarray):
    a = verts
    b = np.roll(verts, -1, axis=0)
    return a, b, b - a


def inside_polygon(points: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Even-odd (crossing number) inside test of planar points (K, 2) in a polygon (V, 2)."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    a, b, _ = _segment_arrays(np.asarray(verts, dtype=float))
    px, py = pts[:, 0:1], pts[:, 1:2]
    ax, ay, bx, by = a[:, 0], a[:, 1], b[:, 0], b[:, 1]
    straddle = (ay > py) != (by > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = ax + (py - ay) * (bx - ax) / (by - ay)
    crossings = np.sum(straddle & (px < x_cross), axis=1)
    return crossings % 2 == 1


def signed_distance_polygon(points: np.ndarray, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar signed distance (m, > 0 inside) of points (K, 2) to a simple polygon (V, 2), and the
    unit vector (K, 2) from each point toward its nearest boundary point (outward for inside points).

    d(p) = +/- min over edges of |p - clamp_projection(p, edge)|; sign from the even-odd rule."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    a, b, ab = _segment_arrays(np.asarray(verts, dtype=float))
    ap = pts[:, None, :] - a[None, :, :]                         # (K, V, 2)
    L2 = np.maximum(np.sum(ab * ab, axis=1), 1e-300)             # (V,)
    t = np.clip(np.sum(ap * ab[None], axis=2) / L2, 0.0, 1.0)    # (K, V)
    nearest = a[None] + t[..., None] * ab[None]                  # (K, V, 2)
    diff = nearest - pts[:, None, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    k = np.argmin(dist, axis=1)
    idx = np.arange(pts.shape[0])
    dmin = dist[idx, k]
    direction = diff[idx, k] / np.maximum(dmin, 1e-12)[:, None]
    sign = np.where(inside_polygon(pts, verts), 1.0, -1.0)
    return sign * dmin, direction


def polygon_is_simple(verts: np.ndarray) -> bool:
    """True if no two non-adjacent edges of the planar polygon intersect (O(V^2), V small)."""
    v = np.asarray(verts, dtype=float)
    n = len(v)

    def cross(o, p, q):
        return (p[0] - o[0]) * (q[1] - o[1]) - (p[1] - o[1]) * (q[0] - o[0])

    for i in range(n):
        p1, p2 = v[i], v[(i + 1) % n]
        for j in range(i + 1, n):
            if j == i or (j + 1) % n == i or (i + 1) % n == j:
                continue
            q1, q2 = v[j], v[(j + 1) % n]
            d1, d2 = cross(q1, q2, p1), cross(q1, q2, p2)
            d3, d4 = cross(p1, p2, q1), cross(p1, p2, q2)
            if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 * d2 < 0 and d3 * d4 < 0:
                return False
    return True


__all__ = ["WGS84_A_M", "WGS84_F", "WGS84_E2", "radii_m", "geodetic_to_ecef", "ecef_to_geodetic",
           "C_enu_from_ecef", "meridian_arc_m", "vincenty_inverse", "vincenty_direct", "LocalGnomonic",
           "inside_polygon", "signed_distance_polygon", "polygon_is_simple"]
