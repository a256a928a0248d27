"""An Okutama-like dynamic flight rendered straight from the simulator (tests and ``bench/dynamic.py``).

The paper's dynamic experiment uses an Okutama-Action clip: a drone on a smooth, slightly irregular
straight path over people who walk, ~300 frames, every other frame for training and the rest for
validation, poses from SfM. Here: the simulator world with walking people (``make_world(dynamic=True)``),
a camera on a straight line at ``altitude_m`` with slow lateral / vertical / heading wobble (sums of
a few random low-frequency sines: smooth but not perfectly straight), looking forward and down at
``pitch_deg``. Each frame is rendered at its own scene time (``i * dt_s``), so people move between
frames.

Poses: ``derived/poses.json`` holds *noisy* poses (source ``"telemetry"``), the true ones go to
``OUT.truth.json`` beside the flight. The noise is injected, not estimated: a consumer GNSS + IMU
(Gauss–Markov drift as :meth:`sim.autopilot.NoiseConfig.realistic`: 0.5 m horizontal, 0.8 m
vertical, tau 30 s; attitude 0.3 deg, tau 5 s) plus white per-frame jitter (``jitter_m``,
``jitter_deg``: frame-time interpolation and SfM residual). Layout = DESIGN.md §3 (frames/,
frames.csv, camera.json, labels/, classes.txt).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from telemetry.camera import Camera
from telemetry.frames import look_at
from telemetry.posesfile import Origin, PoseEntry, PosesFile

T0_US = 1_700_000_000_000_000


@dataclass
class LineSpec:
    """A slightly irregular straight pass (metres, degrees, seconds) over the scene centre."""

    altitude_m: float = 15.0
    #: ground distance covered by the point the camera looks at, centred on the scene
    length_m: float = 30.0
    pitch_deg: float = -60.0
    frames: int = 80
    #: scene seconds between frames
    dt_s: float = 0.2
    #: wobble amplitudes: lateral and vertical metres, heading degrees
    lateral_m: float = 1.5
    vertical_m: float = 0.5
    heading_deg: float = 3.0
    seed: int = 0

    def true_poses(self) -> list[np.ndarray]:
        """OpenCV ``cam_from_world`` per frame (world ENU), flying along +x (east)."""
        rng = np.random.default_rng(self.seed)
        n = max(int(self.frames), 1)
        s = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
        wob = []
        for _ in range(3):  # lateral, vertical, heading: 2 sines each, 0.5-2 cycles over the pass
            f = rng.uniform(0.5, 2.0, 2)
            ph = rng.uniform(0, 2 * np.pi, 2)
            a = rng.uniform(0.5, 1.0, 2)
            w = (a[:, None] * np.sin(2 * np.pi * f[:, None] * s[None] + ph[:, None])).sum(0)
            wob.append(w / max(a.sum(), 1e-9))
        lead = self.altitude_m / math.tan(math.radians(max(abs(self.pitch_deg), 1.0)))
        out = []
        for k in range(n):
            x = -self.length_m / 2 + self.length_m * s[k] - lead
            eye = np.array([x, self.lateral_m * wob[0][k], self.altitude_m + self.vertical_m * wob[1][k]])
            yaw = math.radians(self.heading_deg * wob[2][k])
            target = eye + np.array([lead * math.cos(yaw), lead * math.sin(yaw), -self.altitude_m])
            out.append(look_at(eye, target))
        return out


@dataclass
class PoseNoise:
    """Injected pose errors (see the module docstring). All zero = true poses."""

    gps_sigma_m: float = 0.5
    gps_vertical_sigma_m: float = 0.8
    gps_tau_s: float = 30.0
    attitude_sigma_deg: float = 0.3
    attitude_tau_s: float = 5.0
    jitter_m: float = 0.05
    jitter_deg: float = 0.15
    seed: int = 1


def noisy_poses(poses: list[np.ndarray], times_s: list[float], noise: PoseNoise) -> list[np.ndarray]:
    """``poses`` (cam_from_world) with camera-centre and attitude errors added at ``times_s``."""
    from scipy.spatial.transform import Rotation

    from sim.autopilot import GaussMarkov

    rng = np.random.default_rng(noise.seed)
    gps = GaussMarkov([noise.gps_sigma_m, noise.gps_sigma_m, noise.gps_vertical_sigma_m], noise.gps_tau_s, rng)
    att = GaussMarkov(math.radians(noise.attitude_sigma_deg), noise.attitude_tau_s, rng)
    out: list[np.ndarray | None] = [None] * len(poses)
    for i in np.argsort(np.asarray(times_s, dtype=np.float64), kind="stable"):  # noise processes run forward
        T, t = poses[i], float(times_s[i])
        R_wc = T[:3, :3].T
        c = -R_wc @ T[:3, 3]
        c = c + gps.at(t) + noise.jitter_m * rng.standard_normal(3)
        rot = att.at(t) + math.radians(noise.jitter_deg) * rng.standard_normal(3)
        R_wc = Rotation.from_rotvec(rot).as_matrix() @ R_wc
        Tn = np.eye(4)
        Tn[:3, :3] = R_wc.T
        Tn[:3, 3] = -R_wc.T @ c
        out[i] = Tn
    return out


def write_line_flight(out: str | Path, world, camera: Camera, spec: LineSpec, noise: PoseNoise | None = None,
                      supersample: int = 2) -> PosesFile:
    """Render ``spec`` (people move with scene time) into a recorded-flight folder ``out``; returns
    the poses file written to ``derived/poses.json`` (noisy when ``noise`` is given)."""
    import cv2

    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(exist_ok=True)
    camera.save(out / "camera.json")
    (out / "classes.txt").write_text("".join(n + "\n" for n in world.class_names))
    truth = spec.true_poses()
    times = [i * spec.dt_s for i in range(len(truth))]
    posed = noisy_poses(truth, times, noise) if noise else truth
    entries, rows, truth_rows = [], ["frame,t_unix_us"], []
    for i, (T, Tn, t) in enumerate(zip(truth, posed, times, strict=True)):
        name = f"{i:06d}.png"
        res = world.render(camera, T, t=t, supersample=supersample)
        cv2.imwrite(str(out / "frames" / name), cv2.cvtColor(res.rgb, cv2.COLOR_RGB2BGR))
        (out / "labels" / f"{i:06d}.txt").write_text(res.yolo_labels())
        t_us = T0_US + int(round(t * 1e6))
        rows.append(f"{name},{t_us}")
        entries.append(PoseEntry(name, t_us, Tn, "telemetry"))
        truth_rows.append({"frame": name, "t_unix_us": t_us, "t_scene_s": t, "cam_from_world": T.tolist()})
    (out / "frames.csv").write_text("\n".join(rows) + "\n")
    poses = PosesFile(Origin(0.0, 0.0, 0.0), camera, entries)
    poses.save(out / "derived" / "poses.json")
    out.with_name(out.name + ".truth.json").write_text(json.dumps(
        {"kind": "uavsim-dynamic-line-truth", "spec": asdict(spec), "noise": asdict(noise) if noise else None,
         "scene_t0_unix_us": T0_US, "frames": truth_rows}, indent=1) + "\n")
    return poses
