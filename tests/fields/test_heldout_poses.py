"""Test-time pose alignment of held-out frames (fields.heldout_poses) and the shared pose correction."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fields.dynamic_data import load_dynamic_flight
from fields.dynamic_simscene import LineSpec, PoseNoise, write_line_flight
from fields.dynamic_training import DynamicFitConfig, evaluate_dynamic, fit_dynamic
from fields.heldout_poses import AlignmentOptions, align_flight_frames, align_heldout_poses
from fields.pose_drift import corrected_cam_from_world
from sim.world import make_world
from telemetry.camera import Camera, Mount
from telemetry.frames import camera_center, look_at


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A tiny extended K-Planes fit (200 steps, ~12 s) on a 64x48 dynamic line flight: enough steps for the
    field to hold the ground's texture (fewer leave it a flat colour that no pose error changes; with the
    dynamic planes over the ground layer, 120 steps were too few)."""
    out = tmp_path_factory.mktemp("align") / "flight"
    world = make_world(seed=5, dynamic=True, texture_size=512, texel_m=0.05)
    camera = Camera.from_fov(64, 48, 70.0, Mount(pitch_deg=-60))
    write_line_flight(out, world, camera, LineSpec(altitude_m=6.0, length_m=4.0, frames=8, dt_s=0.5), PoseNoise(),
                      supersample=1)
    dd = load_dynamic_flight(out)
    cfg = DynamicFitConfig(kind="kplanes-ext", iters=200, budget_s=None, n_samples=16, batch_rays=512,
                           max_resolution=32, features=4, hidden=16)
    return dd, fit_dynamic(dd, cfg).model


def _shifted(T: np.ndarray, trans_m, rot_rad) -> np.ndarray:
    return corrected_cam_from_world(T, torch.tensor(rot_rad, dtype=torch.float32),
                                    torch.tensor(trans_m, dtype=torch.float32))


def test_zero_correction_is_the_identity_and_a_shift_moves_only_the_centre():
    T = look_at(np.array([1.0, -2.0, 15.0]), np.array([4.0, 0.0, 0.0]))
    assert np.allclose(_shifted(T, [0.0, 0, 0], [0.0, 0, 0]), T, atol=1e-9)
    moved = _shifted(T, [0.3, -0.1, 0.5], [0.0, 0, 0])
    assert np.allclose(moved[:3, :3], T[:3, :3], atol=1e-9)
    assert np.allclose(camera_center(moved), camera_center(T) + [0.3, -0.1, 0.5], atol=1e-6)
    turned = _shifted(T, [0.0, 0, 0], [0.0, 0.0, 0.02])  # 0.02 rad about world up, about the centre
    assert np.allclose(camera_center(turned), camera_center(T), atol=1e-6)
    angle = np.arccos(np.clip((np.trace(turned[:3, :3] @ T[:3, :3].T) - 1) / 2, -1, 1))
    assert angle == pytest.approx(0.02, abs=1e-5)


def _mse(model, camera, T, t01, image) -> float:
    r = model.render_image(camera, T, t01)
    return float(np.mean((r["rgb"].astype(np.float64) - image.astype(np.float64) / 255.0) ** 2))


def test_alignment_undoes_a_pose_error_against_the_field_own_renders(fitted):
    """Target = the field's own render at a pose, rounded to 8 bits; start 8 cm and 0.3 deg off: the
    photometric loss falls, the image error above the rounding floor (the error at the target pose
    itself) falls at least five-fold, the camera centre moves back towards the target pose, and the
    field is untouched. (With the ground where it belongs, 6 m down, the start error is only ~3x that
    floor, so the floor has to come off.)"""
    dd, model = fitted
    cam = dd.data.camera
    t01 = dd.t01()
    frames = [1, 3]
    truth = [model.field_pose(dd.data.cam_from_world[i], float(t01[i])) for i in frames]
    renders = [model.render_image(cam, T, float(t01[i]))["rgb"] for T, i in zip(truth, frames, strict=True)]
    images = torch.from_numpy((np.stack(renders) * 255).round().astype(np.uint8))
    start = [_shifted(T, [0.08, -0.05, 0.03], [0.004, -0.003, 0.002]) for T in truth]
    state = {k: v.clone() for k, v in model.state_dict().items()}
    flags = [p.requires_grad for p in model.parameters()]
    poses, report = align_heldout_poses(model, cam, start, [float(t01[i]) for i in frames], images,
                                        options=AlignmentOptions(steps=60, batch_rays=512, lr_m=1.5e-2, lr_rad=1.5e-3))
    assert report["frames"] == 2 and report["steps"] == 60
    assert report["loss_end"] < report["loss_start"]
    for T0, T1, Tt, i, img in zip(start, poses, truth, frames, images.numpy(), strict=True):
        floor, before, after = (_mse(model, cam, T, float(t01[i]), img) for T in (Tt, T0, T1))
        assert after - floor < 0.2 * (before - floor)
        centre_error = lambda T: np.linalg.norm(camera_center(T) - camera_center(Tt))  # noqa: E731, B023
        assert centre_error(T1) < centre_error(T0)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in state.items())
    assert [p.requires_grad for p in model.parameters()] == flags


def test_flight_frames_align_on_the_background_and_feed_the_evaluation(fitted):
    dd, model = fitted
    poses, report = align_flight_frames(model, dd, [1, 5], AlignmentOptions(steps=3, batch_rays=64))
    assert set(poses) == {1, 5} and report["steps"] == 3
    assert np.isfinite(report["trans_rms_m"]) and np.isfinite(report["rot_rms_deg"])
    plain = evaluate_dynamic(model, dd, [1, 5])
    same = evaluate_dynamic(model, dd, [1, 5], poses={i: model.field_pose(dd.data.cam_from_world[i], float(dd.t01()[i]))
                                                     for i in (1, 5)})
    assert same["psnr"] == pytest.approx(plain["psnr"])
    aligned = evaluate_dynamic(model, dd, [1, 5], poses=poses)
    assert np.isfinite(aligned["psnr"])


def test_no_frames_bad_shapes_and_an_empty_background(fitted):
    dd, model = fitted
    cam = dd.data.camera
    assert align_heldout_poses(model, cam, [], [], torch.zeros(0, cam.height, cam.width, 3, dtype=torch.uint8)) == \
        ([], {"frames": 0})
    T = [dd.data.cam_from_world[0]]
    img = dd.data.images[:1]
    with pytest.raises(ValueError, match="one time and one image"):
        align_heldout_poses(model, cam, T, [0.0, 0.5], img)
    with pytest.raises(ValueError, match="no background pixel"):
        align_heldout_poses(model, cam, T, [0.0], img, torch.zeros(1, cam.height, cam.width, dtype=torch.bool))


def test_zero_steps_return_the_start_poses(fitted):
    dd, model = fitted
    T = [dd.data.cam_from_world[2]]
    poses, report = align_heldout_poses(model, dd.data.camera, T, [0.3], dd.data.images[2:3],
                                        options=AlignmentOptions(steps=0))
    assert report["steps"] == 0 and report["loss_start"] is None
    assert np.allclose(poses[0], T[0], atol=1e-9)
