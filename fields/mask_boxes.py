"""Mask blobs → bounding boxes: the labels of synthetic views (no human in the loop).

Input is a rendered soft mask: per-pixel probabilities ``(H, W, K)`` over K channels where channel
0 is background and channel c >= 1 is class c - 1 (YOLO class id). At 50 m a person is a few
pixels, masks are soft at their edges, and neighbours can touch, so the rules are explicit:

1. Foreground: ``1 - p_background >= threshold`` (default 0.5, the same half-coverage rule the
   simulator uses for its ground-truth boxes). Optionally the foreground probability is first
   smoothed (Gaussian, ``smooth_px`` sigma); the thresholded foreground is closed (binary
   closing, square of side ``2 close_px + 1``, default 2 → 5 px): a rendered person at 15 m is
   often a column of speckled fragments, each of which would otherwise be its own box. The price:
   people closer than ~``2 close_px`` px merge into one blob.
2. Blobs: 8-connected components of the foreground. With ``relative_threshold`` r > 0 each blob
   keeps only its pixels with foreground >= r x the blob's peak, and what is left is split again
   into 8-connected blobs: the edge of a blurred filled box lies at half its peak whatever the
   peak (soft masks at altitude peak well below 1), and a faint bridge between two strong people
   falls below the cut. With ``threshold`` lowered this way also finds faint people.
3. Class: the class with the largest summed probability over the blob. If a second class holds at
   least ``class_split_share`` of the blob's class mass, the blob is split by per-pixel argmax
   class (two touching people of different classes).
4. Touching people of one class (off by default, ``peak_dip=None``: on rendered field masks the
   split cut standing people into fragments more often than it separated neighbours, see
   bench/RESULTS.md session 4): a blob is split when its (lightly smoothed) foreground
   probability has two or more peaks, at least ``min_peak_separation_px`` apart, with a dip of at
   least ``peak_dip`` in the raw probability along the straight line between every pair; pixels
   go to the peak they flow to (watershed). A hard 0/1 mask therefore never splits, and a split
   that would leave a piece under ``min_area_px`` is not made.
5. Area and confidence: blobs with fewer than ``min_area_px`` pixels, or whose mean foreground
   probability is below ``min_score`` (faint halo or fragment blobs), are dropped.
6. Border: a blob touching the image border is dropped when an expected person size is known
   (``expected_size_px``, a person's largest extent in pixels at that range) and the blob's
   largest extent is below ``(1 - max_border_cut)`` of it, i.e. more than that share is cut off;
   without an expected size, border blobs are kept.

Boxes are pixel edges ``(x0, y0, x1, y1)``: x0, y0 inclusive, x1, y1 exclusive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class BoxRules:
    threshold: float = 0.5
    min_area_px: int = 4
    class_split_share: float = 0.35
    min_peak_separation_px: float = 3.0
    #: dip in foreground probability between two peaks that splits a blob (rule 4); None: never split.
    #: Off by default: at 300 s the 15 m held-out masks scored better without it (bench/RESULTS.md)
    peak_dip: float | None = None
    max_border_cut: float = 0.5
    expected_size_px: float | None = None
    #: blobs whose mean foreground probability is below this are dropped (0: keep all)
    min_score: float = 0.0
    #: share of a blob's peak foreground probability below which its pixels are cut off (rule 2;
    #: 0: off, a blob is its ``threshold`` region; 0.5: half-maximum edges)
    relative_threshold: float = 0.0
    #: Gaussian sigma (pixels) applied to the foreground probability before every other rule (0: off)
    smooth_px: float = 0.0
    #: binary closing of the thresholded foreground, square of side 2 close_px + 1 pixels (0: off);
    #: 2 = the best of 0-3 on the 15 m held-out masks (bench/RESULTS.md session 4)
    close_px: int = 2


@dataclass(frozen=True)
class MaskBox:
    class_id: int
    x0: int
    y0: int
    x1: int
    y1: int
    area_px: int
    score: float  # mean foreground probability over the blob

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    def yolo(self, width: int, height: int) -> str:
        cx = 0.5 * (self.x0 + self.x1) / width
        cy = 0.5 * (self.y0 + self.y1) / height
        return f"{self.class_id} {cx:.6f} {cy:.6f} {self.width / width:.6f} {self.height / height:.6f}"


_EIGHT = np.ones((3, 3), bool)


def boxes_from_probabilities(prob: np.ndarray, rules: BoxRules | None = None) -> list[MaskBox]:
    """Boxes from a soft mask ``prob`` (H, W, K), channel 0 background; see the module rules."""
    rules = rules or BoxRules()
    prob = np.asarray(prob, dtype=np.float32)
    if prob.ndim != 3 or prob.shape[2] < 2:
        raise ValueError(f"mask must be (H, W, K>=2) with channel 0 background, got {prob.shape}")
    prob = np.nan_to_num(prob, nan=0.0, posinf=1.0, neginf=0.0).clip(0.0, 1.0)
    fg = 1.0 - prob[..., 0]
    if rules.smooth_px > 0.0:
        fg = ndimage.gaussian_filter(fg, rules.smooth_px, mode="nearest")
    cls_prob = prob[..., 1:]
    on = fg >= rules.threshold
    if rules.close_px > 0:
        k = 2 * int(rules.close_px) + 1
        # pad so that closing does not erode blobs at the image border
        on = ndimage.binary_closing(np.pad(on, k), np.ones((k, k), bool))[k:-k, k:-k]
    labels, n = ndimage.label(on, structure=_EIGHT)
    boxes: list[MaskBox] = []
    for blob_id, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        for core in _cut_below_peak_share(labels[sl] == blob_id, fg[sl], rules):
            for part, class_id in _split_by_class(core, cls_prob[sl], rules):
                for piece in _split_by_peaks(part, fg[sl], rules):
                    box = _box_of(piece, sl, fg[sl], class_id)
                    if box is not None and _keep(box, prob.shape[:2], rules):
                        boxes.append(box)
    return boxes


def boxes_from_class_map(class_map: np.ndarray, min_area_px: int = 4) -> list[MaskBox]:
    """Boxes from a hard class map (0 background, c + 1 class c): one per 8-connected blob of each class."""
    m = np.asarray(class_map)
    boxes = []
    for c in np.unique(m):
        if c == 0:
            continue
        labels, _ = ndimage.label(m == c, structure=_EIGHT)
        for k, sl in enumerate(ndimage.find_objects(labels), start=1):
            if sl is None:
                continue
            piece = labels[sl] == k
            box = _box_of(piece, sl, piece.astype(np.float32), int(c) - 1)
            if box is not None and box.area_px >= min_area_px:
                boxes.append(box)
    return boxes


def box_iou(a, b) -> float:
    """IoU of two boxes with ``x0, y0, x1, y1`` attributes (pixel edges)."""
    ix = max(0.0, min(a.x1, b.x1) - max(a.x0, b.x0))
    iy = max(0.0, min(a.y1, b.y1) - max(a.y0, b.y0))
    inter = ix * iy
    union = (a.x1 - a.x0) * (a.y1 - a.y0) + (b.x1 - b.x0) * (b.y1 - b.y0) - inter
    return inter / union if union > 0 else 0.0


def boxes_from_instances(instance_ids: np.ndarray, class_of: dict[int, int],
                         rules: BoxRules | None = None) -> list[MaskBox]:
    """Boxes from a hard instance map (0 = background), one per instance: no merge or split."""
    rules = rules or BoxRules()
    ids = np.asarray(instance_ids)
    boxes = []
    for inst, sl in enumerate(ndimage.find_objects(ids.astype(np.int64)), start=1):
        if sl is None:
            continue
        piece = ids[sl] == inst
        box = _box_of(piece, sl, piece.astype(np.float32), class_of.get(inst, 0))
        if box is not None and _keep(box, ids.shape, rules):
            boxes.append(box)
    return boxes


def _cut_below_peak_share(blob: np.ndarray, fg: np.ndarray, rules: BoxRules):
    """Yield the 8-connected parts of ``blob`` whose foreground is >= ``relative_threshold`` x the
    blob's peak (the blob itself when the rule is off)."""
    if rules.relative_threshold <= 0.0:
        yield blob
        return
    core = blob & (fg >= rules.relative_threshold * float(fg[blob].max()))
    part_labels, m = ndimage.label(core, structure=_EIGHT)
    for k in range(1, m + 1):
        yield part_labels == k


def _split_by_class(blob: np.ndarray, cls_prob: np.ndarray, rules: BoxRules):
    """Yield (mask, class_id) parts of a blob: one part, or one per class when classes share it."""
    mass = (cls_prob * blob[..., None]).sum(axis=(0, 1))
    order = np.argsort(mass)[::-1]
    total = float(mass.sum())
    if total <= 0.0:
        yield blob, int(order[0])
        return
    if len(order) < 2 or mass[order[1]] < rules.class_split_share * total:
        yield blob, int(order[0])
        return
    per_pixel = np.argmax(cls_prob, axis=-1)
    for c in np.unique(per_pixel[blob]):
        part_labels, m = ndimage.label(blob & (per_pixel == c), structure=_EIGHT)
        for k in range(1, m + 1):
            yield part_labels == k, int(c)


def _split_by_peaks(part: np.ndarray, fg: np.ndarray, rules: BoxRules) -> list[np.ndarray]:
    """Split one blob at probability dips between well-separated peaks (watershed)."""
    if rules.peak_dip is None or part.sum() < 2 * rules.min_area_px:
        return [part]
    smooth = ndimage.gaussian_filter(np.where(part, fg, 0.0), 0.7)
    peaks = (smooth == ndimage.maximum_filter(smooth, size=3)) & part & (fg >= rules.threshold)
    coords = np.argwhere(peaks)
    if len(coords) < 2:
        return [part]
    # Keep the strongest peak of each cluster closer than the minimum separation.
    order = np.argsort(-smooth[peaks])
    seeds: list[np.ndarray] = []
    for p in coords[order]:
        if all(np.hypot(*(p - q)) >= rules.min_peak_separation_px for q in seeds):
            seeds.append(p)
    if len(seeds) < 2:
        return [part]
    # A real split needs a dip between the seeds along the line joining them.
    # The dip is measured on the raw probability: a hard (0/1) mask never splits, however thin
    # its limbs; only a field that itself was unsure between two people does.
    raw = np.where(part, fg, 0.0)
    good = [seeds[0]]
    for q in seeds[1:]:
        if all(_dip(raw, p, q) >= rules.peak_dip for p in good):
            good.append(q)
    if len(good) < 2:
        return [part]
    owner = _flood(smooth, part, good)
    pieces = [owner == k for k in range(1, len(good) + 1)]
    if any(piece.sum() < rules.min_area_px for piece in pieces):
        return [part]
    return pieces


def _flood(height: np.ndarray, part: np.ndarray, seeds: list[np.ndarray]) -> np.ndarray:
    """Priority flood (watershed) from ``seeds`` over ``part``, highest ``height`` first.

    Returns an int map: k for pixels reached first from seed k (1-based), 0 outside ``part``.
    Blobs are small (a person at altitude is tens to hundreds of pixels), so a heap is enough.
    """
    import heapq

    owner = np.zeros(part.shape, np.int32)
    heap = []
    for k, (r, c) in enumerate(seeds, start=1):
        owner[r, c] = k
        heapq.heappush(heap, (-float(height[r, c]), int(r), int(c)))
    h, w = part.shape
    while heap:
        _, r, c = heapq.heappop(heap)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if 0 <= rr < h and 0 <= cc < w and part[rr, cc] and owner[rr, cc] == 0:
                    owner[rr, cc] = owner[r, c]
                    heapq.heappush(heap, (-float(height[rr, cc]), rr, cc))
    return owner


def _dip(values: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
    n = int(max(abs(q - p))) + 1
    rr = np.linspace(p[0], q[0], n).round().astype(int)
    cc = np.linspace(p[1], q[1], n).round().astype(int)
    line = values[rr, cc]
    return float(min(values[tuple(p)], values[tuple(q)]) - line.min())


def _box_of(piece: np.ndarray, sl, fg: np.ndarray, class_id: int) -> MaskBox | None:
    rows = np.nonzero(piece.any(axis=1))[0]
    cols = np.nonzero(piece.any(axis=0))[0]
    if len(rows) == 0:
        return None
    y0, x0 = sl[0].start + int(rows[0]), sl[1].start + int(cols[0])
    y1, x1 = sl[0].start + int(rows[-1]) + 1, sl[1].start + int(cols[-1]) + 1
    return MaskBox(int(class_id), x0, y0, x1, y1, int(piece.sum()), float(fg[piece].mean()))


def _keep(box: MaskBox, shape, rules: BoxRules) -> bool:
    if box.area_px < rules.min_area_px or box.score < rules.min_score:
        return False
    h, w = shape
    if rules.expected_size_px is None:
        return True
    on_border = box.x0 == 0 or box.y0 == 0 or box.x1 == w or box.y1 == h
    need = (1.0 - rules.max_border_cut) * rules.expected_size_px
    return not (on_border and max(box.width, box.height) < need)
