"""Pinhole camera model shared by the whole project (simulator, SfM, fields, synthesis).

Pixel convention (COLMAP / nerfstudio): the centre of the top-left pixel is at (0.5, 0.5), so a
centred principal point is ``cx = width / 2``. Camera axes are OpenCV's (x right, y down,
z forward). Optional Brown-Conrady distortion ``[k1, k2, p1, p2]`` as in OpenCV and COLMAP's
OPENCV model. ``camera.json`` (DESIGN.md §3) round-trips through :meth:`Camera.to_json` and
:meth:`Camera.from_json`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class CameraError(ValueError):
    """An invalid camera description (``camera.json``)."""


@dataclass(frozen=True)
class Mount:
    """Camera boresight relative to the body FRD frame, Z-Y-X Euler angles in degrees."""

    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels and the camera mount."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    mount: Mount = field(default_factory=Mount)

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy, *self.distortion)
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"camera size must be positive, got {self.width}x{self.height}")
        if not all(math.isfinite(v) for v in values):
            raise CameraError(f"camera intrinsics must be finite, got {values}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, mount: Mount | None = None) -> Camera:
        """Square-pixel camera with the principal point at the image centre."""
        if not 0.0 < hfov_deg < 180.0:
            raise CameraError(f"horizontal field of view must be in (0, 180) deg, got {hfov_deg}")
        f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0, mount=mount or Mount())

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (pixel-centre convention kept)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      self.distortion, self.mount)

    # ---- camera.json --------------------------------------------------------------------
    def to_json(self) -> dict:
        d = {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
             "cx": self.cx, "cy": self.cy,
             "mount": {"roll_deg": self.mount.roll_deg, "pitch_deg": self.mount.pitch_deg,
                       "yaw_deg": self.mount.yaw_deg}}
        if any(self.distortion):
            d["distortion"] = list(self.distortion)
        return d

    @classmethod
    def from_json(cls, d: dict) -> Camera:
        try:
            dist = tuple(float(v) for v in d.get("distortion") or (0.0, 0.0, 0.0, 0.0))
            if len(dist) != 4:
                raise CameraError(f"distortion must be [k1, k2, p1, p2], got {d.get('distortion')}")
            m = d.get("mount") or {}
            mount = Mount(float(m.get("roll_deg", 0.0)), float(m.get("pitch_deg", 0.0)),
                          float(m.get("yaw_deg", 0.0)))
            return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                       float(d["cx"]), float(d["cy"]), dist, mount)
        except KeyError as exc:
            raise CameraError(f"camera.json lacks the key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            if isinstance(exc, CameraError):
                raise
            raise CameraError(f"camera.json has a bad value: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> Camera:
        path = Path(path)
        try:
            return cls.from_json(json.loads(path.read_text()))
        except FileNotFoundError:
            raise CameraError(f"{path}: no such file") from None
        except json.JSONDecodeError as exc:
            raise CameraError(f"{path}: not valid JSON ({exc})") from None

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")

    # ---- geometry -----------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (pixel-centre-at-0.5 convention)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.distortion)

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k1, k2, p1, p2 = self.distortion
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return xd, yd

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points (N,3) to pixels (N,2); also returns ``in_front`` (N,) bool.

        Points at or behind the camera plane get NaN pixels and ``in_front = False``.
        """
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        in_front = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(in_front, p[:, 0] / z, np.nan)
            y = np.where(in_front, p[:, 1] / z, np.nan)
        if self.has_distortion:
            x, y = self._distort(x, y)
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)
        return uv, in_front

    def project_world(self, points_world: np.ndarray, cam_from_world: np.ndarray):
        """Project world points (N,3) with a 4x4 ``cam_from_world``; see :meth:`project`."""
        T = np.asarray(cam_from_world, dtype=np.float64)
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return self.project(p @ T[:3, :3].T + T[:3, 3])

    def pixel_grid(self, supersample: int = 1) -> np.ndarray:
        """Pixel coordinates (H*s, W*s, 2) of an ``s x s`` stratified grid inside every pixel."""
        s = int(supersample)
        u = (np.arange(self.width * s, dtype=np.float64) + 0.5) / s
        v = (np.arange(self.height * s, dtype=np.float64) + 0.5) / s
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions in the camera frame for pixel coordinates (..., 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        if self.has_distortion:
            x, y = self._undistort(x, y)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def _undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 20):
        """Invert the distortion by Newton's method on the 2x2 Jacobian (normalised coordinates)."""
        k1, k2, p1, p2 = self.distortion
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            fx_, fy_ = self._distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            g = 2.0 * (k1 + 2.0 * k2 * r2)  # d(radial)/dx = g * x
            j11 = radial + g * x * x + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + g * y * y + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (j11 * ey - j21 * ex) / det
            if max(np.abs(ex).max(initial=0.0), np.abs(ey).max(initial=0.0)) < 1e-12:
                break
        return x, y

    def rays_world(self, cam_from_world: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-frame ray origin (3,) and unit directions (..., 3) through pixels ``uv``."""
        T = np.asarray(cam_from_world, dtype=np.float64)
        R = T[:3, :3]
        origin = -R.T @ T[:3, 3]
        dirs = self.unproject(uv) @ R  # (R.T @ d) for row vectors
        return origin, dirs

    @property
    def pixel_rad(self) -> float:
        """The angle one pixel subtends at the image centre, radians (1 / the mean focal length in px)."""
        return 2.0 / (self.fx + self.fy)

    def ground_sample_distance(self, range_m: float) -> float:
        """Metres per pixel at ``range_m`` along the optical axis (mean of fx, fy)."""
        return range_m * 2.0 / (self.fx + self.fy)
