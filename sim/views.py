"""The simulator as a view renderer for synthesis: RGB plus a one-hot class mask.

It has the interface of a fitted field's renderer (``render_view``), so the synthesis stage, its
box rules and its benchmarks can run against ground truth.
"""

from __future__ import annotations

import numpy as np

from sim.world import World
from telemetry.camera import Camera


class SimViewRenderer:
    """Renders ``world``; scene time = (t_unix_us - t0_unix_us) / 1e6 seconds (0 when None)."""

    def __init__(self, world: World, t0_unix_us: int = 0, supersample: int = 2):
        self.world = world
        self.t0_unix_us = int(t0_unix_us)
        self.supersample = supersample
        self.n_classes = len(world.class_names)

    def scene_time(self, t_unix_us: int | None) -> float:
        return 0.0 if t_unix_us is None else (int(t_unix_us) - self.t0_unix_us) / 1e6

    def render_full(self, camera: Camera, cam_from_world: np.ndarray, t_unix_us: int | None = None):
        return self.world.render(camera, cam_from_world, t=self.scene_time(t_unix_us),
                                 supersample=self.supersample)

    def render_view(self, camera: Camera, cam_from_world: np.ndarray, t_unix_us: int | None = None):
        result = self.render_full(camera, cam_from_world, t_unix_us)
        return result.rgb, one_hot_classes(result.instance_ids, result.classes, self.n_classes)


def one_hot_classes(instance_ids: np.ndarray, class_of: dict[int, int], n_classes: int) -> np.ndarray:
    """(H, W, n_classes + 1) float32: channel 0 background, channel c + 1 for class c."""
    lut = np.zeros(int(instance_ids.max(initial=0)) + 1, np.int64)
    for inst, c in class_of.items():
        if inst < len(lut):
            lut[inst] = c + 1
    labels = lut[instance_ids]
    return np.eye(n_classes + 1, dtype=np.float32)[labels]
