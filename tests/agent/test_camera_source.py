import cv2
import numpy as np
import pytest

from agent.camera_source import CameraOpenError, FolderReplaySource, open_source


def test_replay_source_loops_frames_in_order_with_rising_times(tmp_path):
    for k in range(3):
        img = np.full((8, 12, 3), 40 * k, np.uint8)
        cv2.imwrite(str(tmp_path / f"{k}.png"), img)
    src = open_source(f"replay:{tmp_path}", fps=200.0)
    assert isinstance(src, FolderReplaySource)
    got = [src.read() for _ in range(5)]
    assert [int(f[1][0, 0, 0]) for f in got] == [0, 40, 80, 0, 40]
    times = [t for t, _ in got]
    assert times == sorted(times) and got[0][1].shape == (8, 12, 3)
    src.close()
    assert src.read() is None


def test_replay_source_errors(tmp_path):
    with pytest.raises(CameraOpenError, match="no images"):
        FolderReplaySource(str(tmp_path), 10.0)
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(CameraOpenError, match="cannot decode"):
        FolderReplaySource(str(tmp_path), 10.0)
