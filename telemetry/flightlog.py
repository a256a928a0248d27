"""The recorded flight (DESIGN.md §3): a crash-safe writer and a validating reader.

Layout::

    FLIGHT/telemetry.tlog  FLIGHT/frames.csv ("frame,t_unix_us")  FLIGHT/frames/  FLIGHT/camera.json
    FLIGHT/labels/ + FLIGHT/classes.txt (optional)

Writer: append-only; every ``sync_interval_s`` (and on close) images written since the last sync are
fsynced first, then the tlog, then frames.csv, so a row in a synced frames.csv always has its image.
A kill -9 leaves everything written to the OS (at worst a cut last tlog record, which the reader
reports); a power cut leaves everything up to the last sync. Disk full (ENOSPC/EDQUOT, or the
optional ``max_bytes`` cap) stops logging cleanly: :attr:`FlightWriter.status` says ``"disk-full"``,
later writes return False, nothing raises.

Reader: :func:`read_flight` raises :class:`FlightError` for what makes a flight unusable (missing
camera.json, frames.csv, telemetry.tlog, bad header) and otherwise returns the flight with one
warning per problem (truncated tlog tail, corrupt or missing images skipped, malformed rows).
"""

from __future__ import annotations

import errno
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from telemetry.camera import Camera
from telemetry.mavlink import TlogReadResult, read_tlog, tlog_record

log = logging.getLogger(__name__)

TLOG = "telemetry.tlog"
FRAMES_CSV = "frames.csv"
FRAMES_DIR = "frames"
CAMERA_JSON = "camera.json"
LABELS_DIR = "labels"
CLASSES_TXT = "classes.txt"
CSV_HEADER = "frame,t_unix_us"
_DISK_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


class FlightError(ValueError):
    """A flight directory that cannot be used."""


class DiskFull(OSError):
    """The flight log hit its size cap or the disk is full."""


@dataclass
class WriterConfig:
    #: flush + fsync everything at most this often (seconds of the writer's clock).
    sync_interval_s: float = 1.0
    #: stop logging when the flight would exceed this many bytes (None: only the disk limits it).
    max_bytes: int | None = None
    #: JPEG quality for frames given as arrays.
    jpeg_quality: int = 90


class FlightWriter:
    """Append-only writer of one recorded flight. Not thread-safe: one owner thread."""

    def __init__(self, root: str | Path, camera: Camera, config: WriterConfig | None = None,
                 class_names: list[str] | None = None, clock=time.monotonic) -> None:
        self.root = Path(root)
        self.config = config or WriterConfig()
        self._clock = clock
        self.status = "ok"
        self.n_frames = 0
        self.n_messages = 0
        self.bytes_written = 0
        self._pending_images: list[Path] = []
        (self.root / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        self.camera = camera
        camera.save(self.root / CAMERA_JSON)
        if class_names is not None:
            (self.root / LABELS_DIR).mkdir(exist_ok=True)
            (self.root / CLASSES_TXT).write_text("".join(n + "\n" for n in class_names))
        self._tlog = open(self.root / TLOG, "ab")
        csv_path = self.root / FRAMES_CSV
        new_csv = not csv_path.exists() or csv_path.stat().st_size == 0
        if not new_csv:  # reopening a flight (e.g. after a restart): append, never overwrite a frame
            rows = csv_path.read_text(errors="replace").splitlines()[1:]
            self.n_frames = len([r for r in rows if r.strip()])
            while (self.root / FRAMES_DIR / f"{self.n_frames:06d}.jpg").exists() or \
                    (self.root / FRAMES_DIR / f"{self.n_frames:06d}.png").exists():
                self.n_frames += 1
        self._csv = open(csv_path, "a")
        if new_csv:
            self._csv.write(CSV_HEADER + "\n")
            self._csv.flush()
            os.fsync(self._csv.fileno())
        self._last_sync = self._clock()
        self._fsync_dir(self.root)

    # ---- writing -------------------------------------------------------------------------------
    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def _reserve(self, n: int) -> None:
        cap = self.config.max_bytes
        if cap is not None and self.bytes_written + n > cap:
            raise DiskFull(errno.ENOSPC, f"flight size cap of {cap} bytes reached")
        self.bytes_written += n

    def _guard(self, fn, *args) -> bool:
        if not self.ok:
            return False
        try:
            fn(*args)
        except OSError as exc:
            if isinstance(exc, DiskFull) or exc.errno in _DISK_FULL:
                self._stop("disk-full", exc)
            else:
                self._stop(f"error: {exc}", exc)
            return False
        self.maybe_sync()
        return self.ok

    def _stop(self, status: str, exc: Exception) -> None:
        log.error("flight log %s stopped: %s (%s)", self.root, status, exc)
        self.status = status
        for fh in (self._tlog, self._csv):
            try:
                fh.close()
            except OSError:
                pass  # buffered bytes that do not fit are dropped; what was synced stays readable

    def add_message(self, t_unix_us: int, raw: bytes) -> bool:
        """Append one received MAVLink frame with its receive time (companion unix µs)."""
        return self._guard(self._add_message, t_unix_us, raw)

    def _add_message(self, t_unix_us: int, raw: bytes) -> None:
        rec = tlog_record(t_unix_us, raw)
        self._reserve(len(rec))
        self._tlog.write(rec)
        self.n_messages += 1

    def add_frame(self, image, t_unix_us: int, labels: str | None = None, ext: str = ".jpg") -> str | None:
        """Write a frame (encoded bytes, or an RGB uint8 array) captured at ``t_unix_us``; its name or None."""
        name = f"{self.n_frames:06d}{ext}"
        return name if self._guard(self._add_frame, name, image, int(t_unix_us), labels) else None

    def _add_frame(self, name: str, image, t_unix_us: int, labels: str | None) -> None:
        data = image if isinstance(image, (bytes, bytearray, memoryview)) else self._encode(image, name)
        row = f"{name},{t_unix_us}\n"
        self._reserve(len(data) + len(row) + (len(labels) if labels else 0))
        path = self.root / FRAMES_DIR / name
        with open(path, "wb") as fh:
            fh.write(data)
        self._pending_images.append(path)
        if labels is not None:
            (self.root / LABELS_DIR).mkdir(exist_ok=True)
            with open(self.root / LABELS_DIR / (Path(name).stem + ".txt"), "w") as fh:
                fh.write(labels)
        self._csv.write(row)  # after the image: a row never points at an image not yet written
        self.n_frames += 1

    def _encode(self, rgb, name: str) -> bytes:
        import cv2

        params = [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality] if name.endswith(".jpg") else []
        ok, buf = cv2.imencode(Path(name).suffix, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise ValueError(f"could not encode frame {name}")
        return buf.tobytes()

    # ---- durability ----------------------------------------------------------------------------
    def maybe_sync(self) -> None:
        if self.ok and self._clock() - self._last_sync >= self.config.sync_interval_s:
            self.sync()

    def sync(self) -> bool:
        """Flush and fsync images, then the tlog, then frames.csv. False if logging has stopped."""
        return self._guard_nosync(self._sync)

    def _guard_nosync(self, fn) -> bool:
        if not self.ok:
            return False
        try:
            fn()
        except OSError as exc:
            self._stop("disk-full" if exc.errno in _DISK_FULL else f"error: {exc}", exc)
            return False
        return True

    def _sync(self) -> None:
        for path in self._pending_images:
            fd = os.open(path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        if self._pending_images:
            self._fsync_dir(self.root / FRAMES_DIR)
        self._pending_images.clear()
        for fh in (self._tlog, self._csv):
            fh.flush()
            os.fsync(fh.fileno())
        self._last_sync = self._clock()

    @staticmethod
    def _fsync_dir(path: Path) -> None:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def close(self) -> None:
        if self.ok:
            self.sync()
            self._tlog.close()
            self._csv.close()
            self.status = "closed"

    def __enter__(self) -> FlightWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---- reading -----------------------------------------------------------------------------------
@dataclass
class Flight:
    """A validated recorded flight: usable frames (name, t_unix_us), camera, tlog, problems found."""

    root: Path
    camera: Camera
    frames: list[tuple[str, int]]
    tlog: TlogReadResult
    problems: list[str] = field(default_factory=list)
    class_names: list[str] | None = None

    def image_path(self, name: str) -> Path:
        return self.root / FRAMES_DIR / name

    def labels_path(self, name: str) -> Path:
        return self.root / LABELS_DIR / (Path(name).stem + ".txt")


def _image_ok(path: Path, decode: bool) -> str | None:
    """None if the image looks complete, else what is wrong."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return "missing"
    if not data:
        return "empty"
    low = path.suffix.lower()
    if low in (".jpg", ".jpeg"):
        if data[:2] != b"\xff\xd8":
            return "not a JPEG (no SOI marker)"
        if b"\xff\xd9" not in data[-64:]:
            return "truncated JPEG (no EOI marker)"
    elif low == ".png" and data[:8] != b"\x89PNG\r\n\x1a\n":
        return "not a PNG"
    if decode:
        import cv2
        import numpy as np

        if cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) is None:
            return "cannot be decoded"
    return None


def read_flight(root: str | Path, decode_images: bool = False) -> Flight:
    """Validate and load a recorded flight (see the module docstring for what raises and what warns)."""
    root = Path(root)
    if not root.is_dir():
        raise FlightError(f"{root}: not a flight directory (does not exist)")
    for name in (CAMERA_JSON, FRAMES_CSV, TLOG):
        if not (root / name).is_file():
            raise FlightError(f"{root}: missing {name}")
    camera = Camera.load(root / CAMERA_JSON)
    problems: list[str] = []
    lines = (root / FRAMES_CSV).read_text(errors="replace").splitlines()
    if not lines or lines[0].strip().replace(" ", "") != CSV_HEADER:
        raise FlightError(f"{root / FRAMES_CSV}: header must be {CSV_HEADER!r}, got {lines[0] if lines else ''!r}")
    frames: list[tuple[str, int]] = []
    seen: set[str] = set()
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) != 2:
            problems.append(f"{FRAMES_CSV}:{lineno}: malformed row {line!r} skipped")
            continue
        name, t = parts[0].strip(), parts[1].strip()
        try:
            t_us = int(t)
        except ValueError:
            problems.append(f"{FRAMES_CSV}:{lineno}: time {t!r} is not integer unix µs; row skipped")
            continue
        if "/" in name or "\\" in name or name.startswith("."):
            problems.append(f"{FRAMES_CSV}:{lineno}: frame name {name!r} escapes frames/; row skipped")
            continue
        if name in seen:
            problems.append(f"{FRAMES_CSV}:{lineno}: duplicate frame {name!r} skipped")
            continue
        bad = _image_ok(root / FRAMES_DIR / name, decode_images)
        if bad == "missing":
            problems.append(f"{FRAMES_CSV}:{lineno}: row without image frames/{name}; skipped")
            continue
        if bad:
            problems.append(f"frames/{name}: {bad}; skipped")
            continue
        seen.add(name)
        frames.append((name, t_us))
    tlog = read_tlog(root / TLOG)
    problems.extend(tlog.problems)
    class_names = None
    if (root / CLASSES_TXT).is_file():
        class_names = [ln.strip() for ln in (root / CLASSES_TXT).read_text().splitlines() if ln.strip()]
    for p in problems:
        if p not in tlog.problems:  # read_tlog logged its own already
            log.warning("%s: %s", root, p)
    return Flight(root, camera, frames, tlog, problems, class_names)
