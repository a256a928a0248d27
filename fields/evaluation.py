"""Image metrics (PSNR, SSIM) and labels from rendered masks (connected components -> boxes).

Images are float arrays in [0, 1] (H, W, 3) or uint8 (converted); masks are (H, W) class ids with
0 = background and ``k + 1`` = class ``k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _float(img) -> np.ndarray:
    a = np.asarray(img)
    return a.astype(np.float64) / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)


def psnr(a, b, valid: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]; ``valid`` (H, W) bool restricts pixels."""
    d = (_float(a) - _float(b)) ** 2
    if valid is not None:
        if not valid.any():
            return float("nan")
        d = d[valid]
    mse = float(d.mean())
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))


def ssim(a, b) -> float:
    """Mean SSIM (Gaussian window 11, sigma 1.5, per channel, as Wang et al. 2004) for [0, 1] images."""
    import cv2

    x, y = _float(a), _float(b)
    c1, c2 = 0.01**2, 0.03**2

    def blur(z):
        return cv2.GaussianBlur(z, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s.mean())


@dataclass
class MaskBox:
    """A box from a mask blob: class id (0-based object class), pixel edges, pixel count."""

    class_id: int
    x0: float
    y0: float
    x1: float
    y1: float
    area_px: int

    def yolo(self, width: int, height: int) -> str:
        cx, cy = (self.x0 + self.x1) / 2 / width, (self.y0 + self.y1) / 2 / height
        return f"{self.class_id} {cx:.6f} {cy:.6f} {(self.x1 - self.x0) / width:.6f} {(self.y1 - self.y0) / height:.6f}"


def boxes_from_mask(mask: np.ndarray, min_area_px: int = 4) -> list[MaskBox]:
    """One box per 8-connected blob of each class; blobs smaller than ``min_area_px`` are dropped."""
    import cv2

    out = []
    m = np.asarray(mask)
    for cls in np.unique(m):
        if cls == 0:
            continue
        n, _, stats, _ = cv2.connectedComponentsWithStats((m == cls).astype(np.uint8), connectivity=8)
        for i in range(1, n):
            x, y, w, h, area = stats[i]
            if area >= min_area_px:
                out.append(MaskBox(int(cls) - 1, float(x), float(y), float(x + w), float(y + h), int(area)))
    return out


def box_iou(a, b) -> float:
    """IoU of two boxes with ``x0, y0, x1, y1`` attributes (pixel edges)."""
    ix = max(0.0, min(a.x1, b.x1) - max(a.x0, b.x0))
    iy = max(0.0, min(a.y1, b.y1) - max(a.y0, b.y0))
    inter = ix * iy
    union = (a.x1 - a.x0) * (a.y1 - a.y0) + (b.x1 - b.x0) * (b.y1 - b.y0) - inter
    return inter / union if union > 0 else 0.0


def match_boxes(truth: list, predicted: list) -> list[float]:
    """Best IoU of any predicted box (any class) for each true box, greedy one-to-one."""
    used: set[int] = set()
    ious = []
    for t in sorted(truth, key=lambda b: -(b.x1 - b.x0) * (b.y1 - b.y0)):
        best, best_j = 0.0, -1
        for j, p in enumerate(predicted):
            if j in used:
                continue
            iou = box_iou(t, p)
            if iou > best:
                best, best_j = iou, j
        if best_j >= 0:
            used.add(best_j)
        ious.append(best)
    return ious
