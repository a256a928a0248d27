"""Solid primitives of the simulated world and vectorised ray intersection.

Three convex solids cover everything the world needs: capsules (limbs, trunks), ellipsoids
(torsos, heads, tree crowns) and oriented boxes (structures, feet). All geometry is in world ENU
metres. Intersection functions take ray origins ``o`` (N,3) and unit directions ``d`` (N,3) and
return the nearest hit distance ``t`` (N,) along the ray, ``inf`` where the ray misses or the hit is
closer than ``t_min``; the ray origin is assumed to lie outside the solid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_EPS = 1e-12


@dataclass(frozen=True)
class Primitive:
    """One solid with a flat albedo (linear RGB, 0..1) and the person instance it belongs to.

    ``kind`` is ``"capsule"`` (``a``, ``b`` segment ends, ``radius``), ``"ellipsoid"`` (``center``,
    ``radii`` along the columns of ``rotation``) or ``"box"`` (``center``, ``radii`` = half
    extents along the columns of ``rotation``). ``instance`` is 0 for scenery, k > 0 for person k.
    """

    kind: str
    albedo: tuple[float, float, float]
    instance: int = 0
    a: np.ndarray | None = None
    b: np.ndarray | None = None
    radius: float = 0.0
    center: np.ndarray | None = None
    radii: np.ndarray | None = None
    rotation: np.ndarray | None = None

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) in world metres."""
        if self.kind == "capsule":
            lo = np.minimum(self.a, self.b) - self.radius
            hi = np.maximum(self.a, self.b) + self.radius
            return lo, hi
        half = np.abs(self.rotation) @ self.radii
        return self.center - half, self.center + half


def capsule(a, b, radius, albedo, instance=0) -> Primitive:
    return Primitive("capsule", tuple(albedo), instance, a=np.asarray(a, float),
                     b=np.asarray(b, float), radius=float(radius))


def ellipsoid(center, radii, rotation, albedo, instance=0) -> Primitive:
    return Primitive("ellipsoid", tuple(albedo), instance, center=np.asarray(center, float),
                     radii=np.asarray(radii, float), rotation=np.asarray(rotation, float))


def box(center, half_extents, rotation, albedo, instance=0) -> Primitive:
    return Primitive("box", tuple(albedo), instance, center=np.asarray(center, float),
                     radii=np.asarray(half_extents, float), rotation=np.asarray(rotation, float))


def intersect(prim: Primitive, o: np.ndarray, d: np.ndarray, t_min: float = 0.0) -> np.ndarray:
    """Nearest hit distance (N,) of rays with ``prim``; ``inf`` for a miss."""
    if prim.kind == "capsule":
        return intersect_capsule(o, d, prim.a, prim.b, prim.radius, t_min)
    if prim.kind == "ellipsoid":
        return intersect_ellipsoid(o, d, prim.center, prim.radii, prim.rotation, t_min)
    if prim.kind == "box":
        return intersect_box(o, d, prim.center, prim.radii, prim.rotation, t_min)
    raise ValueError(f"unknown primitive kind {prim.kind!r}")


def normal_at(prim: Primitive, p: np.ndarray) -> np.ndarray:
    """Outward unit normals (N,3) at surface points ``p`` (N,3)."""
    if prim.kind == "capsule":
        ba = prim.b - prim.a
        h = np.clip(((p - prim.a) @ ba) / max(ba @ ba, _EPS), 0.0, 1.0)
        n = p - (prim.a + h[:, None] * ba)
    elif prim.kind == "ellipsoid":
        local = (p - prim.center) @ prim.rotation
        n = (local / prim.radii**2) @ prim.rotation.T
    else:
        local = (p - prim.center) @ prim.rotation
        rel = np.abs(local) / prim.radii
        axis = np.argmax(rel, axis=1)
        n_local = np.zeros_like(local)
        rows = np.arange(len(local))
        n_local[rows, axis] = np.sign(local[rows, axis])
        n = n_local @ prim.rotation.T
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(norm, _EPS)


def intersect_capsule(o, d, a, b, r, t_min=0.0) -> np.ndarray:
    """Ray-capsule distance: the cylinder body between ``a`` and ``b`` plus two hemispheres."""
    ba = b - a
    oa = o - a
    baba = float(ba @ ba)
    bard = d @ ba
    baoa = oa @ ba
    rdoa = np.einsum("ij,ij->i", d, oa)
    oaoa = np.einsum("ij,ij->i", oa, oa)
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa * baoa - r * r * baba
    h = qb * qb - qa * qc
    t = np.full(len(o), np.inf)
    body = (qa > 1e-9 * baba) & (h >= 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_body = (-qb - np.sqrt(np.maximum(h, 0.0))) / qa
    y = baoa + t_body * bard
    body &= (y > 0.0) & (y < baba) & (t_body > t_min)
    t[body] = t_body[body]
    # Caps: whichever hemisphere the infinite-cylinder hit (or the axis-parallel ray) points to.
    for end in (a, b):
        oc = o - end
        bb = np.einsum("ij,ij->i", d, oc)
        cc = np.einsum("ij,ij->i", oc, oc) - r * r
        hh = bb * bb - cc
        ok = hh >= 0.0
        t_cap = -bb - np.sqrt(np.maximum(hh, 0.0))
        ok &= t_cap > t_min
        t = np.where(ok & (t_cap < t), t_cap, t)
    return t


def intersect_ellipsoid(o, d, center, radii, rotation, t_min=0.0) -> np.ndarray:
    """Ray-ellipsoid distance via the unit sphere in the ellipsoid's scaled frame."""
    ol = ((o - center) @ rotation) / radii
    dl = (d @ rotation) / radii
    qa = np.einsum("ij,ij->i", dl, dl)
    qb = np.einsum("ij,ij->i", ol, dl)
    qc = np.einsum("ij,ij->i", ol, ol) - 1.0
    h = qb * qb - qa * qc
    ok = h >= 0.0
    t_hit = (-qb - np.sqrt(np.maximum(h, 0.0))) / np.maximum(qa, _EPS)
    ok &= t_hit > t_min
    return np.where(ok, t_hit, np.inf)


def intersect_box(o, d, center, half, rotation, t_min=0.0) -> np.ndarray:
    """Ray-oriented-box distance by the slab method."""
    ol = (o - center) @ rotation
    dl = d @ rotation
    dl = np.where(np.abs(dl) < _EPS, _EPS, dl)
    inv = 1.0 / dl
    t0 = (-half - ol) * inv
    t1 = (half - ol) * inv
    t_near = np.minimum(t0, t1).max(axis=1)
    t_far = np.maximum(t0, t1).min(axis=1)
    ok = (t_near <= t_far) & (t_near > t_min)
    return np.where(ok, t_near, np.inf)
