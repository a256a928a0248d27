"""Drawing labelled boxes on images for quick looks and contact sheets (OpenCV, no fonts needed)."""

from __future__ import annotations

import cv2
import numpy as np

#: BGR-free RGB colours per class id (standing, kneeling, prone, then repeats).
CLASS_COLOURS = [(230, 40, 40), (250, 210, 0), (220, 0, 220), (0, 200, 255), (255, 130, 0)]


def draw_boxes(rgb: np.ndarray, boxes, class_names=None, thickness: int = 1) -> np.ndarray:
    """A copy of ``rgb`` (H,W,3 uint8) with boxes drawn.

    ``boxes``: iterables of (class_id, x0, y0, x1, y1) in pixels (edges) or objects with those
    attributes (``class_id``, ``x0`` ...). Class names are written above boxes when given and the
    box is large enough to read.
    """
    out = np.ascontiguousarray(rgb.copy())
    for b in boxes:
        if hasattr(b, "class_id"):
            c, x0, y0, x1, y1 = b.class_id, b.x0, b.y0, b.x1, b.y1
        else:
            c, x0, y0, x1, y1 = b
        colour = CLASS_COLOURS[int(c) % len(CLASS_COLOURS)]
        p0 = (int(np.floor(x0)) - 1, int(np.floor(y0)) - 1)
        p1 = (int(np.ceil(x1)), int(np.ceil(y1)))
        cv2.rectangle(out, p0, p1, colour, thickness)
        if class_names and (x1 - x0) >= 12:
            cv2.putText(out, str(class_names[int(c)]), (p0[0], max(p0[1] - 2, 8)),
                        cv2.FONT_HERSHEY_PLAIN, 0.8, colour, 1, cv2.LINE_AA)
    return out
