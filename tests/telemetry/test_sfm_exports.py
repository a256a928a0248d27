"""derived/ exports of an SfM result: poses.json, colmap/, transforms.json, points.ply, sfm_report.json."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest

from telemetry.camera import Camera
from telemetry.exports import CV_TO_GL, read_points_ply, write_derived, write_points_ply
from telemetry.frames import camera_center, look_at
from telemetry.posesfile import Origin, PosesFile
from telemetry.sfm import FramePose, SfmOptions, SfmResult, refine_poses
from telemetry.sfm_sim import noisy_priors, render_orbit

ORIGIN = Origin(42.1, -76.9, 300.0)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    root = tmp_path_factory.mktemp("flight")
    images, camera, truth, times = render_orbit(root / "frames", n_frames=7, width=128, height=96, arc_deg=70.0,
                                                texture_size=512, texel_m=0.05)
    priors = noisy_priors([p.name for p in images], truth, times, 0.5, 1.0, seed=5)
    res = refine_poses(images, camera, priors, root / "work",
                       SfmOptions(max_image_size=128, sift_first_octave=-1, min_frame_observations=15, num_threads=2))
    assert res.report["ok"]
    return root, res, write_derived(root, res, ORIGIN)


def test_poses_json_follows_the_contract(flight):
    root, res, paths = flight
    pf = PosesFile.load(root / "derived" / "poses.json")
    assert pf.origin == ORIGIN and pf.camera == res.camera
    assert [e.frame for e in pf.frames] == [f.frame for f in res.frames]
    for e, f in zip(pf.frames, res.frames, strict=True):
        assert e.source == f.source
        np.testing.assert_allclose(e.cam_from_world, f.cam_from_world)
        assert "observations" in e.extra and "position_change_m" in e.extra


def test_transforms_json_is_opengl_world_from_cam(flight):
    root, res, _ = flight
    tj = json.loads((root / "derived" / "transforms.json").read_text())
    assert tj["camera_model"] == "OPENCV" and tj["w"] == 128 and tj["h"] == 96
    assert np.allclose(tj["applied_transform"], np.eye(4)[:3])
    assert (root / "derived" / tj["ply_file_path"]).is_file()
    assert len(tj["frames"]) == len(res.frames)
    for fr, f in zip(tj["frames"], res.frames, strict=True):
        assert (root / "derived" / fr["file_path"]).is_file()
        c2w = np.array(fr["transform_matrix"])
        np.testing.assert_allclose(c2w[:3, 3], camera_center(f.cam_from_world), atol=1e-9)
        # OpenGL looks down -z: that is the OpenCV +z (forward) axis
        forward_cv = f.cam_from_world[2, :3]
        np.testing.assert_allclose(-c2w[:3, 2], forward_cv, atol=1e-9)
        np.testing.assert_allclose(c2w @ CV_TO_GL, np.linalg.inv(f.cam_from_world), atol=1e-9)


def test_colmap_model_opens_with_the_same_poses(flight):
    root, res, _ = flight
    rec = pycolmap.Reconstruction(str(root / "derived" / "colmap"))
    assert rec.num_reg_images() == res.num_refined
    assert rec.num_points3D() == len(res.points_xyz)
    by_name = {f.frame: f for f in res.frames}
    for iid in rec.reg_image_ids():
        img = rec.image(iid)
        T = np.eye(4)
        T[:3, :4] = img.cam_from_world().matrix()
        np.testing.assert_allclose(T, by_name[img.name].cam_from_world, atol=1e-9)


def test_points_and_report(flight):
    root, res, _ = flight
    xyz, rgb = read_points_ply(root / "derived" / "points.ply")
    np.testing.assert_allclose(xyz, res.points_xyz)
    np.testing.assert_array_equal(rgb, res.points_rgb)
    rep = json.loads((root / "derived" / "sfm_report.json").read_text())
    assert rep["registered_fraction"] == 1.0 and rep["mean_reprojection_px"] < 1.0
    assert len(rep["frames"]) == len(res.frames)


def test_failed_result_writes_telemetry_poses_and_no_model(tmp_path):
    cam = Camera.from_fov(64, 48, 60.0)
    T = look_at(np.array([0.0, 0.0, 30.0]), np.array([0.0, 0.01, 0.0]))
    frames = [FramePose("a.png", 1, T, "telemetry", "SfM failed: too few matches"),
              FramePose("b.png", 2, None, "telemetry", "SfM failed: too few matches; no prior attitude",
                        {"prior_position_enu": [1.0, 2.0, float("nan")]})]
    res = SfmResult(frames, cam, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0, int),
                    {"ok": False, "reason": "too few matches"})
    paths = write_derived(tmp_path, res, ORIGIN)
    assert "colmap" not in paths
    pf = PosesFile.load(paths["poses"])
    assert pf.frames[0].source == "telemetry" and pf.frames[1].cam_from_world is None
    assert "too few matches" in pf.frames[1].reason
    assert pf.frames[1].extra["prior_position_enu"][2] is None  # NaN is not JSON
    assert json.loads(paths["transforms"].read_text())["frames"][0]["file_path"] == "../frames/a.png"
    xyz, _ = read_points_ply(paths["points"])
    assert xyz.shape == (0, 3)


def test_ply_rejects_mismatched_arrays(tmp_path):
    with pytest.raises(ValueError, match="differ"):
        write_points_ply(tmp_path / "p.ply", np.zeros((3, 3)), np.zeros((2, 3), np.uint8))
