"""estimators/geodesy.py: analytic cases on the WGS-84 ellipsoid, point in polygon, distance to edges."""
import math

import numpy as np
import pytest

from estimators.geodesy import (WGS84_A_M, WGS84_E2, LocalGnomonic, ecef_to_geodetic, geodetic_to_ecef,
                                inside_polygon, meridian_arc_m, polygon_is_simple, radii_m,
                                signed_distance_polygon, vincenty_direct, vincenty_inverse)

D = math.radians


def _distance_to_fence(lat0, lon0, poly_deg):
    """What the monitor does: project about the point, planar signed distance, back to the surface."""
    g = LocalGnomonic(lat0, lon0)
    p = np.radians(np.array(poly_deg))
    d, n = signed_distance_polygon(np.zeros((1, 2)), g.forward(p[:, 0], p[:, 1]))
    return float(g.plane_to_surface_distance_m(d[0])), n[0]


def test_radii_analytic():
    M, N = radii_m(0.0)
    assert N == pytest.approx(WGS84_A_M, abs=1e-9)
    assert M == pytest.approx(WGS84_A_M * (1 - WGS84_E2), abs=1e-9)
    Mp, Np = radii_m(math.pi / 2)
    assert Mp == pytest.approx(Np, rel=1e-12)  # at the pole both equal a^2 / b


def test_ecef_round_trip_every_latitude():
    for lat_deg in (-89.999, -60, -1e-7, 0, 33.3, 71.2, 89.9999):
        for h in (-400.0, 0.0, 8848.0, 30000.0):
            xyz = geodetic_to_ecef(D(lat_deg), D(123.4), h)
            lat, lon, hh = ecef_to_geodetic(xyz)
            assert float(lat) == pytest.approx(D(lat_deg), abs=1e-12)
            assert float(lon) == pytest.approx(D(123.4), abs=1e-12)
            assert float(hh) == pytest.approx(h, abs=1e-6)


def test_vincenty_equator_and_meridian_analytic():
    s, az1, az2 = vincenty_inverse(0.0, D(10.0), 0.0, D(10.2))
    assert s == pytest.approx(WGS84_A_M * D(0.2), abs=1e-6)   # along the equator: a * dlon
    assert math.degrees(az1) == pytest.approx(90.0, abs=1e-9)
    for lat in (D(1.0), D(45.0), D(80.0)):
        s, az1, _ = vincenty_inverse(0.0, D(7.0), lat, D(7.0))
        assert s == pytest.approx(meridian_arc_m(lat), abs=1e-4)   # along a meridian: the meridian arc
        assert az1 == pytest.approx(0.0, abs=1e-12)


def test_vincenty_direct_inverts_inverse():
    rng = np.random.default_rng(1)
    for _ in range(20):
        lat, lon = D(rng.uniform(-80, 80)), D(rng.uniform(-180, 180))
        az, s = rng.uniform(0, 2 * math.pi), rng.uniform(10.0, 50000.0)
        lat2, lon2 = vincenty_direct(lat, lon, az, s)
        s_back, az_back, _ = vincenty_inverse(lat, lon, lat2, lon2)
        assert s_back == pytest.approx(s, abs=1e-6)
        assert math.remainder(az_back - az, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_distance_to_meridian_edge_on_the_equator_is_a_dlon():
    # GIVEN the vehicle on the equator and a square whose east edge is the meridian 0.05 deg east
    # THEN the distance to the fence is the equatorial arc a * 0.05 deg (the geodesic to a meridian
    # from the equator runs along the equator, which meets every meridian at right angles)
    poly = [[-0.2, -0.07], [-0.2, 0.05], [0.2, 0.05], [0.2, -0.07]]
    d, n = _distance_to_fence(0.0, 0.0, poly)
    assert d == pytest.approx(WGS84_A_M * D(0.05), abs=5e-4)
    assert n == pytest.approx([1.0, 0.0], abs=1e-9)  # toward east


@pytest.mark.parametrize("half_dlon_deg, tol_m", [(0.2, 5e-4), (1.0, 1e-2)])
def test_distance_to_equator_edge_is_the_meridian_arc(half_dlon_deg, tol_m):
    # GIVEN the vehicle at latitude 0.1 deg and a fence whose south edge is the equator (a geodesic)
    # THEN the distance is the meridian arc from the equator to 0.1 deg (11.06 km). The gnomonic
    # plane keeps ellipsoidal geodesics straight to O(e^2 (L/R)^2): 0.5 mm with 22 km to the edge's
    # vertices, 6 mm when they are 111 km away.
    poly = [[0.0, -half_dlon_deg], [0.0, half_dlon_deg], [1.0, half_dlon_deg], [1.0, -half_dlon_deg]]
    d, n = _distance_to_fence(D(0.1), 0.0, poly)
    assert d == pytest.approx(meridian_arc_m(D(0.1)), abs=tol_m)
    assert n[1] == pytest.approx(-1.0, abs=1e-9)  # toward south


def test_distance_to_vertex_matches_vincenty_at_20_km():
    # the nearest fence point is a vertex 20 km away: the gnomonic range maps back to the geodesic length
    rng = np.random.default_rng(3)
    for _ in range(10):
        lat0, lon0 = D(rng.uniform(-75, 75)), D(rng.uniform(-180, 180))
        az = rng.uniform(0, 2 * math.pi)
        v = [vincenty_direct(lat0, lon0, az + da, s) for da, s in ((0, 20000.0), (0.3, 60000.0), (-0.3, 60000.0))]
        g = LocalGnomonic(lat0, lon0)
        xy = g.forward(np.array([p[0] for p in v]), np.array([p[1] for p in v]))
        d, _ = signed_distance_polygon(np.zeros((1, 2)), xy)
        assert -float(g.plane_to_surface_distance_m(d[0])) == pytest.approx(20000.0, abs=1e-3)  # outside


def test_point_in_polygon_concave_and_across_the_antimeridian():
    # an L-shaped fence straddling the antimeridian, in degrees (lat, lon)
    L = [[10.0, 179.9], [10.0, -179.9], [10.05, -179.9], [10.05, 179.95], [10.1, 179.95], [10.1, 179.9]]
    cases = {(10.02, 179.99): True, (10.02, -179.95): True, (10.08, 179.92): True,
             (10.08, 179.99): False, (10.08, -179.95): False, (9.99, 179.95): False}
    for (lat, lon), inside in cases.items():
        d, _ = _distance_to_fence(D(lat), D(lon), L)
        assert (d > 0) == inside, (lat, lon, d)


def test_point_in_polygon_near_the_pole():
    ring = [[89.9, 0.0], [89.9, 90.0], [89.9, 180.0], [89.9, -90.0]]  # a square around the north pole
    d_pole, _ = _distance_to_fence(D(89.99), D(45.0), ring)
    assert d_pole > 0
    d_out, _ = _distance_to_fence(D(89.85), D(45.0), ring)
    assert d_out < 0


def test_signed_distance_planar_cases():
    sq = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    d, n = signed_distance_polygon(np.array([[5.0, 2.0], [13.0, 14.0], [5.0, 5.0]]), sq)
    assert d[0] == pytest.approx(2.0) and n[0] == pytest.approx([0.0, -1.0])
    assert d[1] == pytest.approx(-5.0)  # to the corner (10, 10): 3-4-5
    assert d[2] == pytest.approx(5.0)
    assert inside_polygon(np.array([[5.0, 5.0], [-1.0, 5.0]]), sq).tolist() == [True, False]


def test_polygon_is_simple():
    assert polygon_is_simple(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]))
    assert not polygon_is_simple(np.array([[0, 0], [1, 1], [1, 0], [0, 1]]))  # a bow tie


def test_projection_refuses_far_points():
    g = LocalGnomonic(0.0, 0.0)
    with pytest.raises(ValueError, match="fence must be local"):
        g.forward(D(30.0), D(0.0))
