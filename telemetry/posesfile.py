"""The poses file (``derived/poses.json``, also the input of ``uavsim render``): read, write, validate.

Contract (DESIGN.md §3)::

    {"origin": {"lat": deg, "lon": deg, "alt": m AMSL},
     "camera": {camera.json contents},
     "frames": [{"frame": "000123.jpg" | null, "t_unix_us": int | null,
                 "cam_from_world": 4x4 nested lists | null, "source": "telemetry" | "sfm" | "novel",
                 "reason": "..." (only when cam_from_world is null)}]}

``cam_from_world`` is OpenCV (x right, y down, z forward), world = local ENU metres of ``origin``.
Frames that could not be posed carry ``"cam_from_world": null`` and a ``"reason"``. Extra keys of a
frame (e.g. per-frame quality numbers) are kept in :attr:`PoseEntry.extra` and written back.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from telemetry.camera import Camera

SOURCES = ("telemetry", "sfm", "novel")
_KNOWN_KEYS = {"frame", "t_unix_us", "cam_from_world", "source", "reason"}


class PosesFileError(ValueError):
    """A poses file that does not follow the contract."""


@dataclass(frozen=True)
class Origin:
    """Geodetic origin of the local ENU frame: degrees, degrees, metres above mean sea level."""

    lat: float
    lon: float
    alt: float


@dataclass
class PoseEntry:
    """One frame (or novel pose). ``cam_from_world`` is a 4x4 float64 array or None (unposed)."""

    frame: str | None
    t_unix_us: int | None
    cam_from_world: np.ndarray | None
    source: str
    reason: str | None = None
    extra: dict = field(default_factory=dict)

    @property
    def posed(self) -> bool:
        return self.cam_from_world is not None


@dataclass
class PosesFile:
    origin: Origin
    camera: Camera
    frames: list[PoseEntry]

    def posed(self) -> list[PoseEntry]:
        return [f for f in self.frames if f.posed]

    def to_json(self) -> dict:
        frames = []
        for f in self.frames:
            d = {"frame": f.frame, "t_unix_us": f.t_unix_us,
                 "cam_from_world": None if f.cam_from_world is None
                 else np.asarray(f.cam_from_world, float).tolist(),
                 "source": f.source}
            if f.cam_from_world is None:
                d["reason"] = f.reason or "unposed"
            elif f.reason:
                d["reason"] = f.reason
            d.update(f.extra)
            frames.append(d)
        return {"origin": {"lat": self.origin.lat, "lon": self.origin.lon, "alt": self.origin.alt},
                "camera": self.camera.to_json(), "frames": frames}

    def save(self, path: str | Path) -> None:
        """Write atomically (temp file + rename) so a crash never leaves half a file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "w") as fh:
            json.dump(self.to_json(), fh, indent=1)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> PosesFile:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise PosesFileError(f"{path}: no such poses file") from None
        except json.JSONDecodeError as exc:
            raise PosesFileError(f"{path}: not valid JSON ({exc})") from None
        try:
            return cls.from_json(data)
        except PosesFileError as exc:
            raise PosesFileError(f"{path}: {exc}") from None

    @classmethod
    def from_json(cls, data: dict) -> PosesFile:
        if not isinstance(data, dict):
            raise PosesFileError("top level must be an object")
        for key in ("origin", "camera", "frames"):
            if key not in data:
                raise PosesFileError(f"missing key {key!r}")
        o = data["origin"]
        try:
            origin = Origin(float(o["lat"]), float(o["lon"]), float(o["alt"]))
        except (KeyError, TypeError, ValueError):
            raise PosesFileError(f"origin must have numeric lat, lon, alt, got {o!r}") from None
        if not all(math.isfinite(v) for v in (origin.lat, origin.lon, origin.alt)):
            raise PosesFileError(f"origin must be finite, got {o!r}")
        camera = Camera.from_json(data["camera"])
        if not isinstance(data["frames"], list):
            raise PosesFileError("frames must be a list")
        frames = [_entry_from_json(i, d) for i, d in enumerate(data["frames"])]
        return cls(origin, camera, frames)


def _entry_from_json(i: int, d: dict) -> PoseEntry:
    if not isinstance(d, dict):
        raise PosesFileError(f"frame {i} must be an object")
    source = d.get("source")
    if source not in SOURCES:
        raise PosesFileError(f"frame {i}: source must be one of {SOURCES}, got {source!r}")
    t = d.get("t_unix_us")
    if t is not None and (isinstance(t, bool) or not isinstance(t, int)):
        raise PosesFileError(f"frame {i}: t_unix_us must be an integer or null, got {t!r}")
    T = d.get("cam_from_world")
    if T is not None:
        T = validate_cam_from_world(T, where=f"frame {i}")
    extra = {k: v for k, v in d.items() if k not in _KNOWN_KEYS}
    return PoseEntry(d.get("frame"), t, T, source, d.get("reason"), extra)


def validate_cam_from_world(T, where: str = "pose") -> np.ndarray:
    """A finite rigid 4x4 (rotation orthonormal with det +1, last row 0 0 0 1) as float64."""
    try:
        A = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise PosesFileError(f"{where}: cam_from_world must be a 4x4 numeric matrix") from None
    if A.shape != (4, 4):
        raise PosesFileError(f"{where}: cam_from_world must be 4x4, got shape {A.shape}")
    if not np.isfinite(A).all():
        raise PosesFileError(f"{where}: cam_from_world has NaN or inf")
    R = A[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise PosesFileError(f"{where}: cam_from_world rotation is not orthonormal with det +1")
    if not np.allclose(A[3], [0, 0, 0, 1]):
        raise PosesFileError(f"{where}: cam_from_world last row must be 0 0 0 1")
    return A
