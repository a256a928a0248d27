"""A recorded flight as *dynamic* training data: :class:`fields.data.FlightData` plus capture times.

Times are unix µs (companion clock) from the poses file (``t_unix_us``), else from ``frames.csv``.
They are normalised over the flight to ``t01`` in [0, 1] (first capture 0, last 1; a flight of one
instant gets 0 everywhere). Frames keep the order of the poses file; nothing assumes they are
sorted by time. The *dynamic mask* of a frame is its filled person boxes (class mask > 0): pixels
inside a box are "dynamic" (may belong to a moving person), the rest static — the paper's gating.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fields.data import FlightData, FlightDataError, load_flight
from telemetry.posesfile import PosesFile

log = logging.getLogger(__name__)


@dataclass
class DynamicFlightData:
    """Posed frames with capture times; ``data`` is the static loader's result (same frame order)."""

    data: FlightData
    #: (N,) int64 capture times, unix µs
    times_us: np.ndarray
    #: per frame where its pose came from (the poses file's ``source``: "telemetry", "sfm", "novel")
    pose_sources: tuple[str, ...] = ()

    @property
    def all_poses_sfm(self) -> bool:
        """Every frame's pose was refined by SfM (``source`` "sfm")."""
        return bool(self.pose_sources) and all(s == "sfm" for s in self.pose_sources)

    @property
    def n(self) -> int:
        return self.data.n

    @property
    def t0_us(self) -> int:
        return int(self.times_us.min())

    @property
    def span_us(self) -> int:
        return int(self.times_us.max() - self.times_us.min())

    def t01(self, t_us=None) -> np.ndarray:
        """Normalised time of ``t_us`` (default: the frames'), clamped to [0, 1]."""
        t = self.times_us if t_us is None else np.asarray(t_us, dtype=np.int64)
        return normalise_times(t, self.t0_us, self.span_us)

    def dynamic_masks(self) -> torch.Tensor:
        """(N, H, W) bool: inside a labelled person box."""
        return self.data.masks > 0

    def split_alternate(self) -> tuple[list[int], list[int]]:
        """Every other frame *in time order* for training, the rest for validation (the paper's split)."""
        order = [int(i) for i in np.argsort(self.times_us, kind="stable")]
        if len(order) == 1:
            return order, []
        return sorted(order[0::2]), sorted(order[1::2])


def normalise_times(t_us: np.ndarray, t0_us: int, span_us: int) -> np.ndarray:
    """``(t - t0) / span`` clamped to [0, 1] as float32; 0 everywhere when ``span_us`` is 0."""
    t = np.asarray(t_us, dtype=np.int64)
    if span_us <= 0:
        return np.zeros(t.shape, np.float32)
    return np.clip((t - t0_us) / float(span_us), 0.0, 1.0).astype(np.float32)


def time_resolution(n_frames: int) -> int:
    """Grid points along t: half the number of frames (paper), at least 2."""
    return max(2, int(n_frames) // 2)


def _csv_times(flight: Path) -> dict[str, int]:
    p = flight / "frames.csv"
    if not p.is_file():
        return {}
    out = {}
    with p.open(newline="") as fh:
        for row in csv.DictReader(fh):
            try:
                out[row["frame"]] = int(row["t_unix_us"])
            except (KeyError, TypeError, ValueError):
                continue
    return out


def load_dynamic_flight(flight: str | Path, poses_path: str | Path | None = None) -> DynamicFlightData:
    """Load a flight's posed frames and their capture times; raises if a frame has no time."""
    flight = Path(flight)
    data = load_flight(flight, poses_path)
    poses = PosesFile.load(poses_path or flight / "derived" / "poses.json")
    csv_times = None
    times, sources = [], []
    for e in poses.frames:
        if e.cam_from_world is None or e.frame is None:
            continue
        t = e.t_unix_us
        if t is None:
            csv_times = _csv_times(flight) if csv_times is None else csv_times
            t = csv_times.get(e.frame)
        if t is None:
            raise FlightDataError(f"{flight}: frame {e.frame} has no capture time (t_unix_us null in the poses "
                                  "file and not in frames.csv); a dynamic field needs one per frame")
        times.append(int(t))
        sources.append(e.source)
    if len(times) != data.n:
        raise FlightDataError(f"{flight}: {len(times)} timed frames but {data.n} loaded frames")
    return DynamicFlightData(data, np.asarray(times, dtype=np.int64), tuple(sources))
