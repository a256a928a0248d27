"""The foreground threshold of a fitted field's masks, calibrated on its own held-out frames.

How sharp a field's mask is depends on how long it trained, and so does the foreground cut that turns
its blobs into the best boxes: a ~1,000-step field's best cut at 35-50 m is ~0.6, a ~3,400-step
field's ~0.8 (bench/RESULTS.md, synthesis session 7). The flight itself says which: its held-out
frames have label boxes the field never saw. :func:`calibrate_threshold` scores a grid of thresholds
on the masks rendered there (the ``evaluate_frames`` box IoU: each label box's best blob, 0 when
none) and keeps the best; the novel high-altitude views then take that plus
:data:`HIGH_ALTITUDE_OFFSET`. The offset is measured, not derived: on four bench fields (975-3,403
steps) the best cut on tuning views at 35/50 m lay 0.1-0.2 above the held-out 15 m best
(bench/RESULTS.md, synthesis session 8). A plausible reason, not tested: at altitude a person is
2-3x fewer pixels across, so the soft rim the field leaves around it weighs more in the box.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fields.evaluation import match_boxes
from fields.mask_boxes import BoxRules, MaskBox, boxes_from_probabilities

#: thresholds tried on the held-out masks
THRESHOLDS: tuple[float, ...] = tuple(round(0.4 + 0.05 * k, 2) for k in range(11))  # 0.40 ... 0.90
#: added to the held-out best for the 35-50 m novel views (see the module docstring)
HIGH_ALTITUDE_OFFSET = 0.1
#: the cut never goes above this (a higher one loses faint people outright)
MAX_THRESHOLD = 0.9


def calibrate_threshold(probs: dict[int, np.ndarray], truth: dict[int, list[MaskBox]], min_box_px: float = 6.0,
                        rules: BoxRules | None = None) -> dict | None:
    """Best foreground threshold on held-out masks.

    ``probs``: frame index -> rendered class probabilities (H, W, K), channel 0 background; ``truth``:
    frame index -> the frame's label boxes (pixel edges). Boxes smaller than ``min_box_px`` on their
    shorter side are not scored. ``rules``: the other box rules (default :class:`BoxRules`); only the
    threshold varies. Returns None when no scored box exists (nothing to calibrate on), else
    ``{"heldout_best", "synth_threshold", "box_iou": {threshold: mean IoU}, "frames", "boxes"}``.
    Ties go to the lower threshold.
    """
    rules = rules or BoxRules()
    scored = {i: [b for b in truth.get(i, []) if min(b.width, b.height) >= min_box_px] for i in probs}
    n_boxes = sum(len(v) for v in scored.values())
    if n_boxes == 0:
        return None
    masks = {i: np.asarray(prob, np.float32) for i, prob in probs.items() if scored[i]}  # once, not per cut
    table = {}
    for t in THRESHOLDS:
        r = dataclasses.replace(rules, threshold=t)
        ious = []
        for i, prob in masks.items():
            ious += match_boxes(scored[i], boxes_from_probabilities(prob, r))
        table[t] = float(np.mean(ious))
    best = max(THRESHOLDS, key=lambda t: (round(table[t], 6), -t))
    return {"heldout_best": best, "synth_threshold": round(min(best + HIGH_ALTITUDE_OFFSET, MAX_THRESHOLD), 2),
            "box_iou": {f"{t:.2f}": round(v, 4) for t, v in table.items()},
            "frames": sum(1 for v in scored.values() if v), "boxes": n_boxes}
