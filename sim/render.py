"""Ray-cast renderer of the simulated world: RGB, per-instance ids and tight boxes.

Each output pixel integrates an ``s x s`` stratified grid of rays (supersampling, as a real pixel
integrates light). Every ray hits the ground plane (z = 0), a solid, or the sky. Shading is
Lambertian: a sun with a finite disc (each sample takes its own point of the disc, so cast
shadows have soft edges) plus a hemispherical sky term; distant surfaces fade into haze. Work is
kept proportional to what is visible: a solid is only intersected with the rays inside its
projected bounding box, and only tested as a shadow caster for the points inside the projection
of its shadow volume.

Instance ids: a pixel belongs to the person that covers the most of its samples if that is at least
half of them (so a half-covered pixel counts as the person's for even supersampling). A person's
box is the pixel-edge extent of its pixels (x0, y0 inclusive, x1, y1 exclusive, in pixels); people
with fewer than ``min_visible_px`` pixels (including fully occluded ones) get no box.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from sim.primitives import Primitive, intersect, normal_at
from telemetry.camera import Camera

SUN_RGB = 2.3 * np.array([1.0, 0.97, 0.9], np.float32)
SKY_AMBIENT_RGB = 0.55 * np.array([0.75, 0.85, 1.0], np.float32)
HAZE_RGB = np.array([0.62, 0.70, 0.82], np.float32)
HAZE_DISTANCE_M = 2500.0
MIN_VISIBLE_PX = 4


@dataclass(frozen=True)
class Box:
    """A person's tight box in pixels (edges) and how many pixels of it are visible."""

    instance: int
    class_id: int
    x0: float
    y0: float
    x1: float
    y1: float
    visible_px: int

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    @property
    def height(self) -> float:
        return self.y1 - self.y0

    def yolo(self, width: int, height: int) -> str:
        """``class cx cy w h`` normalised to the image size (YOLO label line)."""
        cx = 0.5 * (self.x0 + self.x1) / width
        cy = 0.5 * (self.y0 + self.y1) / height
        return f"{self.class_id} {cx:.6f} {cy:.6f} {self.width / width:.6f} {self.height / height:.6f}"


@dataclass
class RenderResult:
    rgb: np.ndarray  # (H, W, 3) uint8, sRGB
    instance_ids: np.ndarray  # (H, W) uint16, 0 = not a person
    classes: dict[int, int]  # instance -> class id, for every person in the world
    boxes: list[Box]

    def yolo_labels(self) -> str:
        h, w = self.instance_ids.shape
        return "".join(b.yolo(w, h) + "\n" for b in self.boxes)


def _screen_rect(points_world, camera: Camera, cam_from_world, s: int, margin_px: float = 2.0):
    """Supersampled (row0, row1, col0, col1) covering the projection of ``points``, or None."""
    uv, in_front = camera.project_world(points_world, cam_from_world)
    if not in_front.any():
        return None
    H, W = camera.height * s, camera.width * s
    if not in_front.all():
        return 0, H, 0, W
    lo = np.floor((uv.min(axis=0) - margin_px) * s).astype(int)
    hi = np.ceil((uv.max(axis=0) + margin_px) * s).astype(int)
    c0, r0 = max(lo[0], 0), max(lo[1], 0)
    c1, r1 = min(hi[0], W), min(hi[1], H)
    if c0 >= c1 or r0 >= r1:
        return None
    return r0, r1, c0, c1


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])])


def _sun_basis(sun_dir: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to ``sun_dir``."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(sun_dir[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(sun_dir, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(sun_dir, e1)


def _sun_table(sun_dir: np.ndarray, radius_deg: float, s: int) -> np.ndarray:
    """``s*s`` directions stratified over the sun's disc, one per sub-pixel sample position.

    Every pixel integrates the whole disc (one direction per sample), so penumbrae come out
    smooth without per-ray noise.
    """
    e1, e2 = _sun_basis(sun_dir)
    a, b = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    r = np.tan(np.radians(radius_deg)) * np.sqrt((a.ravel() + 0.5) / s)
    phi = 2 * np.pi * (b.ravel() + 0.5 * (a.ravel() % 2) + 0.5) / s
    d = sun_dir + (r * np.cos(phi))[:, None] * e1 + (r * np.sin(phi))[:, None] * e2
    # scramble which sub-pixel gets which disc point so neighbours differ
    perm = np.random.default_rng(7).permutation(s * s)
    return (d / np.linalg.norm(d, axis=1, keepdims=True))[perm]


def render(world, camera: Camera, cam_from_world, t: float = 0.0, supersample: int = 3,
           min_visible_px: int = MIN_VISIBLE_PX) -> RenderResult:
    """Render ``world`` seen by ``camera`` at OpenCV ``cam_from_world`` (4x4) and time ``t`` (s)."""
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    T = np.asarray(cam_from_world, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError("cam_from_world must be a finite 4x4 matrix")
    H, W = camera.height, camera.width
    origin, dirs = camera.rays_world(T, camera.pixel_grid(s))  # dirs (H*s, W*s, 3)
    dirs = dirs.astype(np.float32)  # unit vectors; hit points stay precise to ~1e-5 m at 100 m
    HS, WS = H * s, W * s

    # Ground plane.
    dz = dirs[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hit = np.where((dz < -1e-12) & (origin[2] > 0.0), -origin[2] / dz, np.inf)
    hit = np.full((HS, WS), -1, np.int32)  # -1: ground or sky, k >= 0: primitive k

    prims: list[Primitive] = world.primitives(t)
    boxes_ss = []
    for k, prim in enumerate(prims):
        lo, hi = prim.aabb()
        rect = _screen_rect(_corners(lo, hi), camera, T, s)
        boxes_ss.append(rect)
        if rect is None:
            continue
        r0, r1, c0, c1 = rect
        d_sub = dirs[r0:r1, c0:c1].reshape(-1, 3)
        th = intersect(prim, np.broadcast_to(origin, d_sub.shape), d_sub).reshape(r1 - r0, c1 - c0)
        view_t = t_hit[r0:r1, c0:c1]
        closer = th < view_t
        if closer.any():
            view_t[closer] = th[closer]
            hit[r0:r1, c0:c1][closer] = k

    surface = np.isfinite(t_hit)
    flat_t = t_hit.reshape(-1)
    flat_hit = hit.reshape(-1)
    flat_dirs = dirs.reshape(-1, 3)
    idx = np.nonzero(surface.reshape(-1))[0]
    P = origin.astype(np.float32) + flat_t[idx].astype(np.float32)[:, None] * flat_dirs[idx]
    normals = np.zeros((len(idx), 3))
    normals[:, 2] = 1.0
    albedo = np.zeros((len(idx), 3), np.float32)
    on_prim = flat_hit[idx] >= 0
    ground_rows = np.nonzero(~on_prim)[0]
    if len(ground_rows):
        gi = idx[ground_rows]
        # Sample footprint on the ground: range / focal, stretched by the grazing angle.
        cos_in = np.abs(flat_dirs[gi, 2])
        f = 0.5 * (camera.fx + camera.fy) * s
        footprint = flat_t[gi] / f / np.sqrt(np.maximum(cos_in, 1e-3))
        albedo[ground_rows] = world.texture.sample(P[ground_rows, 0], P[ground_rows, 1], footprint)
    prim_rows = np.nonzero(on_prim)[0]
    if len(prim_rows):
        prim_of = flat_hit[idx[prim_rows]]
        order = np.argsort(prim_of, kind="stable")
        uniq, starts = np.unique(prim_of[order], return_index=True)
        bounds = list(starts[1:]) + [len(order)]
        for k, a, b in zip(uniq, starts, bounds, strict=True):
            rows = prim_rows[order[a:b]]
            normals[rows] = normal_at(prims[k], P[rows])
            albedo[rows] = prims[k].albedo

    # Soft shadows: per-sample sun directions, shadow rays only against nearby casters.
    sd = world.sun_dir
    sub_index = (idx // WS % s) * s + (idx % WS % s)
    sun = _sun_table(sd, world.config.sun_radius_deg, s)[sub_index]
    lit = np.ones(len(idx), bool)
    pos_of_flat = np.full(HS * WS, -1, np.int64)
    pos_of_flat[idx] = np.arange(len(idx))
    # Cheap pre-test: position across the sun beam and along it, per surface point.
    e1, e2 = _sun_basis(sd)
    across = P @ np.stack([e1, e2], axis=1)
    along = P @ sd
    spread = np.tan(np.radians(world.config.sun_radius_deg))
    for k, prim in enumerate(prims):
        lo, hi = prim.aabb()
        corners = _corners(lo, hi)
        # Extend the caster's box down its shadow to the ground plane.
        drop = corners - sd[None, :] * (corners[:, 2:3] / max(sd[2], 0.05))
        rect = _screen_rect(np.vstack([corners, drop]), camera, T, s, margin_px=3.0)
        if rect is None:
            continue
        r0, r1, c0, c1 = rect
        flat = (np.arange(r0, r1)[:, None] * WS + np.arange(c0, c1)[None, :]).reshape(-1)
        rows = pos_of_flat[flat]
        rows = rows[rows >= 0]
        if len(rows) == 0:
            continue
        centre = 0.5 * (lo + hi)
        reach = 0.5 * float(np.linalg.norm(hi - lo))
        gap = np.maximum(centre @ sd - along[rows], 0.0)
        near = np.sum((across[rows] - centre @ np.stack([e1, e2], axis=1)) ** 2, axis=1)
        rows = rows[(near <= (reach + spread * gap + 0.05) ** 2) & (along[rows] < centre @ sd + reach)
                    & lit[rows] & (flat_hit[idx[rows]] != k)]
        if len(rows) == 0:
            continue
        o_sh = P[rows] + 2e-3 * normals[rows]
        ts = intersect(prim, o_sh, sun[rows], t_min=1e-4)
        lit[rows[np.isfinite(ts)]] = False

    n_dot_l = np.clip(np.einsum("ij,ij->i", normals, sun), 0.0, None)
    sky_term = (0.6 + 0.4 * normals[:, 2]).astype(np.float32)
    light = (SUN_RGB[None, :] * (n_dot_l * lit)[:, None].astype(np.float32)
             + SKY_AMBIENT_RGB[None, :] * sky_term[:, None])
    colour_surf = albedo * light
    haze = (1.0 - np.exp(-flat_t[idx].astype(np.float32) / np.float32(HAZE_DISTANCE_M)))[:, None]
    colour_surf += (HAZE_RGB[None, :] - colour_surf) * haze

    colour = np.empty((HS * WS, 3), np.float32)
    colour[idx] = colour_surf
    sky = np.flatnonzero(~surface.reshape(-1))
    if len(sky):
        up = np.clip(flat_dirs[sky, 2], 0.0, 1.0)[:, None]
        colour[sky] = HAZE_RGB * (1.0 - up) + np.array([0.25, 0.42, 0.75], np.float32) * up
    # Box filter over each pixel's s x s samples (INTER_AREA is the exact mean for integer factors).
    lin = cv2.resize(colour.reshape(HS, WS, 3), (W, H), interpolation=cv2.INTER_AREA) if s > 1 \
        else colour.reshape(H, W, 3)
    rgb = (np.clip(lin, 0.0, 1.0) ** (1.0 / 2.2) * 255.0 + 0.5).astype(np.uint8)

    # Instance ids: the person covering the majority of each pixel's samples.
    inst_of_prim = np.array([p.instance for p in prims] + [0], np.int32)
    inst_ss = inst_of_prim[hit].reshape(H, s, W, s).transpose(0, 2, 1, 3).reshape(H, W, s * s)
    instance_ids = np.zeros((H, W), np.uint16)
    touched = inst_ss.any(axis=-1)
    if touched.any():
        samples = inst_ss[touched]  # (M, s*s)
        best = np.zeros(len(samples), np.int32)
        best_count = np.zeros(len(samples), np.int32)
        for j in range(s * s):
            cand = samples[:, j]
            count = (samples == cand[:, None]).sum(axis=-1)
            better = (count > best_count) & (cand != 0)
            best[better] = cand[better]
            best_count[better] = count[better]
        instance_ids[touched] = np.where(2 * best_count >= s * s, best, 0)

    classes = {p.instance: p.class_id for p in world.people}
    boxes: list[Box] = []
    if instance_ids.any():
        counts = np.bincount(instance_ids.ravel())
        for inst, sl in enumerate(ndimage.find_objects(instance_ids.astype(np.int32)), start=1):
            if sl is None or counts[inst] < min_visible_px:
                continue
            boxes.append(Box(inst, classes.get(inst, 0), float(sl[1].start), float(sl[0].start),
                             float(sl[1].stop), float(sl[0].stop), int(counts[inst])))
    return RenderResult(rgb=rgb, instance_ids=instance_ids, classes=classes, boxes=boxes)
