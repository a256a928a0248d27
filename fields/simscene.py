"""A recorded-flight directory rendered straight from the simulator, for tests and benchmarks.

Writes exactly the DESIGN.md §3 layout — ``frames/*.png``, ``frames.csv``, ``camera.json``,
``labels/*.txt`` (YOLO, from the simulator's boxes), ``classes.txt`` — plus
``derived/poses.json`` holding the *true* poses (source ``"telemetry"``). It does not go through
the MAVLink logger (``uavsim sim-flight`` does); it exists so the fields can be fitted and scored
against simulator truth without waiting for telemetry and SfM.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from telemetry.camera import Camera
from telemetry.frames import orbit_pose
from telemetry.posesfile import Origin, PoseEntry, PosesFile

T0_US = 1_700_000_000_000_000


@dataclass
class OrbitSpec:
    """An orbit around the scene centre (metres, degrees). Frames are spread evenly in azimuth."""

    altitude_m: float = 15.0
    radius_m: float = 20.0
    pitch_deg: float = -45.0
    frames: int = 60
    azimuth0_deg: float = 0.0
    #: frame interval on the companion clock, µs
    dt_us: int = 200_000

    def poses(self) -> list[np.ndarray]:
        return [orbit_pose(self.altitude_m, self.radius_m, self.pitch_deg,
                           self.azimuth0_deg + 360.0 * i / self.frames) for i in range(self.frames)]


def write_orbit_flight(out: str | Path, world, camera: Camera, orbit: OrbitSpec,
                       supersample: int = 2) -> PosesFile:
    """Render ``orbit`` with ``world`` into a recorded-flight folder ``out``; returns the poses file."""
    import cv2

    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(exist_ok=True)
    camera.save(out / "camera.json")
    (out / "classes.txt").write_text("".join(n + "\n" for n in world.class_names))
    entries, rows = [], ["frame,t_unix_us"]
    for i, T in enumerate(orbit.poses()):
        name = f"{i:06d}.png"
        res = world.render(camera, T, supersample=supersample)
        cv2.imwrite(str(out / "frames" / name), cv2.cvtColor(res.rgb, cv2.COLOR_RGB2BGR))
        (out / "labels" / f"{i:06d}.txt").write_text(res.yolo_labels())
        t = T0_US + i * orbit.dt_us
        rows.append(f"{name},{t}")
        entries.append(PoseEntry(name, t, T, "telemetry"))
    (out / "frames.csv").write_text("\n".join(rows) + "\n")
    poses = PosesFile(Origin(0.0, 0.0, 0.0), camera, entries)
    poses.save(out / "derived" / "poses.json")
    return poses


def novel_poses_file(camera: Camera, poses: list[np.ndarray]) -> PosesFile:
    """A poses file of novel poses (``frame`` null, source ``"novel"``), input of ``uavsim render``."""
    return PosesFile(Origin(0.0, 0.0, 0.0), camera, [PoseEntry(None, None, T, "novel") for T in poses])
