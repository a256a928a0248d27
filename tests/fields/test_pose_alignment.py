"""Frame misregistration of ground points (fields.pose_alignment): zero for poses that differ from the
truth by one similarity, the hand value for one shifted nadir frame, oblique and horizon frames."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fields.pose_alignment import (
    alignment_report,
    field_pose_from_true,
    fit_world_similarity,
    ground_points,
    misregistration_px,
)
from telemetry.camera import Camera
from telemetry.frames import look_at

CAMERA = Camera.from_fov(160, 120, 70.0)


def pass_poses(n=12, height=15.0, pitch_target=12.0):
    """A straight pass at ``height`` m looking ahead and down (oblique), true ENU."""
    return [look_at([2.0 * i, 0.0, height], [2.0 * i + pitch_target, 1.0, 0.0]) for i in range(n)]


def moved(T, s, R, t):
    """The same camera in a world where ``X_new = (R^T (X - t)) / s``, i.e. ``X = s R X_new + t``."""
    R_wc = T[:3, :3].T
    c = -R_wc @ T[:3, 3]
    c_new = R.T @ (c - t) / s
    R_wc_new = R.T @ R_wc
    out = np.eye(4)
    out[:3, :3] = R_wc_new.T
    out[:3, 3] = -R_wc_new.T @ c_new
    return out


def test_poses_off_by_one_similarity_line_up_exactly():
    truth = pass_poses()
    R = Rotation.from_rotvec([0.01, -0.02, 0.03]).as_matrix()
    field = [moved(T, 1.05, R, np.array([3.0, -1.0, 1.2])) for T in truth]
    rep = alignment_report(CAMERA, (field, truth), {"all": (field, truth)})
    assert rep["all"]["mean_px"] < 1e-3
    assert rep["similarity"]["scale"] == pytest.approx(1.05, rel=1e-4)
    assert rep["similarity"]["shift_m"] == pytest.approx([3.0, -1.0, 1.2], abs=1e-3)


def test_a_true_pose_maps_into_the_field_world_through_the_fitted_similarity():
    """A novel true camera mapped with the similarity fitted on other frames is the field's camera
    that sees the field points at the pixels where the true camera sees their true counterparts."""
    truth = pass_poses()
    R = Rotation.from_rotvec([0.01, -0.02, 0.03]).as_matrix()
    s, t = 1.05, np.array([3.0, -1.0, 1.2])
    field = [moved(T, s, R, t) for T in truth]
    sim = fit_world_similarity(CAMERA, field, truth)
    novel = look_at([5.0, 3.0, 40.0], [9.0, 1.0, 0.0])  # 40 m: higher than any frame it was fitted on
    P = field_pose_from_true(novel, sim)
    assert np.allclose(P, moved(novel, s, R, t), atol=1e-5)
    assert np.allclose(P[:3, :3] @ P[:3, :3].T, np.eye(3), atol=1e-9)
    X_true = np.array([[8.0, 1.0, 0.0], [12.0, -3.0, 1.7]])
    X_field = (X_true - t) @ R / s
    uv_true, _ = CAMERA.project_world(X_true, novel)
    uv_field, _ = CAMERA.project_world(X_field, P)
    assert np.allclose(uv_field, uv_true, atol=1e-3)
    assert np.allclose(field_pose_from_true(novel, np.zeros(7)), novel)


def test_one_shifted_nadir_frame_is_off_by_focal_times_shift_over_height():
    height, shift = 15.0, 0.10
    truth = [look_at([2.0 * i, 0.0, height], [2.0 * i, 0.0, 0.0]) for i in range(8)]
    field = [T.copy() for T in truth]
    bad = moved(truth[3], 1.0, np.eye(3), np.array([-shift, 0.0, 0.0]))  # camera 10 cm east in the field world
    field[3] = bad
    sim = fit_world_similarity(CAMERA, field[:3] + field[4:], truth[:3] + truth[4:])
    px = misregistration_px(CAMERA, field, truth, sim)
    assert px[3] == pytest.approx(CAMERA.fx * shift / height, rel=1e-3)  # every ground point moves alike at nadir
    assert np.delete(px, 3).max() < 1e-4


def test_horizon_pixels_are_dropped_and_a_level_camera_has_no_ground_above_it():
    level = look_at([0.0, 0.0, 15.0], [100.0, 0.0, 15.0])  # optical axis on the horizon: upper half is sky
    uv, X = ground_points(CAMERA, level)
    assert 0 < len(uv) < 48 and np.all(uv[:, 1] > CAMERA.height / 2)
    assert np.allclose(X[:, 2], 0.0)
    up = look_at([0.0, 0.0, 15.0], [0.0, 1.0, 30.0])  # looking up: no ground at all
    uv, X = ground_points(CAMERA, up)
    assert len(uv) == 0
    assert np.isnan(misregistration_px(CAMERA, [up], [up], np.zeros(7))[0])


def test_mismatched_or_empty_pose_lists_are_refused():
    with pytest.raises(ValueError, match="matching"):
        fit_world_similarity(CAMERA, pass_poses(3), pass_poses(2))
    with pytest.raises(ValueError, match="non-empty"):
        fit_world_similarity(CAMERA, [], [])
