"""The poses file contract: round trip, unposed frames, and validation errors."""

import json

import numpy as np
import pytest

from telemetry.camera import Camera
from telemetry.frames import orbit_pose
from telemetry.posesfile import Origin, PoseEntry, PosesFile, PosesFileError


def _example() -> PosesFile:
    cam = Camera.from_fov(64, 48, 60.0)
    frames = [
        PoseEntry("000000.jpg", 1_700_000_000_000_000, orbit_pose(15, 20, -50), "telemetry",
                  extra={"quality": 0.5}),
        PoseEntry("000001.jpg", 1_700_000_000_100_000, None, "telemetry", reason="telemetry gap 0.8 s"),
        PoseEntry(None, None, orbit_pose(50, 30, -60), "novel"),
    ]
    return PosesFile(Origin(42.0, -83.0, 250.0), cam, frames)


def test_round_trip_keeps_everything(tmp_path):
    pf = _example()
    pf.save(tmp_path / "poses.json")
    back = PosesFile.load(tmp_path / "poses.json")
    assert back.origin == pf.origin and back.camera == pf.camera
    assert [f.frame for f in back.frames] == ["000000.jpg", "000001.jpg", None]
    assert np.allclose(back.frames[0].cam_from_world, pf.frames[0].cam_from_world)
    assert back.frames[1].cam_from_world is None and back.frames[1].reason == "telemetry gap 0.8 s"
    assert back.frames[0].extra == {"quality": 0.5}
    assert len(back.posed()) == 2
    assert not (tmp_path / "poses.json.tmp").exists()


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d["frames"][0].update(cam_from_world=[[float("nan")] * 4] * 4), "NaN"),
    (lambda d: d["frames"][0].update(cam_from_world=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     "orthonormal"),
    (lambda d: d["frames"][0].update(cam_from_world=[[1, 0, 0]]), "4x4"),
    (lambda d: d["frames"][0].update(source="guess"), "source"),
    (lambda d: d["frames"][0].update(t_unix_us=1.5), "t_unix_us"),
    (lambda d: d.pop("origin"), "origin"),
])
def test_invalid_files_give_a_clear_error(tmp_path, mutate, message):
    data = _example().to_json()
    mutate(data)
    (tmp_path / "p.json").write_text(json.dumps(data))
    with pytest.raises(PosesFileError, match=message):
        PosesFile.load(tmp_path / "p.json")


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(PosesFileError, match="no such"):
        PosesFile.load(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(PosesFileError, match="JSON"):
        PosesFile.load(tmp_path / "bad.json")
