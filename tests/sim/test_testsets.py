import numpy as np

from sim.testsets import altitude_poses, render_altitude_set
from sim.world import make_world
from telemetry.camera import Camera
from telemetry.frames import camera_center


def test_altitude_poses_are_at_altitude_and_look_down():
    for T in altitude_poses(40.0, 6, seed=1):
        assert camera_center(T)[2] == 40.0 or abs(camera_center(T)[2] - 40.0) < 1e-9
        boresight_world = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        assert boresight_world[2] < -0.7  # at least 45 deg below the horizon


def test_render_altitude_set_writes_a_yolo_val_set(tmp_path):
    world = make_world(seed=2, texture_size=512, texel_m=0.05)
    yaml = render_altitude_set(world, Camera.from_fov(96, 72, 60.0), 20.0, 3, tmp_path, seed=0)
    assert "val: images/val" in yaml.read_text()
    images = sorted((yaml.parent / "images" / "val").iterdir())
    labels = sorted((yaml.parent / "labels" / "val").iterdir())
    assert [p.stem for p in images] == [p.stem for p in labels] == ["alt020_0000", "alt020_0001", "alt020_0002"]
    assert sum(len(p.read_text().splitlines()) for p in labels) > 0
