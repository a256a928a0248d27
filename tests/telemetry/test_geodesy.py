import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telemetry.geodesy import (
    WGS84_A,
    WGS84_B,
    GeodesyError,
    ecef_to_geodetic,
    enu_to_enu_transform,
    enu_to_geodetic,
    geodetic_to_ecef,
    geodetic_to_enu,
)

DEG_M_EQUATOR = 2 * np.pi * WGS84_A / 360.0  # metres per degree of longitude on the equator


def test_known_ecef_values():
    np.testing.assert_allclose(geodetic_to_ecef(0, 0, 0), [WGS84_A, 0, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(0, 90, 0), [0, WGS84_A, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(90, 0, 0), [0, 0, WGS84_B], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(-90, 123, 100), [0, 0, -WGS84_B - 100], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(0, 180, 0), [-WGS84_A, 0, 0], atol=1e-6)
    # 45 N 45 E on the ellipsoid: N = a / sqrt(1 - e2/2), x = y = N/2, z = N (1 - e2) sin 45.
    np.testing.assert_allclose(geodetic_to_ecef(45, 45, 0), [3194419.145, 3194419.145, 4487348.409], atol=2e-3)


def test_ecef_to_geodetic_at_poles_and_equator():
    lat, lon, h = ecef_to_geodetic([0, 0, WGS84_B + 10])
    assert lat == pytest.approx(90.0) and h == pytest.approx(10.0, abs=1e-6)
    lat, lon, h = ecef_to_geodetic([-WGS84_A - 5, 0, 0])
    assert lat == pytest.approx(0.0, abs=1e-12) and abs(lon) == pytest.approx(180.0) and h == pytest.approx(5.0)


@settings(max_examples=200, deadline=None)
@given(st.floats(-90, 90), st.floats(-180, 180), st.floats(-500, 20000))
def test_round_trip_everywhere(lat, lon, h):
    lat2, lon2, h2 = ecef_to_geodetic(geodetic_to_ecef(lat, lon, h))
    assert float(h2) == pytest.approx(h, abs=1e-4)
    assert float(lat2) == pytest.approx(lat, abs=1e-9)
    if abs(lat) < 89.9999:  # longitude is undefined at the pole
        dlon = (float(lon2) - lon + 180.0) % 360.0 - 180.0
        assert abs(dlon) < 1e-9


def test_enu_across_the_antimeridian():
    origin = (0.0, 179.9999, 0.0)
    e = geodetic_to_enu(0.0, -179.9999, 0.0, origin)
    assert e[0] == pytest.approx(0.0002 * DEG_M_EQUATOR, rel=1e-6)  # 22.26 m east, not 40 000 km west
    assert abs(e[1]) < 1e-6 and abs(e[2]) < 1e-3


def test_enu_at_high_latitude():
    origin = (89.99, 0.0, 100.0)
    # A point 90 degrees of longitude away, same latitude: distance = 2 r sin(45 deg), r = N cos(lat).
    lat = np.radians(89.99)
    n = WGS84_A / np.sqrt(1 - 0.00669437999014 * np.sin(lat) ** 2)
    r = (n + 100.0) * np.cos(lat)
    e = geodetic_to_enu(89.99, 90.0, 100.0, origin)
    assert np.linalg.norm(e[:2]) == pytest.approx(2 * r * np.sin(np.pi / 4), rel=1e-6)
    back = enu_to_geodetic(e, origin)
    assert float(back[0]) == pytest.approx(89.99, abs=1e-10)
    assert float(back[1]) == pytest.approx(90.0, abs=1e-8)


def test_enu_axes_point_east_north_up():
    origin = (47.0, 8.0, 400.0)
    e = geodetic_to_enu(47.0, 8.001, 400.0, origin)
    n = geodetic_to_enu(47.001, 8.0, 400.0, origin)
    u = geodetic_to_enu(47.0, 8.0, 410.0, origin)
    assert e[0] > 70 and abs(e[1]) < 0.01
    assert n[1] > 110 and abs(n[0]) < 1e-6
    np.testing.assert_allclose(u, [0, 0, 10], atol=1e-9)


@pytest.mark.parametrize("offset", [(1e5, -2e5, 3000.0), (-3.5e5, 4e5, -200.0), (0.001, 0.002, 0.003)])
def test_large_enu_offsets_round_trip_to_a_millimetre(offset):
    origin = (-33.8688, 151.2093, 58.0)
    lat, lon, h = enu_to_geodetic(np.array(offset), origin)
    np.testing.assert_allclose(geodetic_to_enu(lat, lon, h, origin), offset, atol=1e-3)


def test_vectorised_and_float64():
    origin = (10.0, 20.0, 30.0)
    pts = np.random.default_rng(0).normal(0, 500, (100, 3))
    lat, lon, h = enu_to_geodetic(pts, origin)
    assert lat.shape == (100,) and lat.dtype == np.float64
    np.testing.assert_allclose(geodetic_to_enu(lat, lon, h, origin), pts, atol=1e-6)


def test_enu_to_enu_transform_moves_points_between_origins():
    a, b = (47.0, 8.0, 400.0), (47.0003, 8.0004, 380.0)
    pts = np.random.default_rng(1).normal(0, 50, (10, 3))
    T = enu_to_enu_transform(a, b)
    lat, lon, h = enu_to_geodetic(pts, a)
    expected = geodetic_to_enu(lat, lon, h, b)
    np.testing.assert_allclose(pts @ T[:3, :3].T + T[:3, 3], expected, atol=1e-6)


def test_bad_input_is_a_clear_error():
    with pytest.raises(GeodesyError, match="latitude"):
        geodetic_to_ecef(91.0, 0.0, 0.0)
    with pytest.raises(GeodesyError, match="finite"):
        geodetic_to_enu(np.nan, 0.0, 0.0, (0, 0, 0))
