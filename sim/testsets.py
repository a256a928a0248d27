"""Labelled evaluation sets rendered by the simulator at chosen altitudes (ground truth).

The paper's experiment trains at one altitude (15 m) and tests at others (35-50 m). With a real
flight those test images would be flown; in the simulated world they are rendered, with exact
labels, from orbits around the scene at each altitude: camera pitch drawn from a range, azimuth
spread evenly, a small random aim offset.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from export.paper_datasets import Sample, write_dataset
from sim.world import World
from telemetry.camera import Camera
from telemetry.frames import look_at

log = logging.getLogger(__name__)


def altitude_poses(altitude_m: float, n: int, seed: int, pitch_deg=(-90.0, -45.0),
                   aim_jitter_m: float = 6.0) -> list[np.ndarray]:
    """``n`` cam_from_world poses at ``altitude_m`` looking near the scene centre (ENU origin)."""
    rng = np.random.default_rng(seed)
    poses = []
    for k in range(n):
        pitch = rng.uniform(*pitch_deg)
        radius = altitude_m / np.tan(np.radians(-pitch)) if pitch > -89.9 else 0.0
        az = np.radians(360.0 * k / max(n, 1) + rng.uniform(0, 360.0 / max(n, 1)))
        r_aim, th = aim_jitter_m * np.sqrt(rng.random()), rng.uniform(0, 2 * np.pi)
        aim = np.array([r_aim * np.cos(th), r_aim * np.sin(th), 0.0])
        eye = aim + np.array([radius * np.cos(az), radius * np.sin(az), altitude_m])
        up = np.array([np.cos(az), np.sin(az), 0.0])  # only used at nadir
        poses.append(look_at(eye, aim, up_enu=up) if radius < 1e-6 else look_at(eye, aim))
    return poses


def render_altitude_set(world: World, camera: Camera, altitude_m: float, n: int, out_dir: str | Path,
                        seed: int = 0, supersample: int = 2, t: float = 0.0) -> Path:
    """Render ``n`` labelled views at ``altitude_m`` into a YOLO dataset (all in ``val``).

    Returns the ``data.yaml`` path. Images are written first under ``out_dir/_render`` and
    linked into the dataset layout.
    """
    staging = Path(out_dir) / "_render"
    (staging / "images").mkdir(parents=True, exist_ok=True)
    (staging / "labels").mkdir(parents=True, exist_ok=True)
    samples = []
    for k, T in enumerate(altitude_poses(altitude_m, n, seed)):
        stem = f"alt{int(round(altitude_m)):03d}_{k:04d}"
        result = world.render(camera, T, t=t, supersample=supersample)
        img, lab = staging / "images" / f"{stem}.jpg", staging / "labels" / f"{stem}.txt"
        cv2.imwrite(str(img), cv2.cvtColor(result.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        lab.write_text(result.yolo_labels())
        samples.append(Sample(img, lab))
    return write_dataset(Path(out_dir) / "set", [], samples, list(world.class_names))
