"""SfM seeded by telemetry: real pycolmap runs on tiny simulated orbits (128x96 px)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telemetry.camera import Camera
from telemetry.frames import camera_center, look_at, pose_matrix, rot_x, rot_y, rot_z
from telemetry.sfm import Prior, SfmInputError, SfmOptions, colinearity, pose_errors, refine_poses, umeyama
from telemetry.sfm_sim import gauss_markov, noisy_priors, render_orbit

# One thread: only then is a run bit-for-bit repeatable (two threads once moved a pose by 4 cm in CI).
OPTS = SfmOptions(max_image_size=128, sift_first_octave=-1, min_frame_observations=15, num_threads=1)


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    out = tmp_path_factory.mktemp("orbit")
    images, camera, truth, times = render_orbit(out, n_frames=10, width=128, height=96, arc_deg=100.0,
                                                texture_size=512, texel_m=0.05, supersample=2)
    priors = noisy_priors([p.name for p in images], truth, times, gps_sigma_m=0.5,
                          attitude_sigma_deg=1.0, seed=3)
    return images, camera, truth, priors


@pytest.fixture(scope="module")
def refined(orbit, tmp_path_factory):
    images, camera, truth, priors = orbit
    return refine_poses(images, camera, priors, tmp_path_factory.mktemp("work"), OPTS)


def test_refined_poses_beat_telemetry(orbit, refined):
    _, _, truth, priors = orbit
    assert refined.report["ok"]
    assert refined.num_refined == len(truth)
    assert all(f.reason is None for f in refined.frames)
    est = [f.cam_from_world for f in refined.frames]
    tel = [p.cam_from_world for p in priors]
    aligned, aligned_tel = pose_errors(est, truth, align=True), pose_errors(tel, truth, align=True)
    assert aligned["median_rot_deg"] < aligned_tel["median_rot_deg"] / 3
    assert aligned["median_pos_m"] < aligned_tel["median_pos_m"]
    assert abs(aligned["scale"] - 1.0) < 0.05
    raw, raw_tel = pose_errors(est, truth, align=False), pose_errors(tel, truth, align=False)
    assert raw["median_rot_deg"] <= raw_tel["median_rot_deg"]
    assert raw["median_pos_m"] <= raw_tel["median_pos_m"] * 1.2


def test_result_is_in_enu_with_points_and_report(orbit, refined):
    _, camera, truth, _ = orbit
    assert refined.points_xyz.shape[1] == 3 and len(refined.points_xyz) > 50
    assert refined.points_rgb.dtype == np.uint8 and refined.points_rgb.shape == refined.points_xyz.shape
    assert np.all(np.isfinite(refined.points_xyz))
    # the scene sits on the ground (z ~ 0) below cameras at 15 m
    assert abs(np.median(refined.points_xyz[:, 2])) < 1.5
    rep = refined.report
    assert rep["registered_fraction"] == 1.0
    assert 0 < rep["mean_reprojection_px"] < 1.0
    assert rep["mean_track_length"] >= 2.0
    for f in refined.frames:
        assert f.source == "sfm" and f.stats["position_change_m"] < 3.0
        assert "rotation_change_deg" in f.stats
    assert refined.camera.fx == pytest.approx(camera.fx)


def test_same_seed_same_result(orbit, refined, tmp_path):
    images, camera, _, priors = orbit
    again = refine_poses(images, camera, priors, tmp_path / "w", OPTS)
    for a, b in zip(refined.frames, again.frames, strict=True):
        np.testing.assert_allclose(a.cam_from_world, b.cam_from_world, atol=1e-9)


def test_position_only_priors_use_mapper_and_stay_metric(orbit, tmp_path):
    images, camera, truth, priors = orbit
    pos_only = [Prior(p.frame, p.t_unix_us, p.position_enu, p.sigma_m) for p in priors]
    res = refine_poses(images, camera, pos_only, tmp_path / "w", OPTS)
    ok = [(f.cam_from_world, T) for f, T in zip(res.frames, truth, strict=True) if f.source == "sfm"]
    assert len(ok) >= 8
    err = pose_errors([a for a, _ in ok], [b for _, b in ok], align=True)
    assert err["median_rot_deg"] < 1.0 and abs(err["scale"] - 1) < 0.05
    for f in res.frames:
        if f.source != "sfm":
            assert f.reason and f.cam_from_world is None and "prior_position_enu" in f.stats


def test_nan_prior_is_not_a_crash(orbit, tmp_path):
    images, camera, _, priors = orbit
    bad = list(priors)
    bad[4] = Prior(bad[4].frame, bad[4].t_unix_us, np.array([np.nan, 0.0, 0.0]), 0.5,
                   np.full((4, 4), np.inf))
    res = refine_poses(images, camera, bad, tmp_path / "w", OPTS)
    f = res.frames[4]
    assert f.source == "sfm" or (f.cam_from_world is None and f.reason)
    assert all(np.all(np.isfinite(g.cam_from_world)) for g in res.frames if g.cam_from_world is not None)


def _nadir_strip(tmp_path, with_attitude: bool):
    """A straight line of nadir frames over an almost uniform field (low texture)."""
    rng = np.random.default_rng(0)
    camera = Camera.from_fov(128, 96, 70.0)
    images, priors = [], []
    for k in range(8):
        img = np.full((96, 128, 3), 120, np.uint8) + rng.integers(0, 2, (96, 128, 3), dtype=np.uint8)
        path = tmp_path / f"{k:06d}.png"
        cv2.imwrite(str(path), cv2.GaussianBlur(img, (5, 5), 2.0))
        eye = np.array([3.0 * k, 0.0, 40.0])
        T = look_at(eye, eye + np.array([0.0, 0.001, -1.0]))
        images.append(path)
        priors.append(Prior(path.name, 1_000_000 * k, eye, 0.5, T if with_attitude else None))
    return images, camera, priors


def test_degenerate_nadir_strip_keeps_telemetry_with_reason(tmp_path):
    images, camera, priors = _nadir_strip(tmp_path, with_attitude=True)
    res = refine_poses(images, camera, priors, tmp_path / "w", OPTS)
    assert not res.report["ok"]
    assert "too few matches" in res.report["reason"]
    for f, p in zip(res.frames, priors, strict=True):
        assert f.source == "telemetry" and "too few matches" in f.reason
        np.testing.assert_array_equal(f.cam_from_world, p.cam_from_world)
    assert len(res.points_xyz) == 0


def test_degenerate_without_attitude_has_no_pose_but_keeps_position(tmp_path):
    images, camera, priors = _nadir_strip(tmp_path, with_attitude=False)
    res = refine_poses(images, camera, priors, tmp_path / "w", OPTS)
    for f, p in zip(res.frames, priors, strict=True):
        assert f.cam_from_world is None and "no prior attitude" in f.reason
        assert f.stats["prior_position_enu"] == pytest.approx(list(p.position_enu))


def test_all_positions_nan_cannot_be_georeferenced(tmp_path):
    images, camera, priors = _nadir_strip(tmp_path, with_attitude=True)
    for p in priors:
        p.position_enu = np.array([np.nan, np.nan, np.nan])
    res = refine_poses(images, camera, priors, tmp_path / "w", OPTS)
    assert "georeferenced" in res.report["reason"]
    assert all(f.source == "telemetry" for f in res.frames)


def test_bad_inputs_raise_clear_errors(tmp_path):
    images, camera, priors = _nadir_strip(tmp_path, with_attitude=True)
    with pytest.raises(SfmInputError, match="no images"):
        refine_poses([], camera, [], tmp_path / "w")
    with pytest.raises(SfmInputError, match="priors"):
        refine_poses(images, camera, priors[:-1], tmp_path / "w")
    with pytest.raises(SfmInputError, match="no such image"):
        refine_poses([tmp_path / "nope.png"], camera, [Prior("nope.png", 0, np.zeros(3))], tmp_path / "w")
    with pytest.raises(SfmInputError, match="does not match"):
        refine_poses(images, camera, priors[::-1], tmp_path / "w")
    with pytest.raises(SfmInputError, match="sigma"):
        refine_poses(images[:1], camera, [Prior(images[0].name, 0, np.zeros(3), -1.0)], tmp_path / "w")


@settings(max_examples=30, deadline=None)
@given(st.floats(0.1, 10.0), st.floats(-math.pi, math.pi), st.floats(-1.5, 1.5), st.floats(-math.pi, math.pi),
       st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-100, 100)))
def test_umeyama_recovers_similarity(s, a, b, c, t):
    rng = np.random.default_rng(0)
    src = rng.normal(0, 10, (20, 3))
    R = rot_z(a) @ rot_y(b) @ rot_x(c)
    tgt = s * src @ R.T + np.array(t)
    s2, R2, t2 = umeyama(src, tgt)
    assert s2 == pytest.approx(s, rel=1e-6)
    np.testing.assert_allclose(R2, R, atol=1e-6)
    np.testing.assert_allclose(t2, t, atol=1e-5 * (1 + np.abs(t).max()))


def test_pose_errors_align_removes_a_similarity():
    truth = [look_at(np.array([20 * math.cos(a), 20 * math.sin(a), 15.0]), np.zeros(3))
             for a in np.linspace(0, 2, 8)]
    R = rot_z(0.3)
    moved = []
    for T in truth:  # world moved by x' = 2 R x + (1,2,3)
        c = 2.0 * R @ camera_center(T) + np.array([1.0, 2.0, 3.0])
        Rcw = T[:3, :3] @ R.T
        moved.append(pose_matrix(Rcw, -Rcw @ c))
    e = pose_errors(moved, truth, align=True)
    assert e["median_rot_deg"] < 1e-4 and e["median_pos_m"] < 1e-6 and e["scale"] == pytest.approx(0.5)
    assert pose_errors(moved, truth, align=False)["median_rot_deg"] > 10


def test_gauss_markov_is_stationary_and_smooth():
    x = gauss_markov(20000, 1, 0.5, 1.0, 30.0, np.random.default_rng(1))[:, 0]
    assert np.std(x) == pytest.approx(0.5, rel=0.15)
    assert np.corrcoef(x[:-1], x[1:])[0, 1] > 0.9


def test_colinearity():
    assert colinearity(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)) < 1e-9
    assert colinearity(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)) > 0.5


def test_blank_frames_keep_telemetry_with_reason_others_refined(orbit, tmp_path):
    images, camera, truth, priors = orbit
    folder = tmp_path / "frames"
    folder.mkdir()
    copies = []
    for k, p in enumerate(images):
        dst = folder / p.name
        if k in (3, 7):  # lens cap on: a uniform grey frame
            cv2.imwrite(str(dst), np.full((96, 128, 3), 90, np.uint8))
        else:
            dst.write_bytes(p.read_bytes())
        copies.append(dst)
    res = refine_poses(copies, camera, priors, tmp_path / "w", OPTS)
    assert res.report["ok"] and res.num_refined == len(images) - 2
    for k in (3, 7):
        f = res.frames[k]
        assert f.source == "telemetry" and "too few triangulated points (0 <" in f.reason
        np.testing.assert_array_equal(f.cam_from_world, priors[k].cam_from_world)
    assert set(res.report["unregistered"]) == {images[3].name, images[7].name}


def test_far_from_origin_gives_the_same_shifted_result(orbit, refined, tmp_path):
    """Centring before solving: priors 1000 km from the ENU origin give the same model, shifted."""
    images, camera, _, priors = orbit
    shift = np.array([1.0e6, -2.0e6, 500.0])
    moved = []
    for p in priors:
        T = p.cam_from_world.copy()
        T[:3, 3] = T[:3, 3] - T[:3, :3] @ shift
        moved.append(Prior(p.frame, p.t_unix_us, p.position_enu + shift, p.sigma_m, T))
    res = refine_poses(images, camera, moved, tmp_path / "w", OPTS)
    assert res.num_refined == refined.num_refined
    for a, b in zip(res.frames, refined.frames, strict=True):
        np.testing.assert_allclose(camera_center(a.cam_from_world) - shift, camera_center(b.cam_from_world),
                                   atol=2e-3)
        np.testing.assert_allclose(a.cam_from_world[:3, :3], b.cam_from_world[:3, :3], atol=1e-4)


@pytest.mark.slow
def test_orbit_60_frames_acceptance(tmp_path):
    """Issue 4 acceptance on the full simulated orbit (also bench/sfm.py)."""
    images, camera, truth, times = render_orbit(tmp_path / "orbit", n_frames=60, width=640, height=480)
    priors = noisy_priors([p.name for p in images], truth, times, 0.5, 1.0, seed=1)
    for p in priors:
        p.attitude_sigma_deg = 1.0
    res = refine_poses(images, camera, priors, tmp_path / "w", SfmOptions(seed=1))
    assert res.num_refined == 60
    est, tel = [f.cam_from_world for f in res.frames], [p.cam_from_world for p in priors]
    aligned = pose_errors(est, truth, align=True)
    assert aligned["median_rot_deg"] <= 0.1 and aligned["median_pos_m"] <= 0.05
    assert abs(aligned["scale"] - 1.0) <= 0.01
    raw, raw_tel = pose_errors(est, truth, align=False), pose_errors(tel, truth, align=False)
    assert raw["median_rot_deg"] <= raw_tel["median_rot_deg"] and raw["median_pos_m"] <= raw_tel["median_pos_m"]


def test_candidate_pairs_follow_capture_time_and_prior_position():
    from telemetry.sfm import candidate_pairs

    # listed out of time order; frame 3 has no position
    times = [30, 10, 20, 0]
    pos = [np.array([0.0, 0, 0]), np.array([100.0, 0, 0]), np.array([200.0, 0, 0]), None]
    priors = [Prior(f"{k}.jpg", t, p) for k, (t, p) in enumerate(zip(times, pos, strict=True))]
    seq_only = candidate_pairs(priors, SfmOptions(sequential_overlap=1, spatial_neighbors=0))
    assert seq_only == sorted([(1, 3), (1, 2), (0, 2)])  # time order 3, 1, 2, 0
    spatial = candidate_pairs(priors, SfmOptions(sequential_overlap=1, spatial_neighbors=5,
                                                 spatial_max_distance_m=150.0))
    assert (0, 1) in spatial and (1, 2) in spatial and (0, 3) not in spatial
    no_times = [Prior(p.frame, None, p.position_enu) for p in priors]
    assert candidate_pairs(no_times, SfmOptions(sequential_overlap=1, spatial_neighbors=0)) == [(0, 1), (1, 2), (2, 3)]
