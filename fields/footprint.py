"""Where the data is sharp: the finest pixel footprint the training rays had, per ground cell, and
the hash-grid level weights it implies.

A 15 m orbit sees the ground under it at ~8 cm per pixel and the ground 40 m beyond it only from
the far side of the orbit, 55-65 m away, at ~25 cm. One hash grid spans both (:mod:`fields.scene`
sizes its finest level from the finest GSD of all the frames), so its finest levels are as fine as
the centre's data everywhere: where the data is coarser they cannot be determined, and their hashed
entries collide with the centre's. :func:`footprint_map` records, per xy cell of the scene box, the
finest footprint across the ray (``t / f``: metres a pixel spans at the ray's ground hit, not
foreshortened, since trees and walls are seen face-on) of any training ray that reached that cell.

:func:`level_weights` turns it into per-point, per-level weights as Zip-NeRF damps grid features
finer than a sample's footprint: a level of cell size ``c`` at a point whose finest footprint is
``p`` (a box of width ``p``, standard deviation ``p / sqrt(12)``) keeps
``erf(c / (sqrt(8) * p / sqrt(12)))`` of its features, 0.92 at ``c = p``, 0.61 at ``c = p / 2``,
0.33 at ``c = p / 4``. The weights depend on position only, so the field stays a function of the point
(the occupancy grid, the skip grid and renders at any altitude see one density), and a level damped
somewhere also learns proportionally less there (its gradient carries the same weight).

Frames: world ENU metres; cameras as world-to-camera 4x4 (``cam_from_world``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from fields.scene import frame_ground_hits
from telemetry.camera import Camera

#: sqrt(12) / sqrt(8): cell size over footprint width -> the erf argument (Zip-NeRF's downweighting)
_ERF_SCALE = math.sqrt(12.0) / math.sqrt(8.0)


def footprint_map(camera: Camera, cam_from_world: list[np.ndarray], lo_xy, hi_xy, ground_z: float,
                  cells: tuple[int, int] = (64, 64), step_px: int = 4) -> np.ndarray:
    """Finest across-ray pixel footprint (m) of the training rays' ground hits per xy cell.

    ``cam_from_world``: the training frames' world-to-camera transforms; ``lo_xy``, ``hi_xy``: the
    scene box's horizontal corners (ENU m); ``cells``: (cx, cy) cells along x and y; ``step_px``:
    every this-many pixels along each image axis casts a ray. Returns (cy, cx) float32 metres, row
    = y. Cells no ray reached (hidden, or the box's corners) take the coarsest footprint seen.
    """
    cx, cy = int(cells[0]), int(cells[1])
    lo = np.asarray(lo_xy, np.float64)[:2]
    hi = np.asarray(hi_xy, np.float64)[:2]
    if cx < 1 or cy < 1 or not np.all(hi > lo):
        raise ValueError(f"need >= 1 cell per axis and hi > lo, got cells {cells}, lo {lo}, hi {hi}")
    uv = camera.pixel_grid()[::step_px, ::step_px].reshape(-1, 2)
    f = 0.5 * (camera.fx + camera.fy)
    best = np.full(cy * cx, np.inf)
    for T in cam_from_world:
        xy, t, _, _ = frame_ground_hits(camera, T, uv, ground_z)
        ij = np.floor((xy - lo) / (hi - lo) * (cx, cy)).astype(np.int64)
        inside = (ij >= 0).all(1) & (ij[:, 0] < cx) & (ij[:, 1] < cy)
        np.minimum.at(best, ij[inside, 1] * cx + ij[inside, 0], t[inside] / f)
    seen = np.isfinite(best)
    if not seen.any():
        raise ValueError("no training ray reaches the ground inside the box")
    best[~seen] = best[seen].max()
    return best.reshape(cy, cx).astype(np.float32)


def level_weights(xy01: torch.Tensor, log_footprint: torch.Tensor, cell_m: torch.Tensor) -> torch.Tensor:
    """Per-point, per-level feature weights in (0, 1].

    ``xy01`` (N, 2): the points' x, y in the box's unit square (clamped to its edges);
    ``log_footprint`` (cy, cx): log of :func:`footprint_map` (metres), read bilinearly;
    ``cell_m`` (L,): each level's cell size, m. Returns (N, L) ``erf(c / (sqrt(8) p / sqrt(12)))``
    (> 0 for any finite footprint).
    """
    g = (xy01.float().clamp(0.0, 1.0) * 2.0 - 1.0).view(1, -1, 1, 2)
    logp = F.grid_sample(log_footprint[None, None].float(), g, mode="bilinear", padding_mode="border",
                         align_corners=False).view(-1)
    ratio = cell_m.float()[None, :] * torch.exp(-logp)[:, None]
    return torch.erf(_ERF_SCALE * ratio)
