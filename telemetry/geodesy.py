"""WGS84 geodesy: geodetic (lat, lon, h) ↔ ECEF ↔ local ENU, all float64.

- geodetic: latitude and longitude in degrees, height in metres above the WGS84 ellipsoid. MAVLink
  GLOBAL_POSITION_INT carries AMSL altitude; over a flight-sized area the geoid undulation is a
  constant offset, so AMSL altitude can be used as the height of a *local* frame (the ENU origin and
  every point share the same offset, which cancels to well below a millimetre over kilometres).
- ECEF: earth-centred earth-fixed metres.
- ENU: local east-north-up metres at a geodetic origin (the tangent plane, not a map projection).

ECEF → geodetic uses Bowring's closed form followed by two Newton refinements; it is exact to well
below a millimetre everywhere including the poles and the antimeridian.
"""

from __future__ import annotations

import numpy as np

#: WGS84 semi-major axis, metres.
WGS84_A = 6378137.0
#: WGS84 flattening.
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)


class GeodesyError(ValueError):
    """Non-finite or out-of-range geodetic input."""


def _check_latlon(lat_deg, lon_deg) -> None:
    lat = np.asarray(lat_deg, dtype=np.float64)
    lon = np.asarray(lon_deg, dtype=np.float64)
    if not (np.isfinite(lat).all() and np.isfinite(lon).all()):
        raise GeodesyError(f"latitude/longitude must be finite, got {lat_deg!r}, {lon_deg!r}")
    if (np.abs(lat) > 90.0).any():
        raise GeodesyError(f"latitude must be within [-90, 90] deg, got {lat_deg!r}")


def geodetic_to_ecef(lat_deg, lon_deg, h_m) -> np.ndarray:
    """ECEF metres (..., 3) of geodetic points (degrees, degrees, metres above the ellipsoid)."""
    _check_latlon(lat_deg, lon_deg)
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    h = np.asarray(h_m, dtype=np.float64)
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    x = (n + h) * cl * np.cos(lon)
    y = (n + h) * cl * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sl
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(xyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat_deg, lon_deg, h_m) of ECEF points (..., 3); longitude in (-180, 180]."""
    p = np.asarray(xyz, dtype=np.float64)
    if not np.isfinite(p).all():
        raise GeodesyError("ECEF coordinates must be finite")
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    # Bowring's initial guess, then Newton-like refinement of the latitude.
    beta = np.arctan2(z * WGS84_A, r * WGS84_B)
    lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3, r - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    for _ in range(2):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
        lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
                         r - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    # Height: stable formula valid at all latitudes (including the poles where cl -> 0).
    h = r * cl + z * sl - WGS84_A * WGS84_A / n
    return np.degrees(lat), np.degrees(lon), h


def R_enu_from_ecef(lat_deg: float, lon_deg: float) -> np.ndarray:
    """3x3 rotation taking ECEF vectors to ENU vectors at the given geodetic point."""
    _check_latlon(lat_deg, lon_deg)
    lat, lon = np.radians(float(lat_deg)), np.radians(float(lon_deg))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-so, co, 0.0],
                     [-sl * co, -sl * so, cl],
                     [cl * co, cl * so, sl]])


def geodetic_to_enu(lat_deg, lon_deg, h_m, origin) -> np.ndarray:
    """ENU metres (..., 3) of geodetic points relative to ``origin`` = (lat_deg, lon_deg, h_m)."""
    lat0, lon0, h0 = (float(v) for v in origin)
    d = geodetic_to_ecef(lat_deg, lon_deg, h_m) - geodetic_to_ecef(lat0, lon0, h0)
    return d @ R_enu_from_ecef(lat0, lon0).T


def enu_to_geodetic(enu, origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat_deg, lon_deg, h_m) of ENU points (..., 3) relative to ``origin`` = (lat, lon, h)."""
    lat0, lon0, h0 = (float(v) for v in origin)
    e = np.asarray(enu, dtype=np.float64)
    if not np.isfinite(e).all():
        raise GeodesyError("ENU coordinates must be finite")
    xyz = geodetic_to_ecef(lat0, lon0, h0) + e @ R_enu_from_ecef(lat0, lon0)
    return ecef_to_geodetic(xyz)


def enu_to_enu_transform(origin_from, origin_to) -> np.ndarray:
    """4x4 rigid transform taking ENU points of ``origin_from`` to ENU points of ``origin_to``.

    Use it to move a ``cam_from_world`` between frames: ``cam_from_world_to = T_from @ inv(this)``.
    """
    lat_a, lon_a, h_a = (float(v) for v in origin_from)
    lat_b, lon_b, h_b = (float(v) for v in origin_to)
    R_a = R_enu_from_ecef(lat_a, lon_a)
    R_b = R_enu_from_ecef(lat_b, lon_b)
    T = np.eye(4)
    T[:3, :3] = R_b @ R_a.T
    T[:3, 3] = R_b @ (geodetic_to_ecef(lat_a, lon_a, h_a) - geodetic_to_ecef(lat_b, lon_b, h_b))
    return T
