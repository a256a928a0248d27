"""Classes of synthetic boxes from the real frames' labels, by geometry (label transfer).

The mask head says *where* an object of interest is; which class it is can come from the real
labels instead. A box found in a rendered view is lifted to 3D (the rendered depth at its
foreground pixels), those points are projected into every labelled real frame, and each real label
box that contains a projected point votes for its class. The class with the most votes wins.

Why: under a short fit the class channels of the mask head lag its foreground channel. They then
follow the classes' share of labelled pixels rather than the person. On the quick demo (322 steps)
every held-out person came out "prone", the class with the largest label boxes; label transfer
gave 35 of 35 matched people their true class (bench/RESULTS.md, session 5).

Votes: a projected point inside ``n`` label boxes of one frame gives each ``1 / n`` (an oblique
frame can put a person behind another's box; the other frames outvote that). Frames where the point
falls in no box give nothing, so a person a frame does not label cannot vote it to background. A
box without votes (it lies where no real frame has a label) keeps the mask head's class.
For a dynamic scene only frames within ``max_dt_us`` of the view's time vote (people move).

Frames: ``cam_from_world`` OpenCV world-to-camera 4x4, world ENU metres; pixel boxes are pixel
edges (x0, y0 inclusive, x1, y1 exclusive); depth is metres along the unit ray.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fields.mask_boxes import MaskBox
from telemetry.camera import Camera

#: foreground pixels of a box lifted to 3D (evenly spaced when a box has more)
MAX_POINTS_PER_BOX = 64


@dataclass
class LabelledFrames:
    """The real labelled frames as class voters.

    ``boxes[k]``: (B, 5) float array of frame k's labels, rows ``class, x0, y0, x1, y1`` (pixels of
    ``camera``); ``times_us[k]``: capture time (unix µs) or None when unknown.
    """

    camera: Camera
    cam_from_world: list[np.ndarray]
    boxes: list[np.ndarray]
    n_classes: int
    times_us: list[int | None] | None = None

    def __post_init__(self) -> None:
        if len(self.cam_from_world) != len(self.boxes):
            raise ValueError(f"{len(self.cam_from_world)} poses but {len(self.boxes)} label lists")
        self.boxes = [np.asarray(b, np.float64).reshape(-1, 5) for b in self.boxes]
        self._R = np.stack([np.asarray(T, np.float64)[:3, :3] for T in self.cam_from_world]) if self.boxes else None
        self._t = np.stack([np.asarray(T, np.float64)[:3, 3] for T in self.cam_from_world]) if self.boxes else None

    @classmethod
    def from_flight(cls, flight: str | Path, poses_path: str | Path | None = None) -> LabelledFrames:
        """The posed frames of ``flight`` that have a label file (``labels/STEM.txt``, YOLO)."""
        from fields.data import parse_labels, read_classes
        from telemetry.posesfile import PosesFile

        flight = Path(flight)
        poses = PosesFile.load(poses_path or flight / "derived" / "poses.json")
        cam, n_classes = poses.camera, len(read_classes(flight))
        Ts, boxes, times = [], [], []
        for e in poses.posed():
            label = flight / "labels" / (Path(e.frame).stem + ".txt") if e.frame else None
            if label is None or not label.is_file():
                continue
            rows = parse_labels(label.read_text(), cam.width, cam.height, n_classes)
            Ts.append(np.asarray(e.cam_from_world, np.float64))
            boxes.append(np.array(rows, np.float64).reshape(-1, 5))
            times.append(e.t_unix_us)
        return cls(cam, Ts, boxes, n_classes, times)

    @classmethod
    def from_flight_data(cls, data, frames: list[int] | None = None) -> LabelledFrames:
        """From a loaded :class:`fields.data.FlightData` (``frames``: indices to use, default all labelled)."""
        idx = [i for i in (frames if frames is not None else range(data.n)) if bool(data.has_mask[i])]
        return cls(data.camera, [data.cam_from_world[i] for i in idx],
                   [np.array(data.boxes[i], np.float64).reshape(-1, 5) for i in idx], len(data.classes))

    def class_votes(self, points_world: np.ndarray, t_unix_us: int | None = None,
                    max_dt_us: int | None = None) -> np.ndarray:
        """Votes (n_classes,) of the labelled frames for world points (N, 3), ENU m; see the module rules."""
        votes = np.zeros(self.n_classes)
        p = np.asarray(points_world, np.float64).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1)]
        if len(p) == 0 or self._R is None:
            return votes
        for k in self._frames_near(t_unix_us, max_dt_us):
            b = self.boxes[k]
            if len(b) == 0:
                continue
            uv, front = self.camera.project(p @ self._R[k].T + self._t[k])
            uv = uv[front]
            if len(uv) == 0:
                continue
            u, v = uv[:, :1], uv[:, 1:]
            inside = (u >= b[:, 1]) & (u < b[:, 3]) & (v >= b[:, 2]) & (v < b[:, 4])  # (N, B)
            n_in = inside.sum(axis=1, keepdims=True)
            share = np.where(inside, 1.0 / np.maximum(n_in, 1), 0.0).sum(axis=0)  # per label box
            np.add.at(votes, b[:, 0].astype(int), share)
        return votes

    def _frames_near(self, t_unix_us: int | None, max_dt_us: int | None) -> list[int]:
        if max_dt_us is None or t_unix_us is None or self.times_us is None:
            return list(range(len(self.boxes)))
        return [k for k, t in enumerate(self.times_us) if t is not None and abs(t - t_unix_us) <= max_dt_us]

    def relabel(self, boxes: list[MaskBox], foreground: np.ndarray, depth: np.ndarray, camera: Camera,
                cam_from_world: np.ndarray, t_unix_us: int | None = None, max_dt_us: int | None = None,
                threshold: float = 0.5) -> tuple[list[MaskBox], int]:
        """Boxes of a rendered view with their class from the votes, and how many had no votes.

        ``foreground`` (H, W): 1 - background probability; ``depth`` (H, W): metres along each pixel's
        unit ray from ``cam_from_world``'s centre. Pixels of a box with foreground >= ``threshold``
        (at least its strongest one) are lifted to 3D.
        """
        out, unvoted = [], 0
        for box in boxes:
            fg = foreground[box.y0:box.y1, box.x0:box.x1]
            ys, xs = np.nonzero(fg >= min(threshold, float(fg.max())))
            if len(ys) > MAX_POINTS_PER_BOX:
                keep = np.linspace(0, len(ys) - 1, MAX_POINTS_PER_BOX).round().astype(int)
                ys, xs = ys[keep], xs[keep]
            ys, xs = ys + box.y0, xs + box.x0
            # rays through those pixels' centres only (pixel centres at +0.5, as camera.pixel_grid)
            origin, dirs = camera.rays_world(cam_from_world, np.stack([xs + 0.5, ys + 0.5], axis=-1))
            points = origin + dirs * depth[ys, xs, None]
            votes = self.class_votes(points, t_unix_us, max_dt_us)
            if votes.sum() <= 0.0:
                unvoted += 1
                out.append(box)
            else:
                out.append(replace(box, class_id=int(np.argmax(votes))))
        return out, unvoted
