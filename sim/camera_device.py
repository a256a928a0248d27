"""A simulated camera: renders the sim world on its own clock at a frame rate, at the TRUE pose.

The camera free-runs: frame k is exposed at ``first_us + k * period`` where the period carries the
camera oscillator's error (``clock_drift_ppm``) and ``first_us`` an arbitrary phase, so frame times
never line up with telemetry samples. The capture time it reports is on the companion clock (as a
V4L2 kernel timestamp is), in unix µs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CameraDeviceConfig:
    fps: float = 2.0
    #: delay of the first exposure after the start (µs), an arbitrary phase against the telemetry
    phase_us: int = 37_345
    #: camera oscillator error (ppm): the actual frame period is (1 + drift) / fps
    clock_drift_ppm: float = -40.0
    supersample: int = 2


class SimCamera:
    """Frame schedule + rendering. ``world``: :class:`sim.world.World`; ``camera``: intrinsics."""

    def __init__(self, world, camera, config: CameraDeviceConfig, start_unix_us: int) -> None:
        if not config.fps > 0:
            raise ValueError(f"camera fps must be > 0, got {config.fps}")
        self.world = world
        self.camera = camera
        self.config = config
        self.first_us = int(start_unix_us) + int(config.phase_us)
        self.period_us = 1e6 / config.fps * (1.0 + config.clock_drift_ppm * 1e-6)
        self.k = 0

    def next_capture_us(self) -> int:
        return self.first_us + int(round(self.k * self.period_us))

    def scene_time_s(self, t_unix_us: int) -> float:
        """Scene time of the simulator: seconds since the first frame (DESIGN: null t → first frame)."""
        return (t_unix_us - self.first_us) / 1e6

    def capture(self, cam_from_world: np.ndarray):
        """Render the due frame at the true ``cam_from_world``; (t_unix_us, RenderResult). Advances."""
        t = self.next_capture_us()
        res = self.world.render(self.camera, cam_from_world, t=self.scene_time_s(t),
                                supersample=self.config.supersample)
        self.k += 1
        return t, res
