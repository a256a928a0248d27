"""Camera frame sources for capture: anything ``cv2.VideoCapture`` opens.

``source`` is a device index ("0"), a V4L2 path ("/dev/video0"), a URL ("rtsp://..."), or a
GStreamer pipeline (text containing "!", opened with the GStreamer backend). Frames are stamped
with the companion clock (unix µs) when the driver hands them over; RGB uint8.
"""

from __future__ import annotations

import logging
import time

import cv2

log = logging.getLogger(__name__)


class CameraOpenError(OSError):
    """The camera source cannot be opened."""


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
