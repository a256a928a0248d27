"""Rotations, mounts and the camera model: conventions and their hard cases."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telemetry.camera import Camera, CameraError, Mount
from telemetry.frames import (
    cam_from_world_from_attitude,
    camera_center,
    euler_zyx_to_matrix,
    invert_pose,
    look_at,
    matrix_to_euler_zyx,
    mount_from_cam,
    orbit_pose,
)

angles = st.floats(-np.pi, np.pi, allow_nan=False)


@given(angles, st.floats(-np.pi / 2, np.pi / 2), angles)
def test_euler_round_trip_reproduces_the_rotation(yaw, pitch, roll):
    R = euler_zyx_to_matrix(yaw, pitch, roll)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.allclose(euler_zyx_to_matrix(*matrix_to_euler_zyx(R)), R, atol=1e-9)


def test_euler_at_nadir_singularity_is_finite_and_consistent():
    R = euler_zyx_to_matrix(0.7, -np.pi / 2, 0.2)  # yaw and roll not separable here
    ypr = matrix_to_euler_zyx(R)
    assert np.all(np.isfinite(ypr))
    assert np.allclose(euler_zyx_to_matrix(*ypr), R, atol=1e-9)


def test_zero_mount_looks_forward_and_pitch_minus_90_looks_down():
    R_body_cam = mount_from_cam(0.0, 0.0, 0.0)
    assert np.allclose(R_body_cam @ [0, 0, 1], [1, 0, 0])  # boresight = body forward
    assert np.allclose(R_body_cam @ [1, 0, 0], [0, 1, 0])  # image x = body right
    assert np.allclose(R_body_cam @ [0, 1, 0], [0, 0, 1])  # image y = body down
    assert np.allclose(mount_from_cam(0.0, -90.0, 0.0) @ [0, 0, 1], [0, 0, 1], atol=1e-12)


def test_vehicle_heading_east_with_forward_camera_looks_east():
    R_ned_body = euler_zyx_to_matrix(np.pi / 2, 0.0, 0.0)  # NED yaw 90 deg = east
    T = cam_from_world_from_attitude([1.0, 2.0, 3.0], R_ned_body, mount_from_cam(0, 0, 0))
    R_world_cam = T[:3, :3].T
    assert np.allclose(R_world_cam @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # boresight east (ENU x)
    assert np.allclose(R_world_cam @ [0, 1, 0], [0, 0, -1], atol=1e-12)  # image down = world down
    assert np.allclose(camera_center(T), [1, 2, 3])


def test_orbit_pose_looks_at_centre_at_the_right_pitch():
    T = orbit_pose(15.0, 20.0, np.degrees(-np.arctan2(15.0, 20.0)), azimuth_deg=123.0)
    centre_cam = T[:3, :3] @ np.zeros(3) + T[:3, 3]
    assert abs(centre_cam[0]) < 1e-9 and abs(centre_cam[1]) < 1e-9 and centre_cam[2] > 0
    assert np.allclose(invert_pose(invert_pose(T)), T)


@pytest.mark.parametrize("eye", [[0, 0, 50.0], [1e-12, 0, 50.0], [5, 5, 0.0]])
def test_look_at_handles_nadir_and_horizontal(eye):
    T = look_at(eye, [0.0, 0.0, 0.0])
    assert np.isfinite(T).all()
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    with pytest.raises(ValueError):
        look_at([1, 2, 3], [1, 2, 3])


@settings(max_examples=60)
@given(st.floats(-0.2, 0.3), st.floats(0.0, 0.05), st.floats(-0.01, 0.01),
       st.floats(-0.01, 0.01), st.floats(0.05, 0.95), st.floats(0.05, 0.95))
def test_project_unproject_round_trip_with_distortion(k1, k2, p1, p2, fu, fv):
    """Within the range where the lens distortion is monotonic (and so invertible)."""
    cam = Camera(640, 480, 500.0, 505.0, 321.0, 239.0, (k1, k2, p1, p2))
    uv = np.array([[fu * 640, fv * 480]])
    d = cam.unproject(uv)
    back, ok = cam.project(d * 7.0)
    assert ok.all()
    assert np.allclose(back, uv, atol=1e-3)


def test_points_behind_camera_are_flagged_not_projected():
    cam = Camera.from_fov(64, 48, 60.0)
    uv, ok = cam.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 2.0]]))
    assert ok.tolist() == [False, False, True]
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()


def test_pixel_centre_convention_and_gsd():
    cam = Camera.from_fov(100, 80, 90.0)
    assert cam.cx == 50.0 and cam.cy == 40.0
    assert np.allclose(cam.unproject(np.array([50.0, 40.0])), [0, 0, 1])
    assert cam.ground_sample_distance(10.0) == pytest.approx(10.0 / 50.0)
    grid = cam.pixel_grid(2)
    assert grid.shape == (160, 200, 2) and grid[0, 0, 0] == 0.25


def test_camera_json_round_trip_and_errors(tmp_path):
    cam = Camera(320, 240, 300.0, 300.0, 160.0, 120.0, (0.01, 0, 0, 0), Mount(0, -60, 5))
    cam.save(tmp_path / "camera.json")
    assert Camera.load(tmp_path / "camera.json") == cam
    (tmp_path / "bad.json").write_text(json.dumps({"width": 10, "height": 10, "fx": 5}))
    with pytest.raises(CameraError, match="'fy'"):
        Camera.load(tmp_path / "bad.json")
    with pytest.raises(CameraError, match="finite"):
        Camera(10, 10, float("nan"), 5.0, 5.0, 5.0)
    with pytest.raises(CameraError, match="no such file"):
        Camera.load(tmp_path / "missing.json")
