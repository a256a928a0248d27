"""A writer thread in front of :class:`telemetry.flightlog.FlightWriter`, so capture never waits on disk.

The capture loop calls :meth:`QueuedFlightWriter.add_frame` / :meth:`add_message`, which only put the
item on a bounded queue; one thread JPEG-encodes and writes (OpenCV and file I/O release the GIL, so
the encoding runs beside the capture on a second core). A slow fsync or a burst is absorbed by the
queue; a frame is *dropped* only when the queue is full, and counted in :attr:`dropped_frames`.
Telemetry messages are never dropped for a full queue (they are tiny; the put blocks briefly
instead), and keep their order relative to frames.
"""

from __future__ import annotations

import logging
import queue
import threading

from telemetry.flightlog import FlightWriter

log = logging.getLogger(__name__)

_STOP = object()


class QueuedFlightWriter:
    def __init__(self, writer: FlightWriter, max_frames_queued: int = 16) -> None:
        self.writer = writer
        self._q: queue.Queue = queue.Queue()
        self._frames_queued = threading.Semaphore(max_frames_queued)
        self.dropped_frames = 0
        self.frame_names: list[str] = []
        self._thread = threading.Thread(target=self._run, name="flight-writer", daemon=True)
        self._thread.start()

    @property
    def status(self) -> str:
        return self.writer.status

    def add_message(self, t_unix_us: int, raw: bytes) -> bool:
        if not self.writer.ok:
            return False
        self._q.put(("m", t_unix_us, raw))
        return True

    def add_frame(self, image, t_unix_us: int, labels: str | None = None) -> bool:
        """Queue a frame; False (and counted as dropped) when the queue is full or logging stopped."""
        if not self.writer.ok:
            return False
        if not self._frames_queued.acquire(blocking=False):
            self.dropped_frames += 1
            log.warning("flight writer queue full: frame at %d dropped", t_unix_us)
            return False
        self._q.put(("f", t_unix_us, image, labels))
        return True

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is _STOP:
                return
            if item[0] == "m":
                self.writer.add_message(item[1], item[2])
            else:
                try:
                    name = self.writer.add_frame(item[2], item[1], labels=item[3])
                    if name is not None:
                        self.frame_names.append(name)
                finally:
                    self._frames_queued.release()

    def close(self) -> None:
        """Write everything queued, then sync and close the flight."""
        self._q.put(_STOP)
        self._thread.join()
        self.writer.close()
