"""Image metrics (PSNR, SSIM) and labels from rendered masks (connected components -> boxes).

Images are float arrays in [0, 1] (H, W, 3) or uint8 (converted); masks are (H, W) class ids with
0 = background and ``k + 1`` = class ``k``.
"""

from __future__ import annotations

import numpy as np

from fields.mask_boxes import MaskBox, box_iou, boxes_from_class_map

__all__ = ["psnr", "ssim", "boxes_from_mask", "box_iou", "match_boxes", "label_boxes", "MaskBox"]


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


def boxes_from_mask(mask: np.ndarray, min_area_px: int = 4) -> list[MaskBox]:
    """One box per 8-connected blob of each class of a class-id mask (0 background, k+1 class k)."""
    return boxes_from_class_map(mask, min_area_px)


def label_boxes(rows) -> list[MaskBox]:
    """Label boxes as :class:`MaskBox`: ``rows`` of (class, x0, y0, x1, y1) in pixel edges (float or int)."""
    return [MaskBox(int(c), x0, y0, x1, y1, 0, 1.0) for c, x0, y0, x1, y1 in rows]


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
