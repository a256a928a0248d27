"""Camera frame sources for capture: anything ``cv2.VideoCapture`` opens, or a folder replayed.

``source`` is a device index ("0"), a V4L2 path ("/dev/video0"), a URL ("rtsp://..."), a
GStreamer pipeline (text containing "!", opened with the GStreamer backend), or
``replay:DIR`` — the images of a folder (sorted, decoded once) looped at the configured rate, for
bench tests and offline checks. Frames are stamped with the companion clock (unix µs) when the
driver hands them over; RGB uint8.
"""

from __future__ import annotations

import logging
import time

import cv2

log = logging.getLogger(__name__)


class CameraOpenError(OSError):
    """The camera source cannot be opened."""


def open_source(source: str, fps: float):
    """The frame source for a ``camera.source`` setting (see the module docstring)."""
    if source.startswith("replay:"):
        return FolderReplaySource(source[len("replay:"):], fps)
    return OpenCVSource(source)


class FolderReplaySource:
    """Loops the images of a folder at ``fps`` on the wall clock (free-running like a sensor)."""

    def __init__(self, folder: str, fps: float):
        from pathlib import Path

        paths = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        if not paths:
            raise CameraOpenError(f"replay camera: no images in {folder!r}")
        self.frames = []
        for p in paths:
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                raise CameraOpenError(f"replay camera: cannot decode {p}")
            self.frames.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        self.period_s = 1.0 / fps
        self.next_t = time.monotonic()
        self.k = 0
        self._closed = False

    def read(self):
        if self._closed:
            return None
        delay = self.next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self.next_t += self.period_s
        frame = self.frames[self.k % len(self.frames)]
        self.k += 1
        return time.time_ns() // 1000, frame

    def close(self) -> None:
        self._closed = True


class OpenCVSource:
    def __init__(self, source: str):
        self.source = source
        if source.strip().isdigit():
            cap = cv2.VideoCapture(int(source))
        elif "!" in source:
            cap = cv2.VideoCapture(source, cv2.CAP_GSTREAMER)
        else:
            cap = cv2.VideoCapture(source)
        if not cap.isOpened():
            raise CameraOpenError(f"cannot open camera source {source!r}")
        self.cap = cap
        self.failures = 0

    def read(self):
        """(t_unix_us, RGB) of the next frame, or None when the driver returned nothing."""
        ok, frame = self.cap.read()
        t = time.time_ns() // 1000
        if not ok or frame is None:
            self.failures += 1
            if self.failures % 50 == 1:
                log.warning("camera %r returned no frame (%d times)", self.source, self.failures)
            return None
        if frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
        else:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        return t, frame

    def close(self) -> None:
        self.cap.release()
