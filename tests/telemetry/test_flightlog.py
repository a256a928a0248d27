import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from telemetry.camera import Camera
from telemetry.flightlog import FlightError, FlightWriter, WriterConfig, read_flight

from .tlogfactory import T0, TlogBuilder, factory_flight

CAM = Camera.from_fov(32, 24, 70.0)


def jpeg(seed=0):
    img = np.random.default_rng(seed).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def write_flight(root, n_frames=5):
    b = TlogBuilder()
    factory_flight(b, duration_s=2.0)
    with FlightWriter(root, CAM, class_names=["standing", "kneeling", "prone"]) as w:
        for t, raw in b.items:
            assert w.add_message(t, raw)
        for k in range(n_frames):
            assert w.add_frame(jpeg(k), T0 + k * 100_000, labels="0 0.5 0.5 0.1 0.2\n") == f"{k:06d}.jpg"
    return len(b.items)


def test_write_then_read(tmp_path):
    n_msgs = write_flight(tmp_path / "f")
    fl = read_flight(tmp_path / "f", decode_images=True)
    assert fl.problems == []
    assert [t for _, t in fl.frames] == [T0 + k * 100_000 for k in range(5)]
    assert len(fl.tlog.records) == n_msgs
    assert fl.class_names == ["standing", "kneeling", "prone"]
    assert fl.labels_path("000001.jpg").read_text().startswith("0 0.5")
    assert (tmp_path / "f" / "frames.csv").read_text().splitlines()[0] == "frame,t_unix_us"


def test_array_frames_are_encoded(tmp_path):
    with FlightWriter(tmp_path / "f", CAM) as w:
        name = w.add_frame(np.zeros((24, 32, 3), np.uint8), T0)
    assert cv2.imread(str(tmp_path / "f" / "frames" / name)).shape == (24, 32, 3)


def test_reader_problems_one_each(tmp_path):
    root = tmp_path / "f"
    write_flight(root)
    (root / "frames" / "000002.jpg").write_bytes(jpeg(2)[:100])  # truncated JPEG
    (root / "frames" / "000003.jpg").unlink()  # row without image
    with open(root / "frames.csv", "a") as fh:
        fh.write("000009.jpg,notanumber\nbroken row\n")
    data = (root / "telemetry.tlog").read_bytes()
    (root / "telemetry.tlog").write_bytes(data[:-4])  # truncated tail
    fl = read_flight(root)
    assert [n for n, _ in fl.frames] == ["000000.jpg", "000001.jpg", "000004.jpg"]
    text = "\n".join(fl.problems)
    assert "truncated JPEG" in text and "row without image" in text and "not integer" in text
    assert "malformed row" in text and "truncated last record" in text
    assert len(fl.problems) == 5


@pytest.mark.parametrize("missing", ["camera.json", "frames.csv", "telemetry.tlog"])
def test_missing_files_are_clear_errors(tmp_path, missing):
    root = tmp_path / "f"
    write_flight(root, 1)
    (root / missing).unlink()
    with pytest.raises(FlightError, match=f"missing {missing}"):
        read_flight(root)


def test_not_a_directory(tmp_path):
    with pytest.raises(FlightError, match="not a flight directory"):
        read_flight(tmp_path / "nope")


def test_size_cap_stops_logging_cleanly(tmp_path):
    w = FlightWriter(tmp_path / "f", CAM, WriterConfig(max_bytes=3000))
    accepted = 0
    for k in range(100):
        if not w.add_frame(jpeg(k), T0 + k):
            break
        accepted += 1
    assert w.status == "disk-full"
    assert not w.add_message(T0, b"\xfd" + bytes(20))  # later writes refused, nothing raises
    w.close()
    fl = read_flight(tmp_path / "f")
    assert len(fl.frames) == accepted and accepted > 0


def test_real_enospc_stops_logging_cleanly(tmp_path):
    """The tlog is /dev/full: every flush fails with ENOSPC, as on a full disk."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    root = tmp_path / "f"
    root.mkdir()
    (root / "telemetry.tlog").symlink_to("/dev/full")
    w = FlightWriter(root, CAM, WriterConfig(sync_interval_s=0.0))
    results = [w.add_message(T0 + i, b"\xfd" + bytes(30)) for i in range(10)]
    assert results[-1] is False and w.status == "disk-full"
    w.close()  # no exception


WRITER_SCRIPT = textwrap.dedent("""
    import sys, time
    import numpy as np, cv2
    from telemetry.camera import Camera
    from telemetry.flightlog import FlightWriter, WriterConfig
    from tests.telemetry.tlogfactory import TlogBuilder, factory_flight, T0
    b = TlogBuilder(); factory_flight(b, duration_s=60.0)
    img = cv2.imencode('.jpg', np.full((24, 32, 3), 128, np.uint8))[1].tobytes()
    w = FlightWriter(sys.argv[1], Camera.from_fov(32, 24, 70.0), WriterConfig(sync_interval_s=0.02))
    k = 0
    while True:
        for t, raw in b.items[(k * 7) % len(b.items):(k * 7) % len(b.items) + 7]:
            w.add_message(t, raw)
        w.add_frame(img, T0 + k * 1000)
        k += 1
        if k == 30:
            w.sync()
            print('ready', flush=True)
""")


def test_kill_9_leaves_a_readable_flight(tmp_path):
    root = tmp_path / "f"
    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, "-c", WRITER_SCRIPT, str(root)], cwd=repo, stdout=subprocess.PIPE,
                            env={**os.environ, "PYTHONPATH": str(repo)})
    try:
        assert proc.stdout.readline().strip() == b"ready"
        time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    fl = read_flight(root, decode_images=True)
    assert len(fl.frames) >= 30
    assert len(fl.tlog.records) >= 30 * 7 - 1
    # the only damage a kill can do: a cut last tlog record or a last image cut short (skipped)
    assert all("truncated" in p or "without image" in p for p in fl.problems), fl.problems


def test_queued_writer_keeps_order_and_counts_drops(tmp_path):
    import threading

    from telemetry.logqueue import QueuedFlightWriter

    q = QueuedFlightWriter(FlightWriter(tmp_path / "a", CAM), max_frames_queued=64)
    for k in range(20):
        assert q.add_message(T0 + k, b"\xfd" + bytes(20))
        assert q.add_frame(jpeg(k), T0 + k)
    q.close()
    fl = read_flight(tmp_path / "a")
    assert [t for _, t in fl.frames] == [T0 + k for k in range(20)] and q.dropped_frames == 0

    gate = threading.Event()
    w = FlightWriter(tmp_path / "b", CAM)
    real = w.add_frame
    w.add_frame = lambda *a, **kw: (gate.wait(5), real(*a, **kw))[1]  # a disk that stalls
    q = QueuedFlightWriter(w, max_frames_queued=2)
    accepted = [q.add_frame(jpeg(k), T0 + k) for k in range(6)]
    gate.set()
    q.close()
    assert accepted == [True, True, False, False, False, False] and q.dropped_frames == 4
    assert len(read_flight(tmp_path / "b").frames) == 2


def test_reopening_a_flight_appends(tmp_path):
    write_flight(tmp_path / "f", 3)
    with FlightWriter(tmp_path / "f", CAM) as w:
        assert w.add_frame(jpeg(9), T0 + 10**6) == "000003.jpg"
    fl = read_flight(tmp_path / "f")
    assert [n for n, _ in fl.frames] == ["000000.jpg", "000001.jpg", "000002.jpg", "000003.jpg"]
    assert fl.problems == []
