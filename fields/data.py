"""A recorded flight as training data: posed frames, per-pixel class masks from the labels, rays.

Reads ``derived/poses.json`` (poses-file contract, OpenCV cam_from_world, ENU metres), the images
under ``frames/`` and, when present, ``labels/NAME.txt`` (YOLO) -> a *filled-box* class mask per
frame: 0 = background, ``k + 1`` = class ``k`` (larger boxes drawn first so small ones stay on
top). Frames without a label file get ``has_mask = False`` and do not train the mask head (a
label file that is empty means "no objects": all background, and does train it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from telemetry.camera import Camera
from telemetry.posesfile import PosesFile

log = logging.getLogger(__name__)

DEFAULT_CLASSES = ("standing", "kneeling", "prone")


class FlightDataError(ValueError):
    """A flight folder that cannot be used for fitting."""


def read_classes(flight: Path) -> tuple[str, ...]:
    p = Path(flight) / "classes.txt"
    if p.is_file():
        names = tuple(line.strip() for line in p.read_text().splitlines() if line.strip())
        if names:
            return names
    return DEFAULT_CLASSES


def parse_labels(label_text: str, width: int, height: int, n_classes: int) -> list[tuple]:
    """YOLO label lines -> [(class, x0, y0, x1, y1)] in pixel edges; malformed lines raise."""
    out = []
    for i, line in enumerate(label_text.splitlines()):
        parts = line.split()
        if not parts:
            continue
        if len(parts) < 5:
            raise FlightDataError(f"label line {i + 1}: expected 'class cx cy w h', got {line!r}")
        c = int(float(parts[0]))
        if not 0 <= c < n_classes:
            raise FlightDataError(f"label line {i + 1}: class {c} outside 0..{n_classes - 1}")
        cx, cy, w, h = (float(v) for v in parts[1:5])
        out.append((c, (cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width, (cy + h / 2) * height))
    return out


def box_mask(label_text: str, width: int, height: int, n_classes: int) -> np.ndarray:
    """Filled-box class mask (H, W) uint8 from YOLO label lines; malformed lines raise."""
    mask = np.zeros((height, width), np.uint8)
    boxes = parse_labels(label_text, width, height, n_classes)
    for c, x0, y0, x1, y1 in sorted(boxes, key=lambda b: -(b[3] - b[1]) * (b[4] - b[2])):
        x0, x1 = int(np.floor(x0 + 0.5)), int(np.floor(x1 + 0.5))
        y0, y1 = int(np.floor(y0 + 0.5)), int(np.floor(y1 + 0.5))
        mask[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = c + 1
    return mask


@dataclass
class FlightData:
    """All posed frames of a flight in memory (uint8 images: 60 x 320 x 240 x 3 = 14 MB)."""

    camera: Camera
    names: list[str]
    cam_from_world: list[np.ndarray]
    images: torch.Tensor  # (N, H, W, 3) uint8
    masks: torch.Tensor  # (N, H, W) uint8 class masks
    has_mask: torch.Tensor  # (N,) bool
    classes: tuple[str, ...]
    #: per frame the label boxes [(class, x0, y0, x1, y1)] in pixel edges ([] without labels)
    boxes: list[list[tuple]]

    @property
    def n(self) -> int:
        return len(self.names)

    def split(self, every: int) -> tuple[list[int], list[int]]:
        """Train and held-out frame indices: every ``every``-th frame (index % every == every-1) held out."""
        if every <= 1:
            return list(range(self.n)), []
        test = [i for i in range(self.n) if i % every == every - 1]
        return [i for i in range(self.n) if i % every != every - 1], test


def load_flight(flight: str | Path, poses_path: str | Path | None = None) -> FlightData:
    """Load a recorded flight's posed frames, masks and camera."""
    import cv2

    flight = Path(flight)
    if not flight.is_dir():
        raise FlightDataError(f"{flight}: no such flight folder")
    poses = PosesFile.load(poses_path or flight / "derived" / "poses.json")
    camera = poses.camera
    classes = read_classes(flight)
    names, Ts, imgs, masks, has, boxes = [], [], [], [], [], []
    skipped = 0
    for entry in poses.frames:
        if entry.cam_from_world is None or entry.frame is None:
            skipped += 1
            continue
        path = flight / "frames" / entry.frame
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise FlightDataError(f"{path}: missing or unreadable image")
        if img.shape[:2] != (camera.height, camera.width):
            raise FlightDataError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, "
                                  f"camera says {camera.width}x{camera.height}")
        label = flight / "labels" / (Path(entry.frame).stem + ".txt")
        if label.is_file():
            text = label.read_text()
            try:
                masks.append(box_mask(text, camera.width, camera.height, len(classes)))
                boxes.append(parse_labels(text, camera.width, camera.height, len(classes)))
            except FlightDataError as exc:
                raise FlightDataError(f"{label}: {exc}") from None
            has.append(True)
        else:
            masks.append(np.zeros((camera.height, camera.width), np.uint8))
            boxes.append([])
            has.append(False)
        names.append(entry.frame)
        Ts.append(np.asarray(entry.cam_from_world, np.float64))
        imgs.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    if not names:
        raise FlightDataError(f"{flight}: no posed frames in the poses file ({skipped} unposed)")
    if skipped:
        log.info("skipped %d unposed frames", skipped)
    return FlightData(camera, names, Ts, torch.from_numpy(np.stack(imgs)), torch.from_numpy(np.stack(masks)),
                      torch.tensor(has), classes, boxes)


class RayBank:
    """Rays of all pixels of a set of frames, generated on demand (world ENU, float32, scene-centred).

    Camera-frame unit directions per pixel are computed once (distortion included); a batch of
    (frame, pixel) pairs is rotated into the world with each frame's rotation.
    """

    def __init__(self, camera: Camera, cam_from_world: list[np.ndarray], device="cpu"):
        uv = camera.pixel_grid().reshape(-1, 2)
        self.dirs_cam = torch.from_numpy(camera.unproject(uv)).float().to(device)  # (H*W, 3)
        R = np.stack([np.asarray(T)[:3, :3] for T in cam_from_world])  # cam_from_world rotation
        t = np.stack([np.asarray(T)[:3, 3] for T in cam_from_world])
        self.R_world_cam = torch.from_numpy(np.transpose(R, (0, 2, 1)).copy()).float().to(device)
        self.origins = torch.from_numpy(-np.einsum("nji,nj->ni", R, t)).float().to(device)
        self.hw = camera.height * camera.width

    def rays(self, frame_idx: torch.Tensor, pixel_idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d = torch.einsum("nij,nj->ni", self.R_world_cam[frame_idx], self.dirs_cam[pixel_idx])
        return self.origins[frame_idx], d
