"""Novel poses: observed region, dropping views that look outside it, trajectories, dynamic t ± Δt."""

import numpy as np
import pytest

from fields.novel_poses import (
    NovelPoseOptions,
    dynamic_novel_poses,
    observed_region,
    outside_fraction,
    raised_along_axis,
    scene_centre,
    static_novel_poses,
)
from telemetry.camera import Camera
from telemetry.frames import camera_center, look_at, orbit_pose
from telemetry.posesfile import PoseEntry

CAM = Camera.from_fov(128, 96, 70.0)
PITCH_15 = -np.degrees(np.arctan2(15.0, 20.0))
REAL = [orbit_pose(15.0, 20.0, PITCH_15, az) for az in range(0, 360, 15)]


def test_scene_centre_is_where_the_orbit_looks():
    assert np.allclose(scene_centre(CAM, REAL), [0, 0, 0], atol=1e-6)


def test_a_view_of_the_centre_is_inside_and_a_view_far_away_is_dropped_with_reason():
    region = observed_region(CAM, REAL)
    inside = look_at([0.0, 0.0, 20.0], [0.0, 0.0, 0.0])
    far = look_at([300.0, 0.0, 20.0], [300.0, 5.0, 0.0])
    assert outside_fraction(CAM, inside, region) < 0.05
    assert outside_fraction(CAM, far, region) == 1.0
    sky = orbit_pose(20.0, 20.0, 10.0)  # camera pitched up: sees sky
    assert outside_fraction(CAM, sky, region) > 0.5


def test_static_poses_hit_the_requested_altitudes_and_stay_inside():
    opts = NovelPoseOptions(altitudes_m=(20.0, 30.0), pitch_deg=(-90.0, -60.0), count=12, seed=1)
    poses = static_novel_poses(CAM, REAL, opts)
    kept = [p for p in poses if p.kept]
    assert len(kept) == 12
    for p in kept:
        assert np.isfinite(p.cam_from_world).all()
        assert camera_center(p.cam_from_world)[2] == pytest.approx(p.altitude_m)
        assert p.altitude_m in (20.0, 30.0)
        assert p.outside_fraction <= opts.max_outside_fraction
    for p in poses:
        if not p.kept:
            assert "outside the observed region" in p.reason
    assert {p.altitude_m for p in kept} == {20.0, 30.0}


def test_trajectories_are_smooth_arcs():
    opts = NovelPoseOptions(altitudes_m=(25.0,), pitch_deg=(-70.0, -70.0 + 1e-9), count=5,
                            poses_per_trajectory=5, arc_step_deg=10.0, max_outside_fraction=1.0)
    poses = static_novel_poses(CAM, REAL, opts)
    centres = np.array([camera_center(p.cam_from_world) for p in poses])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert np.allclose(steps, steps[0], rtol=1e-6)  # evenly spaced along the orbit
    assert np.allclose(np.diff([p.azimuth_deg for p in poses]) % 360.0, 10.0)


def test_too_high_for_the_observed_region_drops_everything_with_a_warning(caplog):
    opts = NovelPoseOptions(altitudes_m=(400.0,), count=3, attempts_per_pose=2)
    poses = static_novel_poses(CAM, REAL, opts)
    assert not any(p.kept for p in poses)
    assert "only 0 of 3" in caplog.text


def test_bad_options_and_inputs_raise():
    with pytest.raises(ValueError, match="pitch"):
        static_novel_poses(CAM, REAL, NovelPoseOptions(pitch_deg=(-50.0, 10.0)))
    with pytest.raises(ValueError, match="no posed"):
        static_novel_poses(CAM, [], NovelPoseOptions())
    with pytest.raises(ValueError, match="sees the ground"):
        observed_region(CAM, [orbit_pose(20.0, 20.0, 30.0)])  # looking up


def _entries(times):
    return [PoseEntry(f"{i:06d}.jpg", t, REAL[i % len(REAL)], "telemetry") for i, t in enumerate(times)]


def test_dynamic_poses_are_three_per_point_at_t_and_t_pm_dt():
    times = [1_000_000 + 100_000 * i for i in range(20)]
    out = dynamic_novel_poses(_entries(times[::-1]), n_points=4, frame_rate_hz=10.0)  # out of order in
    assert len(out) == 12
    ts = np.array([e.t_unix_us for e in out]).reshape(4, 3)
    assert (np.diff(ts, axis=1) == 100_000).all()
    assert ts[0, 1] == times[0] and ts[-1, 1] == times[-1]
    assert all(e.source == "novel" and e.posed for e in out)


def test_dynamic_edge_cases():
    assert len(dynamic_novel_poses(_entries([5, 6]), n_points=10, frame_rate_hz=30.0)) == 6
    unposed = [PoseEntry("a.jpg", 5, None, "telemetry", reason="gap")]
    with pytest.raises(ValueError, match="trajectory"):
        dynamic_novel_poses(unposed, 3, 30.0)
    with pytest.raises(ValueError, match="frame rate"):
        dynamic_novel_poses(_entries([5]), 3, 0.0)


@pytest.mark.parametrize("target", [[8.66, 0.0, 0.0], [0.0, 0.0, 0.0], [3.0, -2.0, 0.0]])
def test_raised_along_axis_keeps_the_ground_point_and_attitude(target):
    """Oblique (60 deg down), nadir and a third view: twice the distance, the same centre pixel."""
    T = look_at(np.array([0.0, 0.0, 15.0]), np.array(target), up_enu=(1.0, 0.0, 0.0))
    up = raised_along_axis(T, 2.0)
    assert np.allclose(up[:3, :3], T[:3, :3])
    assert camera_center(up)[2] == pytest.approx(30.0)
    assert np.linalg.norm(camera_center(up) - target) == pytest.approx(2 * np.linalg.norm(camera_center(T) - target))
    assert np.allclose(raised_along_axis(T, 1.0), T)


def test_raised_along_axis_rejects_a_camera_that_does_not_look_down():
    level = look_at(np.array([0.0, 0.0, 15.0]), np.array([10.0, 0.0, 15.0]))
    with pytest.raises(ValueError, match="look down"):
        raised_along_axis(level, 2.0)
    below = look_at(np.array([0.0, 0.0, -1.0]), np.array([3.0, 0.0, -5.0]))
    with pytest.raises(ValueError, match="look down"):
        raised_along_axis(below, 2.0)
    with pytest.raises(ValueError, match="positive scale"):
        raised_along_axis(look_at(np.array([0.0, 0.0, 15.0]), np.array([1.0, 0.0, 0.0])), float("nan"))
