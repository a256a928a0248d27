"""Labelled training sets rendered by the simulator: low-altitude orbits around several worlds.

A detector needs a starting point. The paper fine-tunes a COCO-pretrained YOLOv8n; nothing may be
downloaded here, so the stand-in is a base detector trained on simulator renders at the training
altitude (15 m) over worlds *other* than the one being flown (different seeds: terrain, textures,
clothing and people placement all differ). This module renders such a set.

Views: camera at ``altitude_m`` above the ground (z = 0, ENU metres, scene centre at the origin), orbit
radius uniform in ``radius_m``, pitch = look-at pitch ± ``pitch_jitter_deg`` (clipped to [-90°, -20°]),
azimuth uniform, aim point jittered ±6 m. Images are PNG, labels YOLO txt; file stems
``s{seed}_{k:05d}``. Rendering is resumable: a view whose label file exists is skipped, and the view
parameters are drawn for every view either way, so a resumed set is identical to an uninterrupted one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OrbitSetSpec:
    """Where views are taken from (metres, degrees) and how they are rendered (pixels)."""

    altitude_m: float = 15.0
    radius_m: tuple[float, float] = (6.0, 22.0)
    pitch_jitter_deg: float = 10.0
    aim_jitter_m: float = 6.0
    width: int = 320
    height: int = 240
    hfov_deg: float = 70.0
    supersample: int = 2


def render_orbit_split(root: str | Path, seeds, n_images: int, rng_seed: int,
                       spec: OrbitSetSpec = OrbitSetSpec(), progress=None, world_overrides: dict | None = None) -> int:
    """Render ``n_images`` views spread evenly over the worlds ``seeds`` into root/images, root/labels.

    Returns the number of views rendered now (the others existed). ``progress(done, total)`` is called
    after each world. ``world_overrides`` go to :func:`sim.world.make_world` (e.g. a small texture in tests).
    """
    import cv2

    from sim.world import make_world
    from telemetry.camera import Camera, Mount
    from telemetry.frames import orbit_pose

    seeds = tuple(int(s) for s in seeds)
    if not seeds or n_images < 1:
        raise ValueError(f"need at least one world seed and one image (got {len(seeds)} seeds, {n_images} images)")
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "labels").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(rng_seed)
    per_world = int(np.ceil(n_images / len(seeds)))
    k = rendered = 0
    for seed in seeds:
        world = None
        for _ in range(per_world):
            if k >= n_images:
                break
            name = f"s{seed}_{k:05d}"
            k += 1
            radius = rng.uniform(*spec.radius_m)
            pitch = -np.degrees(np.arctan2(spec.altitude_m, radius)) + rng.uniform(-spec.pitch_jitter_deg,
                                                                                 spec.pitch_jitter_deg)
            pitch = float(np.clip(pitch, -90.0, -20.0))
            azimuth = rng.uniform(0, 360)
            centre = (rng.uniform(-spec.aim_jitter_m, spec.aim_jitter_m),
                      rng.uniform(-spec.aim_jitter_m, spec.aim_jitter_m), 0.0)
            if (root / "labels" / f"{name}.txt").exists():
                continue
            if world is None:
                world = make_world(seed=seed, **(world_overrides or {}))
            camera = Camera.from_fov(spec.width, spec.height, spec.hfov_deg, Mount(pitch_deg=pitch))
            T = orbit_pose(spec.altitude_m, radius, pitch, azimuth, centre)
            res = world.render(camera, T, supersample=spec.supersample)
            # image first, label last: a label file marks a finished view
            cv2.imwrite(str(root / "images" / f"{name}.png"), cv2.cvtColor(res.rgb, cv2.COLOR_RGB2BGR))
            (root / "labels" / f"{name}.txt").write_text(res.yolo_labels())
            rendered += 1
        log.info("%s: world %d done (%d/%d)", root.name, seed, k, n_images)
        if progress:
            progress(k, n_images)
    return rendered


def write_data_yaml(root: str | Path, class_names) -> Path:
    """``root/data.yaml`` for ``root/train`` and ``root/val`` (YOLO layout)."""
    root = Path(root)
    names = "\n".join(f"  {i}: {n}" for i, n in enumerate(class_names))
    yaml = root / "data.yaml"
    yaml.write_text(f"path: {root.resolve()}\ntrain: train/images\nval: val/images\nnames:\n{names}\n")
    return yaml
