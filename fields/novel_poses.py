"""Novel camera poses for synthesis: new altitudes, pitches and orbit radii (static scenes), or
points on the real trajectory at t and t ± Δt (dynamic scenes).

All poses are OpenCV ``cam_from_world`` 4x4 in the flight's world frame (local ENU metres); the
ground is the plane ``z = ground_z``. A field can only render what the real frames saw, so every
static candidate is checked against the *observed region*: the ground cells seen by at least
``min_views`` real frames. Candidates whose image shows more than ``max_outside_fraction`` of
unobserved ground (or sky) are dropped, with the reason kept.

Trajectories: each one is an arc of an orbit around the scene centre at one altitude and camera
pitch, the camera looking at the centre (so the orbit radius follows from altitude and pitch:
``radius = altitude / tan(-pitch)``, plus an optional aim offset); poses along the arc are evenly
spaced in azimuth, so consecutive images form a smooth flight.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from telemetry.camera import Camera
from telemetry.frames import camera_center, look_at
from telemetry.posesfile import PoseEntry

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NovelPoseOptions:
    """How static novel poses are sampled. Angles in degrees, distances in metres."""

    altitudes_m: tuple[float, ...] = (20.0, 30.0, 40.0, 50.0)
    pitch_deg: tuple[float, float] = (-90.0, -50.0)  # uniform range; -90 is nadir
    #: horizontal offset of the aim point from the scene centre (uniform in a disc of this radius)
    aim_jitter_m: float = 3.0
    count: int = 40
    poses_per_trajectory: int = 5
    #: azimuth step between consecutive poses of a trajectory
    arc_step_deg: float = 12.0
    max_outside_fraction: float = 0.1
    min_views: int = 2
    seed: int = 0
    #: give up after this many candidates per requested pose
    attempts_per_pose: int = 20


@dataclass
class ObservedRegion:
    """Ground cells (``cell_m`` square) seen by real frames: ``counts[row, col]`` views each.

    Cell (0, 0) has its lower-left corner at ``origin_xy`` (ENU); rows go north (+y).
    """

    origin_xy: np.ndarray
    cell_m: float
    counts: np.ndarray
    ground_z: float = 0.0
    max_range_m: float = 250.0

    def seen(self, xy: np.ndarray, min_views: int) -> np.ndarray:
        ij = np.floor((np.asarray(xy) - self.origin_xy) / self.cell_m).astype(np.int64)
        h, w = self.counts.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.zeros(len(ij), bool)
        out[inside] = self.counts[ij[inside, 1], ij[inside, 0]] >= min_views
        return out


@dataclass
class NovelPose:
    cam_from_world: np.ndarray
    altitude_m: float
    pitch_deg: float
    radius_m: float
    azimuth_deg: float
    outside_fraction: float
    trajectory: int
    kept: bool = True
    reason: str | None = None
    extra: dict = field(default_factory=dict)

    def entry(self, frame: str | None = None, t_unix_us: int | None = None) -> PoseEntry:
        """The poses-file entry (``source: novel``) with the sampling parameters as extras."""
        return PoseEntry(frame, t_unix_us, self.cam_from_world, "novel", extra={
            "altitude_m": round(self.altitude_m, 3), "pitch_deg": round(self.pitch_deg, 3),
            "radius_m": round(self.radius_m, 3), "azimuth_deg": round(self.azimuth_deg, 3),
            "outside_fraction": round(self.outside_fraction, 4), "trajectory": self.trajectory})


def _ground_hits(camera: Camera, cam_from_world: np.ndarray, ground_z: float, max_range_m: float,
                 grid: tuple[int, int] = (24, 18)):
    """Ground points (N,2) hit by a grid of pixel rays, and a (N,) mask of rays that hit in range."""
    u = (np.arange(grid[0]) + 0.5) * camera.width / grid[0]
    v = (np.arange(grid[1]) + 0.5) * camera.height / grid[1]
    uv = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    origin, dirs = camera.rays_world(cam_from_world, uv)
    dz = dirs[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ground_z - origin[2]) / dz
    ok = (dz < -1e-9) & (t > 0) & (t <= max_range_m)
    t = np.where(ok, t, 0.0)
    return origin[:2] + t[:, None] * dirs[:, :2], ok


def observed_region(camera: Camera, poses: list[np.ndarray], ground_z: float = 0.0,
                    cell_m: float = 0.5, max_range_m: float = 250.0) -> ObservedRegion:
    """Rasterise the real frames' ground footprints (convex hulls of their ray grids)."""
    hulls = []
    for T in poses:
        xy, ok = _ground_hits(camera, T, ground_z, max_range_m)
        if ok.sum() >= 3:
            hulls.append(cv2.convexHull(xy[ok].astype(np.float32)).reshape(-1, 2))
    if not hulls:
        raise ValueError("no real frame sees the ground: cannot tell which region was observed")
    allpts = np.vstack(hulls)
    lo = np.floor(allpts.min(axis=0) / cell_m) * cell_m - cell_m
    hi = np.ceil(allpts.max(axis=0) / cell_m) * cell_m + cell_m
    w, h = (np.round((hi - lo) / cell_m).astype(int) + 1).tolist()
    counts = np.zeros((h, w), np.int32)
    one = np.zeros((h, w), np.uint8)
    for hull in hulls:
        one[:] = 0
        cv2.fillConvexPoly(one, np.round((hull - lo) / cell_m).astype(np.int32), 1)
        counts += one
    return ObservedRegion(lo, cell_m, counts, ground_z, max_range_m)


def outside_fraction(camera: Camera, cam_from_world: np.ndarray, region: ObservedRegion,
                     min_views: int = 2) -> float:
    """Share of the image showing sky, far ground, or ground fewer than ``min_views`` frames saw."""
    xy, ok = _ground_hits(camera, cam_from_world, region.ground_z, region.max_range_m)
    good = ok & region.seen(xy, min_views)
    return float(1.0 - good.mean())


def scene_centre(camera: Camera, poses: list[np.ndarray], ground_z: float = 0.0) -> np.ndarray:
    """Where the real frames look: median ground hit of their optical axes (ENU, z = ground)."""
    hits = []
    for T in poses:
        xy, ok = _ground_hits(camera, T, ground_z, 1e4, grid=(1, 1))
        if ok[0]:
            hits.append(xy[0])
    if not hits:  # cameras looking at the horizon: fall back to below the cameras
        hits = [camera_center(T)[:2] for T in poses]
    c = np.median(np.asarray(hits), axis=0)
    return np.array([c[0], c[1], ground_z])


def static_novel_poses(camera: Camera, real_poses: list[np.ndarray], options: NovelPoseOptions,
                       ground_z: float = 0.0, centre: np.ndarray | None = None,
                       region: ObservedRegion | None = None) -> list[NovelPose]:
    """Sample ``options.count`` kept poses (plus the dropped candidates, ``kept=False``).

    Altitudes are metres above the ground plane. Altitudes cycle through ``altitudes_m`` so each
    gets an equal share. Raises ValueError when no real poses are given.
    """
    if not real_poses:
        raise ValueError("no posed real frames: novel poses need the observed scene")
    lo, hi = sorted(options.pitch_deg)
    if not (-90.0 <= lo and hi < 0.0):
        raise ValueError(f"pitch range must lie in [-90, 0) deg, got {options.pitch_deg}")
    if not options.altitudes_m or min(options.altitudes_m) <= 0:
        raise ValueError(f"altitudes must be positive metres, got {options.altitudes_m}")
    rng = np.random.default_rng(options.seed)
    region = region or observed_region(camera, real_poses, ground_z)
    centre = scene_centre(camera, real_poses, ground_z) if centre is None else np.asarray(centre, float)
    kept: list[NovelPose] = []
    dropped: list[NovelPose] = []
    budget = options.count * options.attempts_per_pose
    trajectory = 0
    while len(kept) < options.count and budget > 0:
        alt = float(options.altitudes_m[trajectory % len(options.altitudes_m)])
        pitch = float(rng.uniform(lo, hi))
        r_aim = options.aim_jitter_m * np.sqrt(rng.random())
        th = rng.uniform(0, 2 * np.pi)
        aim = centre + np.array([r_aim * np.cos(th), r_aim * np.sin(th), 0.0])
        radius = alt / np.tan(np.radians(-pitch)) if pitch > -89.999 else 0.0
        az0 = rng.uniform(0, 360.0)
        for j in range(options.poses_per_trajectory):
            if len(kept) >= options.count or budget <= 0:
                break
            budget -= 1
            az = az0 + j * options.arc_step_deg
            eye = aim + np.array([radius * np.cos(np.radians(az)), radius * np.sin(np.radians(az)), alt])
            if radius < 1e-6:
                # nadir: point the image top along the arc direction so the trajectory still turns
                up = np.array([np.cos(np.radians(az)), np.sin(np.radians(az)), 0.0])
                T = look_at(eye, aim, up_enu=up)
            else:
                T = look_at(eye, aim)
            frac = outside_fraction(camera, T, region, options.min_views)
            pose = NovelPose(T, alt, pitch, radius, az % 360.0, frac, trajectory)
            if frac > options.max_outside_fraction:
                pose.kept = False
                pose.reason = (f"{frac:.0%} of the view is outside the observed region "
                               f"(limit {options.max_outside_fraction:.0%})")
                dropped.append(pose)
            else:
                kept.append(pose)
        trajectory += 1
    if len(kept) < options.count:
        log.warning("only %d of %d novel poses stay inside the observed region (%d dropped); "
                    "lower the altitudes or raise max_outside_fraction", len(kept), options.count,
                    len(dropped))
    return kept + dropped


def dynamic_novel_poses(entries: list[PoseEntry], n_points: int, frame_rate_hz: float) -> list[PoseEntry]:
    """N points on the real trajectory, each at t - Δt, t, t + Δt (Δt = 1 / frame rate): 3N poses.

    ``entries`` are posed real frames with capture times (unix µs). Points are spread evenly over
    the flight. The returned entries keep the real pose and set ``t_unix_us`` (scene time).
    """
    if frame_rate_hz <= 0 or not np.isfinite(frame_rate_hz):
        raise ValueError(f"frame rate must be a positive number of Hz, got {frame_rate_hz}")
    timed = sorted((e for e in entries if e.posed and e.t_unix_us is not None), key=lambda e: e.t_unix_us)
    if not timed:
        raise ValueError("no posed frames with capture times: dynamic synthesis needs the trajectory")
    n = min(int(n_points), len(timed))
    if n <= 0:
        return []
    picks = np.unique(np.round(np.linspace(0, len(timed) - 1, n)).astype(int))
    dt_us = int(round(1e6 / frame_rate_hz))
    out = []
    for i in picks:
        e = timed[i]
        for k in (-1, 0, 1):
            out.append(PoseEntry(None, e.t_unix_us + k * dt_us, e.cam_from_world.copy(), "novel",
                                 extra={"from_frame": e.frame, "dt_steps": k}))
    return out


def raised_along_axis(cam_from_world: np.ndarray, scale: float, ground_z: float = 0.0) -> np.ndarray:
    """The camera moved back along its optical axis until its distance to the ground point (plane
    ``z = ground_z``) on that axis is ``scale`` times larger, same attitude: the same ground point in
    the centre, seen from higher up (scale 2 from 15 m above the ground: 30 m). OpenCV
    ``cam_from_world``, ENU metres."""
    T = np.asarray(cam_from_world, dtype=np.float64)
    if not np.isfinite(T).all() or not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"need a finite pose and a positive scale, got scale {scale}")
    R = T[:3, :3]
    centre = -R.T @ T[:3, 3]
    axis = R[2]  # the optical axis (camera +z) in the world
    if axis[2] >= -1e-6 or centre[2] <= ground_z:
        raise ValueError("the camera does not look down at the ground from above it")
    reach = (ground_z - centre[2]) / axis[2]
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = -R @ (centre - axis * reach * (scale - 1.0))
    return out
