"""Scene bounds and model sizing: model only what the scene needs.

Bounds (world ENU metres): a *ground slab* box.
- Ground height: the 5th percentile of sparse SfM point heights when a point cloud exists
  (``derived/points.ply``, ``derived/points3D.txt`` or ``derived/colmap/**/points3D.txt``), else the
  telemetry fallback z = 0 (the ENU origin is the take-off point, on the ground; a flight over
  sloping terrain should provide points).
- Slab top: the 99.5th percentile of point heights above the ground (the tallest object) + 10 %,
  else the fallback ``0.7 x`` the lowest camera height above the ground (a camera sees down onto
  what it overflies; capped at 30 m).
- Floor (rays that reach it end opaque there): ``floor_margin_m`` below the ground estimate, and with
  sparse points that far below their 0.5th height percentile; the static fit takes 0.1 m (a view from
  above sees the floor wherever the field left the ground as fog), the dynamic fit the older rule,
  5 % of the slab's height and at least 0.5 m.
- Horizontal extent: where training rays (a sparse pixel grid of every frame) hit the ground, limited
  to ``max_range_factor x`` the camera height so near-horizontal rays do not stretch the box to the
  horizon; the ``100 - coverage_pct`` to ``coverage_pct`` percentiles of those hits, plus a margin
  (2 m). The static fit takes every hit (``coverage_pct=100``: what a higher view sees beyond the
  trimmed box was seen by the data and is modelled as geometry); the dynamic fit the 2nd-98th
  percentiles. Beyond the box: the cheap background.

Sizing: the finest cell is the finest ground sample distance of the training frames (5th
percentile of metres per pixel where the rays hit the ground: no finer than the data), the
coarsest about 1/16 of the extent; levels grow geometrically by <= 1.5x; the hash table holds
about as many entries as the finest level has surface cells (area / cell^2), rounded to a power of
two and shrunk until the model fits the size budget. Planes take the same finest cell, capped by
the budget. Every number and the reasoning go into ``fit.json``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from telemetry.camera import Camera

log = logging.getLogger(__name__)


@dataclass
class SceneBounds:
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    ground_z: float
    source: str
    finest_gsd_m: float
    median_gsd_m: float
    notes: list[str] = field(default_factory=list)

    @property
    def extent(self) -> np.ndarray:
        return np.asarray(self.hi) - np.asarray(self.lo)

    def to_json(self) -> dict:
        return asdict(self)


def find_sparse_points(flight: Path) -> np.ndarray | None:
    """(N, 3) ENU points from an SfM point cloud in ``derived/`` if there is one, else None."""
    derived = Path(flight) / "derived"
    ply = derived / "points.ply"
    if ply.is_file():
        return _read_ply_xyz(ply)
    for txt in [derived / "points3D.txt", *sorted(derived.glob("colmap/**/points3D.txt"))]:
        if txt.is_file():
            rows = [line.split() for line in txt.read_text().splitlines() if line and not line.startswith("#")]
            if rows:
                return np.array([[float(r[1]), float(r[2]), float(r[3])] for r in rows])
    return None


def _read_ply_xyz(path: Path) -> np.ndarray | None:
    """x, y, z of an ASCII or binary little-endian PLY vertex element (float/double properties)."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if end < 0:
        return None
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[data.index(b"\n", end) + 1:]
    fmt, n, props = "ascii", 0, []
    in_vertex = False
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = int(parts[2])
        elif parts[0] == "property" and in_vertex:
            props.append((parts[-1], parts[1]))
    names = [p[0] for p in props]
    if n == 0 or not {"x", "y", "z"} <= set(names):
        return None
    if fmt == "ascii":
        arr = np.loadtxt(body.decode().splitlines()[:n], ndmin=2)
    else:
        types = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1",
                 "uint8": "u1", "int": "<i4", "int32": "<i4", "uint": "<u4", "short": "<i2", "ushort": "<u2"}
        dt = np.dtype([(nm, types[t]) for nm, t in props])
        rec = np.frombuffer(body, dtype=dt, count=n)
        arr = np.stack([rec[nm].astype(np.float64) for nm in names], axis=1)
    return arr[:, [names.index("x"), names.index("y"), names.index("z")]]


def frame_ground_hits(camera: Camera, cam_from_world: np.ndarray, uv: np.ndarray, ground_z: float):
    """Where the rays of pixels ``uv`` (M, 2) of one frame (world-to-camera 4x4) meet the plane
    ``z = ground_z``: ground points xy (K, 2) ENU m, their distances along the unit rays (K,) m, the
    rays' directions (K, 3), and the camera's height above the plane (m). Rays not going down are dropped."""
    o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
    down = d[:, 2] < -1e-6
    t = (ground_z - o[2]) / np.where(down, d[:, 2], -1.0)
    ok = down & (t > 0)
    return o[:2] + t[ok, None] * d[ok, :2], t[ok], d[ok], float(o[2] - ground_z)


def ground_hits(camera: Camera, cam_from_world: list[np.ndarray], ground_z: float, step_px: int = 16):
    """Ground points (M, 2) and metres-per-pixel there (M,) for a sparse pixel grid of every frame."""
    uv = camera.pixel_grid()[::step_px, ::step_px].reshape(-1, 2)
    f = 0.5 * (camera.fx + camera.fy)
    pts, gsd, heights = [], [], []
    for T in cam_from_world:
        xy, t, d, height = frame_ground_hits(camera, T, uv, ground_z)
        heights.append(height)
        pts.append(xy)
        # metres per pixel along the ray at distance t, projected onto the ground (obliquity)
        gsd.append(t / f / np.maximum(np.abs(d[:, 2]), 0.2))
    return np.concatenate(pts), np.concatenate(gsd), np.asarray(heights)


def scene_bounds(flight: Path | None, camera: Camera, cam_from_world: list[np.ndarray],
                 max_range_factor: float = 4.0, margin_m: float = 2.0,
                 coverage_pct: float = 98.0, floor_margin_m: float | None = None) -> SceneBounds:
    """The ground slab for a flight (see the module docstring). Horizontally, the box spans the
    ``100 - coverage_pct`` to ``coverage_pct`` percentiles of the training rays' ground hits (within
    reach) plus ``margin_m`` metres; ``coverage_pct=100`` takes every ground point a training ray saw.
    Its floor lies ``floor_margin_m`` below the ground estimate, and with sparse points at least that far
    below their 0.5th height percentile (sloping ground reaches below the 5th percentile); None: 5 % of
    the slab's height, at least 0.5 m, below the ground estimate."""
    if not 50.0 < coverage_pct <= 100.0:
        raise ValueError(f"coverage_pct must be in (50, 100], got {coverage_pct}")
    if floor_margin_m is not None and not (0.0 < floor_margin_m < math.inf):
        raise ValueError(f"floor_margin_m must be positive and finite, got {floor_margin_m}")
    notes = []
    points = find_sparse_points(Path(flight)) if flight is not None else None
    centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in cam_from_world])
    if points is not None and len(points) >= 50:
        z = points[:, 2]
        ground = float(np.percentile(z, 5))
        lowest = float(np.percentile(z, 0.5))  # sloping ground reaches below the ground estimate
        top = ground + 1.1 * max(float(np.percentile(z, 99.5)) - ground, 1.0)
        source = "sparse points"
        notes.append(f"ground z {ground:.2f} m = 5th pct of {len(points)} sparse points; top = 99.5th pct + 10 %")
    else:
        ground = lowest = 0.0
        h_min = float((centres[:, 2] - ground).min())
        if h_min <= 0:
            raise ValueError(f"a camera is at or below the assumed ground (height {h_min:.2f} m)")
        top = ground + min(0.7 * h_min, 30.0)
        source = "telemetry"
        notes.append(f"no sparse points: ground z = 0 (take-off point), top = 0.7 x lowest camera height "
                     f"{h_min:.1f} m = {top - ground:.1f} m")
    hits, gsd, heights = ground_hits(camera, cam_from_world, ground)
    if len(hits) == 0:
        raise ValueError("no training ray reaches the ground: cannot bound the scene")
    reach = max_range_factor * float(np.median(heights))
    c = centres[:, :2].mean(0)
    near = np.linalg.norm(hits - c, axis=1) <= reach + np.linalg.norm(centres[:, :2] - c, axis=1).max()
    hits_k = hits[near] if near.sum() > 10 else hits
    lo_xy = np.percentile(hits_k, 100.0 - coverage_pct, axis=0) - margin_m
    hi_xy = np.percentile(hits_k, coverage_pct, axis=0) + margin_m
    if floor_margin_m is None:
        below = max(0.5, 0.05 * (top - ground))
    else:
        below = ground - lowest + float(floor_margin_m)
    bottom = ground - below
    notes.append(f"floor {bottom:.2f} m, {below:.2f} m below the ground: rays that reach it end there")
    notes.append(f"xy extent from {len(hits_k)} ground hits of training rays ({100 - coverage_pct:g}-"
                 f"{coverage_pct:g}th pct + {margin_m} m)")
    return SceneBounds((float(lo_xy[0]), float(lo_xy[1]), bottom), (float(hi_xy[0]), float(hi_xy[1]), top),
                       ground, source, float(np.percentile(gsd, 5)), float(np.median(gsd)), notes)


@dataclass
class Sizing:
    encoding: str
    resolutions: list
    features: int
    log2_table: int
    finest_cell_m: float
    coarsest_cell_m: float
    reasoning: list[str]


def hash_params(resolutions, features, log2_table) -> int:
    return sum(min((r[0] + 1) * (r[1] + 1) * (r[2] + 1), 2**log2_table) for r in resolutions) * features


def _plane_params(resolutions, features) -> int:
    return sum((r[0] * r[1] + r[0] * r[2] + r[1] * r[2]) for r in resolutions) * features


def size_model(bounds: SceneBounds, encoding: str = "hash", budget_mb: float = 16.0, features: int | None = None,
               coarsest_divisions: int = 16, max_growth: float = 1.5, cell_factor: float = 1.0) -> Sizing:
    """Resolutions and table size for the scene (see the module docstring). 4 bytes per parameter."""
    ext = bounds.extent
    finest = max(bounds.finest_gsd_m * cell_factor, 1e-3)
    coarsest = float(ext.max()) / coarsest_divisions
    why = [f"extent {ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} m ({bounds.source})",
           f"finest GSD {bounds.finest_gsd_m * 100:.1f} cm/px (5th pct; median {bounds.median_gsd_m * 100:.1f}) "
           f"-> finest cell {finest * 100:.1f} cm",
           f"coarsest cell {coarsest:.2f} m = longest side / {coarsest_divisions}"]
    budget = budget_mb * 1e6 / 4

    def res_for(cell):
        return tuple(max(2, int(math.ceil(e / cell))) for e in ext)

    if encoding == "hash":
        features = features or 2
        levels = int(min(16, max(4, math.ceil(math.log(coarsest / finest) / math.log(max_growth)) + 1)))
        cells = np.exp(np.linspace(math.log(coarsest), math.log(finest), levels))
        resolutions = [res_for(c) for c in cells]
        surface = ext[0] * ext[1] / finest**2
        log2 = int(min(22, max(14, math.ceil(math.log2(surface)))))
        why.append(f"{levels} levels, growth {(coarsest / finest) ** (1 / max(levels - 1, 1)):.2f}; "
                   f"finest-level surface cells {surface:.3g} -> table 2^{log2}")
        while log2 > 12 and hash_params(resolutions, features, log2) > budget:
            log2 -= 1
        why.append(f"table 2^{log2} x {features} features per level fits the {budget_mb:g} MB budget")
        return Sizing("hash", resolutions, features, log2, finest, coarsest, why)
    if encoding == "planes":
        features = features or 16
        scales = 3
        cell = finest
        while True:
            cells = [cell * 4, cell * 2, cell]
            resolutions = [res_for(c) for c in cells]
            if _plane_params(resolutions, features) <= budget:
                break
            cell *= 1.1
        why.append(f"{scales} scales (x1, x2, x4), {features} features; finest plane cell {cell * 100:.1f} cm "
                   f"(data allow {finest * 100:.1f} cm; limited by the {budget_mb:g} MB budget)"
                   if cell > finest * 1.01 else f"{scales} scales, {features} features, finest cell = data GSD")
        return Sizing("planes", resolutions, features, 16, cell, cells[0], why)
    raise ValueError(f"unknown encoding {encoding!r}; expected 'hash' or 'planes'")
