"""Synthesis: render novel views (RGB + mask), turn mask blobs into boxes, write a labelled set.

Output layout (``derived/synth/`` of a flight)::

    images/NAME.jpg      rendered views
    labels/NAME.txt      YOLO labels from mask blobs ("class cx cy w h", normalised)
    masks/NAME.png       optional: argmax class per pixel (0 background, c+1 class c)
    poses.json           poses file, "source": "novel", "frame": "NAME.jpg" (image, label and
                         pose share one stem)
    contact_sheet.png    thumbnails with boxes drawn
    report.json          counts, box statistics, images per minute

The renderer is anything with ``render_view(camera, cam_from_world, t_unix_us) -> (rgb, prob)``:
``rgb`` (H, W, 3) uint8 and ``prob`` (H, W, K) per-pixel probabilities with channel 0 background
and channel c + 1 class c. A fitted field provides one; so does the simulator (ground truth),
which the tests and benchmarks use to measure the box rules alone.

Box classes: the mask's own (the class with the most probability over the blob), or, with
``labels_from`` (:class:`fields.label_transfer.LabelledFrames`), voted by the real frames' labels
that see the blob's 3D points; that needs a renderer with ``render_view_depth`` (a fitted field).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from fields.label_transfer import LabelledFrames
from fields.mask_boxes import BoxRules, MaskBox, box_iou, boxes_from_probabilities
from telemetry.camera import Camera
from telemetry.posesfile import Origin, PoseEntry, PosesFile

log = logging.getLogger(__name__)


class ViewRenderer(Protocol):
    def render_view(self, camera: Camera, cam_from_world: np.ndarray,
                    t_unix_us: int | None) -> tuple[np.ndarray, np.ndarray]: ...


#: box rules for static novel views (35-50 m): foreground threshold 0.6 instead of 0.5. At 50 m the blobs of the
#: filled-box-trained mask are 1-2 px wider than the person; the higher cut narrows them. Chosen on 35/50 m views
#: apart from the benchmark's test views (bench/RESULTS.md, synthesis session 5); the 15 m held-out scores and
#: dynamic views (flown altitude) keep the default 0.5.
HIGH_ALTITUDE_RULES = BoxRules(threshold=0.6)


@dataclass(frozen=True)
class SynthOptions:
    rules: BoxRules = field(default_factory=BoxRules)
    jpeg_quality: int = 95
    write_masks: bool = True
    contact_sheet_tiles: int = 16
    name_prefix: str = "synth_"


@dataclass
class SynthReport:
    images: int
    boxes: int
    boxes_per_class: dict[str, int]
    empty_images: int
    seconds: float
    images_per_minute: float
    dropped_poses: list[dict]
    #: "mask" (the mask head's class) or "labels" (voted by the real labels, fields.label_transfer)
    class_source: str = "mask"
    #: boxes whose class the label votes changed, and boxes no real label saw (mask class kept)
    relabelled_boxes: int = 0
    unvoted_boxes: int = 0

    def to_json(self) -> dict:
        return asdict(self)


def synthesize(renderer: ViewRenderer, camera: Camera, origin: Origin, poses: list[PoseEntry],
               out_dir: str | Path, class_names: list[str], options: SynthOptions | None = None,
               dropped: list[dict] | None = None,
               progress: Callable[[int, int], None] | None = None,
               labels_from: LabelledFrames | None = None, max_dt_us: int | None = None) -> SynthReport:
    """Render every pose, derive boxes from the masks, write the synthetic set to ``out_dir``.

    ``poses`` are poses-file entries (``cam_from_world`` set; ``t_unix_us`` sets the scene time of
    dynamic fields). Images are written as they are rendered, so an interrupted run keeps what it
    finished; ``poses.json`` and the report are written last. ``labels_from``: take each box's class
    from the real labels (module docstring); ``max_dt_us``: only real frames that close in time vote.
    """
    options = options or SynthOptions()
    if labels_from is not None and not hasattr(renderer, "render_view_depth"):
        raise TypeError(f"class votes from labels need depth; {type(renderer).__name__} has no render_view_depth")
    out = Path(out_dir)
    for sub in ("images", "labels") + (("masks",) if options.write_masks else ()):
        (out / sub).mkdir(parents=True, exist_ok=True)
    per_class = dict.fromkeys(class_names, 0)
    entries: list[PoseEntry] = []
    sheet: list[tuple[np.ndarray, list[MaskBox]]] = []
    n_boxes = empty = relabelled = unvoted = 0
    t0 = time.perf_counter()
    sheet_every = max(1, math.ceil(len(poses) / max(options.contact_sheet_tiles, 1)))
    for i, pose in enumerate(poses):
        if pose.cam_from_world is None:
            raise ValueError(f"pose {i} has no cam_from_world: only posed entries can be rendered")
        if labels_from is None:
            rgb, prob = renderer.render_view(camera, pose.cam_from_world, pose.t_unix_us)
        else:
            rgb, prob, depth = renderer.render_view_depth(camera, pose.cam_from_world, pose.t_unix_us)
        if rgb.shape[:2] != (camera.height, camera.width) or prob.shape[:2] != rgb.shape[:2]:
            raise ValueError(f"renderer returned {rgb.shape} / {prob.shape} for a "
                             f"{camera.width}x{camera.height} camera")
        boxes = boxes_from_probabilities(prob, options.rules)
        if labels_from is not None:
            mask_classes = [b.class_id for b in boxes]
            boxes, n_unvoted = labels_from.relabel(boxes, 1.0 - prob[..., 0], depth, camera, pose.cam_from_world,
                                                   pose.t_unix_us, max_dt_us, options.rules.threshold)
            relabelled += sum(b.class_id != c for b, c in zip(boxes, mask_classes, strict=True))
            unvoted += n_unvoted
        stem = f"{options.name_prefix}{i:05d}"
        cv2.imwrite(str(out / "images" / f"{stem}.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality])
        (out / "labels" / f"{stem}.txt").write_text(
            "".join(b.yolo(camera.width, camera.height) + "\n" for b in boxes))
        if options.write_masks:
            cv2.imwrite(str(out / "masks" / f"{stem}.png"), np.argmax(prob, axis=-1).astype(np.uint8))
        entries.append(PoseEntry(f"{stem}.jpg", pose.t_unix_us, pose.cam_from_world, "novel",
                                 extra=dict(pose.extra)))
        n_boxes += len(boxes)
        empty += not boxes
        for b in boxes:
            if 0 <= b.class_id < len(class_names):
                per_class[class_names[b.class_id]] += 1
        if i % sheet_every == 0:
            sheet.append((rgb, boxes))
        if progress:
            progress(i + 1, len(poses))
    seconds = time.perf_counter() - t0
    PosesFile(origin, camera, entries).save(out / "poses.json")
    if sheet:
        cv2.imwrite(str(out / "contact_sheet.png"),
                    cv2.cvtColor(contact_sheet(sheet, class_names), cv2.COLOR_RGB2BGR))
    report = SynthReport(len(poses), n_boxes, per_class, empty, seconds,
                         60.0 * len(poses) / seconds if seconds > 0 else 0.0, dropped or [],
                         "mask" if labels_from is None else "labels", relabelled, unvoted)
    (out / "report.json").write_text(json.dumps(report.to_json(), indent=1) + "\n")
    return report


def contact_sheet(items: list[tuple[np.ndarray, list]], class_names: list[str], columns: int = 4,
                  tile_width: int = 320) -> np.ndarray:
    """Thumbnails with boxes drawn, in a grid (RGB uint8)."""
    from sim.draw import draw_boxes

    tiles = []
    for rgb, boxes in items:
        drawn = draw_boxes(rgb, boxes, class_names)
        scale = tile_width / rgb.shape[1]
        tiles.append(cv2.resize(drawn, (tile_width, max(1, round(rgb.shape[0] * scale))),
                                interpolation=cv2.INTER_AREA))
    h = max(t.shape[0] for t in tiles)
    rows = []
    for r in range(0, len(tiles), columns):
        row = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles[r:r + columns]]
        row += [np.zeros((h, tile_width, 3), np.uint8)] * (columns - len(row))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


@dataclass
class BoxMatch:
    """Detection-style agreement of boxes with ground truth (greedy by IoU)."""

    true_positives: int
    false_positives: int
    false_negatives: int
    ious: list[float]

    @property
    def recall(self) -> float:
        n = self.true_positives + self.false_negatives
        return self.true_positives / n if n else 1.0

    @property
    def precision(self) -> float:
        n = self.true_positives + self.false_positives
        return self.true_positives / n if n else 1.0

    @property
    def mean_iou(self) -> float:
        return float(np.mean(self.ious)) if self.ious else float("nan")

    def __add__(self, other: BoxMatch) -> BoxMatch:
        return BoxMatch(self.true_positives + other.true_positives,
                        self.false_positives + other.false_positives,
                        self.false_negatives + other.false_negatives, self.ious + other.ious)


def match_boxes(pred: list, truth: list, iou_threshold: float = 0.5, min_truth_height_px: float = 0.0,
                same_class: bool = True) -> BoxMatch:
    """Greedy one-to-one matching of predicted to true boxes (objects with class_id, x0..y1).

    Truth boxes shorter than ``min_truth_height_px`` are ignored (neither missed nor matched, and
    predictions matching them are not counted as false positives), as detectors are scored.
    """
    small = [t for t in truth if (t.y1 - t.y0) < min_truth_height_px]
    big = [t for t in truth if (t.y1 - t.y0) >= min_truth_height_px]
    pairs = []
    for i, p in enumerate(pred):
        for j, t in enumerate(big):
            if same_class and p.class_id != t.class_id:
                continue
            iou = box_iou(p, t)
            if iou >= iou_threshold:
                pairs.append((iou, i, j))
    used_p, used_t, ious = set(), set(), []
    for iou, i, j in sorted(pairs, reverse=True):
        if i not in used_p and j not in used_t:
            used_p.add(i)
            used_t.add(j)
            ious.append(iou)
    fp = 0
    for i, p in enumerate(pred):
        if i in used_p:
            continue
        if any(box_iou(p, t) >= iou_threshold for t in small):
            continue
        fp += 1
    return BoxMatch(len(used_p), fp, len(big) - len(used_t), ious)
