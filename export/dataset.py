"""YOLO-format datasets: ``data.yaml`` reading, label parsing, and training augmentation.

``data.yaml`` keys (as ultralytics reads them): ``path`` (root; relative to the yaml's folder,
default that folder), ``train`` and ``val`` (each a folder of images, a .txt list of image
paths, or a list of those; relative to ``path``), ``names`` (dict ``{0: name}`` or list), ``nc``
optional. Labels: for ``.../images/X.png`` the file ``.../labels/X.txt`` with lines
``class cx cy w h`` normalised to 0..1. Tolerant by design: an image without a label file is
background, malformed lines are skipped with a warning, boxes are clipped to the image.

Training samples are [3,S,S] float32 RGB 0..1 with targets [M,6] rows
(batch index, class, x0, y0, x1, y1) in pixels of the sample.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from export.infer import letterbox

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"}


class DatasetError(ValueError):
    """The data.yaml or the dataset it points to cannot be used."""


@dataclass
class DataConfig:
    """A parsed data.yaml: image lists per split and class names."""

    root: Path
    train: list[Path]
    val: list[Path]
    names: dict[int, str]

    @property
    def nc(self) -> int:
        return len(self.names)


def _list_images(spec, root: Path) -> list[Path]:
    if spec is None:
        return []
    if isinstance(spec, (list, tuple)):
        return [p for s in spec for p in _list_images(s, root)]
    p = Path(str(spec))
    p = p if p.is_absolute() else root / p
    if p.is_dir():
        return sorted(q for q in p.rglob("*") if q.suffix.lower() in IMAGE_SUFFIXES)
    if p.is_file() and p.suffix == ".txt":
        out = []
        for line in p.read_text().splitlines():
            line = line.strip()
            if line:
                q = Path(line)
                out.append(q if q.is_absolute() else (p.parent / q if line.startswith(".") else root / q))
        return out
    raise DatasetError(f"dataset split {spec!r} not found (looked for {p})")


def load_data_config(path: str | Path) -> DataConfig:
    """Read ``data.yaml``; raises :class:`DatasetError` with the reason if unusable."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"data.yaml not found: {path}")
    try:
        cfg = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path} is not valid YAML: {exc}") from exc
    if not isinstance(cfg, dict):
        raise DatasetError(f"{path}: expected a mapping with train/val/names")
    root = Path(str(cfg.get("path") or path.parent))
    root = root if root.is_absolute() else (path.parent / root).resolve()
    names = cfg.get("names")
    if isinstance(names, list):
        names = dict(enumerate(names))
    if not isinstance(names, dict) or not names:
        nc = cfg.get("nc")
        if not isinstance(nc, int) or nc < 1:
            raise DatasetError(f"{path}: 'names' (dict or list) or 'nc' is required")
        names = {i: f"class{i}" for i in range(nc)}
    names = {int(k): str(v) for k, v in names.items()}
    if sorted(names) != list(range(len(names))):
        raise DatasetError(f"{path}: class ids must be 0..{len(names) - 1}, got {sorted(names)}")
    if "train" not in cfg and "val" not in cfg:
        raise DatasetError(f"{path}: needs 'train' and/or 'val'")
    return DataConfig(root, _list_images(cfg.get("train"), root), _list_images(cfg.get("val"), root), names)


def label_path(image: Path) -> Path:
    """``.../images/a/b.png`` → ``.../labels/a/b.txt`` (last 'images' component), else beside the image."""
    parts = list(image.parts)
    for i in range(len(parts) - 2, -1, -1):
        if parts[i] == "images":
            parts[i] = "labels"
            return Path(*parts).with_suffix(".txt")
    return image.with_suffix(".txt")


def read_labels(path: Path, nc: int) -> np.ndarray:
    """[M,5] float32 rows (class, cx, cy, w, h) normalised; missing file → empty (background)."""
    if not path.is_file():
        return np.zeros((0, 5), np.float32)
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        try:
            vals = [float(v) for v in parts[:5]]
        except ValueError:
            vals = []
        if len(vals) != 5 or not all(math.isfinite(v) for v in vals) or not 0 <= vals[0] < nc \
                or vals[0] != int(vals[0]):
            log.warning("%s:%d: skipping malformed label %r", path, n, line.strip()[:80])
            continue
        rows.append(vals)
    if not rows:
        return np.zeros((0, 5), np.float32)
    lab = np.asarray(rows, np.float32)
    # clip boxes to the image, drop degenerate ones
    x0 = np.clip(lab[:, 1] - lab[:, 3] / 2, 0, 1)
    x1 = np.clip(lab[:, 1] + lab[:, 3] / 2, 0, 1)
    y0 = np.clip(lab[:, 2] - lab[:, 4] / 2, 0, 1)
    y1 = np.clip(lab[:, 2] + lab[:, 4] / 2, 0, 1)
    lab = np.stack([lab[:, 0], (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0], 1)
    return lab[(lab[:, 3] > 0) & (lab[:, 4] > 0)]


def load_rgb(path: Path) -> np.ndarray:
    """Image file → HxWx3 RGB uint8 (greyscale expanded)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"cannot read image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


@dataclass
class AugmentConfig:
    """Training augmentation (the usual YOLOv8 recipe, defaults as published)."""

    mosaic: float = 1.0     #: probability of a 4-image mosaic
    degrees: float = 0.0
    translate: float = 0.1  #: fraction of the image size
    scale: float = 0.5      #: zoom gain range ±
    fliplr: float = 0.5
    flipud: float = 0.0
    hsv_h: float = 0.015
    hsv_s: float = 0.7
    hsv_v: float = 0.4


class YoloDataset:
    """Images (resized so the long side is ``imgsz``, cached in RAM) with labels in pixels."""

    def __init__(self, images: list[Path], nc: int, imgsz: int = 640, augment: AugmentConfig | None = None,
                 seed: int = 0):
        if not images:
            raise DatasetError("dataset split has no images")
        self.files = list(images)
        self.imgsz = imgsz
        self.augment = augment
        self.rng = np.random.default_rng(seed)
        self.labels = [read_labels(label_path(p), nc) for p in self.files]
        self._cache: dict[int, np.ndarray] = {}
        n_bg = sum(len(lab) == 0 for lab in self.labels)
        log.info("dataset: %d images, %d boxes, %d background", len(self.files),
                 sum(len(lab) for lab in self.labels), n_bg)

    def __len__(self) -> int:
        return len(self.files)

    def load_resized(self, i: int) -> np.ndarray:
        img = self._cache.get(i)
        if img is None:
            img = load_rgb(self.files[i])
            h, w = img.shape[:2]
            r = self.imgsz / max(h, w)
            if r != 1:
                img = cv2.resize(img, (max(1, round(w * r)), max(1, round(h * r))),
                                 interpolation=cv2.INTER_LINEAR if r > 1 else cv2.INTER_AREA)
            self._cache[i] = img
        return img

    def boxes_px(self, i: int, w: int, h: int) -> np.ndarray:
        """[M,5] rows (class, x0, y0, x1, y1) in pixels of a w x h image."""
        lab = self.labels[i]
        out = np.zeros((len(lab), 5), np.float32)
        out[:, 0] = lab[:, 0]
        out[:, 1] = (lab[:, 1] - lab[:, 3] / 2) * w
        out[:, 2] = (lab[:, 2] - lab[:, 4] / 2) * h
        out[:, 3] = (lab[:, 1] + lab[:, 3] / 2) * w
        out[:, 4] = (lab[:, 2] + lab[:, 4] / 2) * h
        return out

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(HxWx3 uint8 S x S image, [M,5] class + x0y0x1y1 pixels)."""
        aug = self.augment
        s = self.imgsz
        if aug and self.rng.random() < aug.mosaic:
            img, boxes = self._mosaic(i)
            img, boxes = self._affine(img, boxes, border=-s // 2)
        else:
            src = self.load_resized(i)
            img, lb = letterbox(src, (s, s))
            boxes = self.boxes_px(i, src.shape[1], src.shape[0])
            boxes[:, [1, 3]] = boxes[:, [1, 3]] * lb.scale + lb.pad_x
            boxes[:, [2, 4]] = boxes[:, [2, 4]] * lb.scale + lb.pad_y
            if aug:
                img, boxes = self._affine(img, boxes, border=0)
        if aug:
            img = self._hsv(img)
            if self.rng.random() < aug.fliplr:
                img = np.ascontiguousarray(img[:, ::-1])
                boxes[:, [1, 3]] = s - boxes[:, [3, 1]]
            if self.rng.random() < aug.flipud:
                img = np.ascontiguousarray(img[::-1])
                boxes[:, [2, 4]] = s - boxes[:, [4, 2]]
        return img, boxes

    def _mosaic(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        s = self.imgsz
        yc, xc = (int(self.rng.uniform(s / 2, 3 * s / 2)) for _ in range(2))
        idx = [i, *self.rng.integers(0, len(self), 3).tolist()]
        canvas = np.full((2 * s, 2 * s, 3), 114, np.uint8)
        all_boxes = []
        for k, j in enumerate(idx):
            img = self.load_resized(j)
            h, w = img.shape[:2]
            if k == 0:    # top left
                x1a, y1a, x2a, y2a = max(xc - w, 0), max(yc - h, 0), xc, yc
                x1b, y1b, x2b, y2b = w - (x2a - x1a), h - (y2a - y1a), w, h
            elif k == 1:  # top right
                x1a, y1a, x2a, y2a = xc, max(yc - h, 0), min(xc + w, 2 * s), yc
                x1b, y1b, x2b, y2b = 0, h - (y2a - y1a), min(w, x2a - x1a), h
            elif k == 2:  # bottom left
                x1a, y1a, x2a, y2a = max(xc - w, 0), yc, xc, min(2 * s, yc + h)
                x1b, y1b, x2b, y2b = w - (x2a - x1a), 0, w, min(y2a - y1a, h)
            else:         # bottom right
                x1a, y1a, x2a, y2a = xc, yc, min(xc + w, 2 * s), min(2 * s, yc + h)
                x1b, y1b, x2b, y2b = 0, 0, min(w, x2a - x1a), min(y2a - y1a, h)
            canvas[y1a:y2a, x1a:x2a] = img[y1b:y2b, x1b:x2b]
            b = self.boxes_px(j, w, h)
            b[:, [1, 3]] += x1a - x1b
            b[:, [2, 4]] += y1a - y1b
            all_boxes.append(b)
        boxes = np.concatenate(all_boxes)
        np.clip(boxes[:, 1:], 0, 2 * s, out=boxes[:, 1:])
        return canvas, boxes

    def _affine(self, img: np.ndarray, boxes: np.ndarray, border: int) -> tuple[np.ndarray, np.ndarray]:
        """Random rotation/scale/translation; output S x S (``border`` < 0 crops a mosaic canvas)."""
        aug = self.augment
        s = self.imgsz
        h, w = img.shape[0] + 2 * border, img.shape[1] + 2 * border
        C = np.eye(3)
        C[0, 2], C[1, 2] = -img.shape[1] / 2, -img.shape[0] / 2
        R = np.eye(3)
        a = self.rng.uniform(-aug.degrees, aug.degrees)
        sc = self.rng.uniform(1 - aug.scale, 1 + aug.scale)
        R[:2] = cv2.getRotationMatrix2D((0, 0), a, sc)
        T = np.eye(3)
        T[0, 2] = self.rng.uniform(0.5 - aug.translate, 0.5 + aug.translate) * w
        T[1, 2] = self.rng.uniform(0.5 - aug.translate, 0.5 + aug.translate) * h
        M = T @ R @ C
        out = cv2.warpAffine(img, M[:2], (w, h), borderValue=(114, 114, 114))
        assert out.shape[:2] == (s, s)
        if len(boxes):
            corners = boxes[:, [1, 2, 3, 2, 3, 4, 1, 4]].reshape(-1, 2)
            xy = (np.c_[corners, np.ones(len(corners))] @ M.T)[:, :2].reshape(-1, 8)
            new = np.stack([xy[:, 0::2].min(1), xy[:, 1::2].min(1), xy[:, 0::2].max(1), xy[:, 1::2].max(1)], 1)
            new = np.clip(new, 0, s)
            # keep boxes with enough area left (≥ 10 % of the transformed box) and ≥ 2 px sides
            w0 = (boxes[:, 3] - boxes[:, 1]) * sc
            h0 = (boxes[:, 4] - boxes[:, 2]) * sc
            nw, nh = new[:, 2] - new[:, 0], new[:, 3] - new[:, 1]
            ok = (nw > 2) & (nh > 2) & (nw * nh / np.maximum(w0 * h0, 1e-9) > 0.1)
            boxes = np.c_[boxes[ok, :1], new[ok]].astype(np.float32)
        return out, boxes

    def _hsv(self, img: np.ndarray) -> np.ndarray:
        aug = self.augment
        r = self.rng.uniform(-1, 1, 3) * [aug.hsv_h, aug.hsv_s, aug.hsv_v] + 1
        hue, sat, val = cv2.split(cv2.cvtColor(img, cv2.COLOR_RGB2HSV))
        x = np.arange(256, dtype=np.float32)
        lut_h = ((x * r[0]) % 180).astype(np.uint8)
        lut_s = np.clip(x * r[1], 0, 255).astype(np.uint8)
        lut_v = np.clip(x * r[2], 0, 255).astype(np.uint8)
        hsv = cv2.merge((cv2.LUT(hue, lut_h), cv2.LUT(sat, lut_s), cv2.LUT(val, lut_v)))
        return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


def collate(samples: list[tuple[np.ndarray, np.ndarray]]):
    """List of (image, boxes) → (float32 [B,3,S,S] 0..1, [M,6] rows (batch idx, class, x0,y0,x1,y1))."""
    imgs = np.stack([s[0] for s in samples]).transpose(0, 3, 1, 2).astype(np.float32) / 255.0
    targets = [np.c_[np.full((len(b), 1), k, np.float32), b] for k, (_, b) in enumerate(samples)]
    return imgs, (np.concatenate(targets) if targets else np.zeros((0, 6), np.float32)).astype(np.float32)
