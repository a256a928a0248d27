"""How well a set of camera poses lines frames up: the image misregistration of true ground points.

Comparing a field's camera poses with the true poses centre by centre and angle by angle mixes two
things that cancel in the image: over flat ground seen from 15 m, a 3 cm shift and a 0.1 deg tilt move
the picture alike. What a field needs is that its frames *agree* about where the ground is. This module
measures that directly, in pixels.

The field's world and the true world differ by one unknown similarity ``G`` (true ENU from field
world: ``X_true = s R X_field + t``): a field fitted to poses that are all off by the same amount
reconstructs the same scene, moved. For frame ``i`` with pose ``P_i`` (OpenCV ``cam_from_world``, field
world) and true pose ``Q_i`` (``cam_from_world``, true ENU), a true ground point ``X`` (on the plane
``z = ground_z``) lies at pixel ``pi(Q_i X)`` in the real photo and at ``pi(P_i G^-1 X)`` in the field's
render. Their distance, after the ``G`` that minimises it over a reference set of frames (the
training frames: the field's world is their consensus), is the misregistration.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from telemetry.camera import Camera


def _centre(T: np.ndarray) -> np.ndarray:
    return -T[:3, :3].T @ T[:3, 3]


def ground_points(camera: Camera, true_cam_from_world: np.ndarray, ground_z: float = 0.0,
                  grid: tuple[int, int] = (8, 6)) -> tuple[np.ndarray, np.ndarray]:
    """A ``grid`` (columns, rows) of pixels (N, 2) across the frame, inset half a cell, and the true
    ENU ground points (N, 3) they see; pixels whose ray misses the ground (at or above the horizon)
    are dropped."""
    us = (np.arange(grid[0]) + 0.5) * camera.width / grid[0]
    vs = (np.arange(grid[1]) + 0.5) * camera.height / grid[1]
    uv = np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)
    o, d = camera.rays_world(np.asarray(true_cam_from_world, dtype=np.float64), uv)
    down = d[:, 2] < -1e-6
    t = (ground_z - o[2]) / np.where(down, d[:, 2], -1.0)
    ok = down & (t > 0)
    return uv[ok], o + t[ok, None] * d[ok]


def _similarity(params: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, R, t) of ``X_true = s R X_field + t`` from 7 parameters (rotvec, t, log s)."""
    return float(np.exp(params[6])), Rotation.from_rotvec(params[:3]).as_matrix(), params[3:6]


def _residuals(params: np.ndarray, camera: Camera, poses: Sequence[np.ndarray],
               points: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    s, R, t = _similarity(params)
    out = []
    for P, (uv, X) in zip(poses, points, strict=True):
        X_field = (X - t) @ R / s  # G^-1 X: rows, R^T (X - t) / s
        cam = X_field @ P[:3, :3].T + P[:3, 3]
        px, front = camera.project(cam)
        err = px - uv
        err[~front] = 1e3  # behind the camera: a large, finite penalty
        out.append(err.ravel())
    return np.concatenate(out) if out else np.zeros(0)


def fit_world_similarity(camera: Camera, field_poses: Sequence[np.ndarray], true_poses: Sequence[np.ndarray],
                         ground_z: float = 0.0) -> np.ndarray:
    """The 7 parameters (rotvec, t (m), log scale) of the similarity from the field's world to the
    true ENU that minimises the ground points' misregistration over these frames. Starts from the
    mean centre offset (scale 1, no rotation), then least squares (robust soft-L1 loss, 1 px)."""
    field_poses = [np.asarray(P, dtype=np.float64) for P in field_poses]
    true_poses = [np.asarray(Q, dtype=np.float64) for Q in true_poses]
    if len(field_poses) != len(true_poses) or not field_poses:
        raise ValueError(f"need matching, non-empty pose lists, got {len(field_poses)} and {len(true_poses)}")
    points = [ground_points(camera, Q, ground_z) for Q in true_poses]
    x0 = np.zeros(7)
    x0[3:6] = np.mean([_centre(Q) - _centre(P) for P, Q in zip(field_poses, true_poses, strict=True)], axis=0)
    sol = least_squares(_residuals, x0, args=(camera, field_poses, points), loss="soft_l1", f_scale=1.0,
                        x_scale=np.array([1e-2, 1e-2, 1e-2, 1.0, 1.0, 1.0, 1e-2]))
    return sol.x


def misregistration_px(camera: Camera, field_poses: Sequence[np.ndarray], true_poses: Sequence[np.ndarray],
                       similarity: np.ndarray, ground_z: float = 0.0) -> np.ndarray:
    """Per frame, the mean distance (px) between where the true ground points appear in the real
    frame and in a render at the field's pose, the worlds related by ``similarity``
    (:func:`fit_world_similarity`)."""
    out = []
    for P, Q in zip(field_poses, true_poses, strict=True):
        pts = ground_points(camera, np.asarray(Q, dtype=np.float64), ground_z)
        r = _residuals(similarity, camera, [np.asarray(P, dtype=np.float64)], [pts]).reshape(-1, 2)
        out.append(float(np.linalg.norm(r, axis=1).mean()) if len(r) else float("nan"))
    return np.asarray(out)


def alignment_report(camera: Camera, reference: tuple[Sequence[np.ndarray], Sequence[np.ndarray]],
                     sets: dict[str, tuple[Sequence[np.ndarray], Sequence[np.ndarray]]],
                     ground_z: float = 0.0) -> dict:
    """Fit the world similarity on ``reference`` = (field poses, true poses), then the median and
    mean per-frame misregistration (px) of each named set of (field poses, true poses)."""
    sim = fit_world_similarity(camera, *reference, ground_z=ground_z)
    s, R, t = _similarity(sim)
    report = {"similarity": {"scale": s, "rot_deg": float(np.degrees(np.linalg.norm(sim[:3]))),
                             "shift_m": [float(v) for v in t]}}
    for name, (field_poses, true_poses) in sets.items():
        px = misregistration_px(camera, field_poses, true_poses, sim, ground_z)
        report[name] = {"median_px": float(np.nanmedian(px)), "mean_px": float(np.nanmean(px)),
                        "p90_px": float(np.nanpercentile(px, 90))}
    return report


def field_pose_from_true(true_cam_from_world: np.ndarray, similarity: np.ndarray) -> np.ndarray:
    """The OpenCV ``cam_from_world`` in the field's world of a camera whose true pose (true ENU) is
    ``true_cam_from_world``, the worlds related by ``similarity`` (:func:`fit_world_similarity`,
    ``X_true = s R X_field + t``): a field point projects to the pixel its true counterpart does.
    Rigid: the scale ``s`` divides the translation (camera coordinates scaled by ``s`` project alike)."""
    s, R, t = _similarity(np.asarray(similarity, dtype=np.float64))
    Q = np.asarray(true_cam_from_world, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = Q[:3, :3] @ R
    out[:3, 3] = (Q[:3, :3] @ t + Q[:3, 3]) / s
    return out
