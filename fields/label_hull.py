"""Occupancy cells the label boxes vouch for: where the training frames' boxes agree an object stands.

Why: the occupancy sampler (:class:`fields.samplers.OccupancySampler`) empties the cells whose
density is low at its first full refresh (step ``FitConfig.occupancy_warmup``), and an emptied cell
keeps only ``empty_share`` of the samples per metre. A person the field has not formed by then gets
about a sample every two rays. The label boxes say where the objects of interest are, so with
``FitConfig.occupancy_keep_share`` set those cells stay occupied whatever their density.

Measured (bench/RESULTS.md, static session 35): resuming a 300 s field in which one person had not
formed (its cells emptied), 90 s with the cells kept gave held-out box IoU 0.800 against 0.759
without. From scratch it did not stop that person failing (one of two 300 s fits), so it is off by
default: the emptied cells were a symptom, not the cause.

A cell is vouched for when at least ``min_views`` labelled frames see its centre (in front of the
camera, inside the image) and at least ``min_share`` of them put it inside one of their label boxes:
a visual hull of the boxes by vote, so a frame whose label misses a person (occluded, cut by the
border) does not veto the others. Only cells whose centre lies within ``max_height_m`` above the
ground are tested (people are under 2 m; the hull of a 45-degree orbit's boxes ends within a few
decimetres of the head).

Frames: ``cam_from_world`` OpenCV world-to-camera 4x4, world ENU metres; boxes are
``(class, x0, y0, x1, y1)`` pixel edges (x0, y0 inclusive, x1, y1 exclusive).
"""

from __future__ import annotations

import numpy as np
import torch


def vouched_cells(grid_shape: tuple[int, int, int], lo, hi, ground_z: float, camera, cam_from_world: list,
                  boxes: list[list[tuple]], min_share: float = 0.7, min_views: int = 3,
                  max_height_m: float = 3.0) -> torch.Tensor:
    """(gx, gy, gz) bool: the cells of a grid over the box [lo, hi] (ENU metres) that the label boxes
    vouch for (module docstring). ``cam_from_world`` and ``boxes`` are per labelled frame (frames without
    labels must not be passed: they would vote "no object" everywhere)."""
    if len(cam_from_world) != len(boxes):
        raise ValueError(f"{len(cam_from_world)} poses but {len(boxes)} box lists")
    if not 0.0 < min_share <= 1.0 or min_views < 1:
        raise ValueError(f"min_share must be in (0, 1] and min_views >= 1, got {min_share}, {min_views}")
    shape = tuple(int(g) for g in grid_shape)
    out = np.zeros(shape, bool)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    size = (hi - lo) / np.asarray(shape)
    z_centres = lo[2] + (np.arange(shape[2]) + 0.5) * size[2]
    layers = np.flatnonzero((z_centres >= ground_z - size[2]) & (z_centres <= ground_z + max_height_m))
    if not len(layers) or not any(len(b) for b in boxes):
        return torch.from_numpy(out)
    ix, iy, iz = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), layers, indexing="ij")
    centres = lo + (np.stack([ix, iy, iz], -1).reshape(-1, 3) + 0.5) * size
    seen = np.zeros(len(centres), np.int32)
    inside = np.zeros(len(centres), np.int32)
    for T, frame_boxes in zip(cam_from_world, boxes, strict=True):
        uv, front = camera.project_world(centres, T)
        with np.errstate(invalid="ignore"):
            in_image = front & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        seen += in_image
        hit = np.zeros(len(centres), bool)
        for _, x0, y0, x1, y1 in frame_boxes:
            with np.errstate(invalid="ignore"):
                hit |= (uv[:, 0] >= x0) & (uv[:, 0] < x1) & (uv[:, 1] >= y0) & (uv[:, 1] < y1)
        inside += hit & in_image
    vouched = (seen >= min_views) & (inside >= min_share * np.maximum(seen, 1))
    out[ix.reshape(-1)[vouched], iy.reshape(-1)[vouched], iz.reshape(-1)[vouched]] = True
    return torch.from_numpy(out)
