"""Simulated SfM inputs: orbit images rendered by the simulator and noisy telemetry priors.

Used by the SfM tests and ``bench/sfm.py``. Telemetry errors are first-order Gauss-Markov
processes (``x[k+1] = a x[k] + sqrt(1 - a^2) sigma w[k]``, ``a = exp(-dt / tau)``), stationary
with the given 1-sigma, because real GPS and AHRS errors drift slowly rather than jump per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from telemetry.camera import Camera
from telemetry.frames import camera_center, orbit_pose, pose_matrix, rot_x, rot_y, rot_z
from telemetry.sfm import Prior


def gauss_markov(n: int, dims: int, sigma: float, dt_s: float, tau_s: float,
                 rng: np.random.Generator) -> np.ndarray:
    """(n, dims) samples of a stationary first-order Gauss-Markov process with std ``sigma``."""
    a = math.exp(-dt_s / tau_s)
    x = np.empty((n, dims))
    x[0] = rng.normal(0.0, sigma, dims)
    for k in range(1, n):
        x[k] = a * x[k - 1] + math.sqrt(1.0 - a * a) * sigma * rng.normal(0.0, 1.0, dims)
    return x


@dataclass
class SimFlight:
    images: list[Path]
    camera: Camera
    truth: list[np.ndarray]
    """True OpenCV ``cam_from_world`` per frame (ENU)."""
    priors: list[Prior]


def perturb_pose(T: np.ndarray, dpos_enu: np.ndarray, drot_rad: np.ndarray) -> np.ndarray:
    """``T`` with its centre moved by ``dpos_enu`` and its world-frame attitude rotated (x,y,z small angles)."""
    R = T[:3, :3]
    c = camera_center(T) + dpos_enu
    dR = rot_z(drot_rad[2]) @ rot_y(drot_rad[1]) @ rot_x(drot_rad[0])
    R2 = R @ dR.T  # world frame rotated by dR: cam_from_world' = R dR^T
    return pose_matrix(R2, -R2 @ c)


def noisy_priors(names: list[str], truth: list[np.ndarray], t_unix_us: list[int], gps_sigma_m: float,
                 attitude_sigma_deg: float, seed: int, tau_s: float = 60.0,
                 with_attitude: bool = True) -> list[Prior]:
    """Telemetry priors from true poses with Gauss-Markov GPS (per axis) and attitude noise."""
    rng = np.random.default_rng(seed)
    n = len(truth)
    dt = (t_unix_us[1] - t_unix_us[0]) * 1e-6 if n > 1 else 1.0
    dpos = gauss_markov(n, 3, gps_sigma_m, dt, tau_s, rng) if gps_sigma_m > 0 else np.zeros((n, 3))
    drot = (gauss_markov(n, 3, math.radians(attitude_sigma_deg), dt, tau_s, rng)
            if attitude_sigma_deg > 0 else np.zeros((n, 3)))
    priors = []
    for k, (name, T) in enumerate(zip(names, truth, strict=True)):
        Tn = perturb_pose(T, dpos[k], drot[k])
        priors.append(Prior(name, t_unix_us[k], camera_center(Tn), max(gps_sigma_m, 0.05),
                            Tn if with_attitude else None))
    return priors


def orbit_truth(n_frames: int, altitude_m: float = 15.0, radius_m: float = 20.0, arc_deg: float = 360.0,
                speed_m_s: float = 3.0) -> tuple[list[np.ndarray], list[int]]:
    """True ``cam_from_world`` poses of an orbit looking at the centre, and capture times (unix µs)."""
    pitch = -math.degrees(math.atan2(altitude_m, radius_m))
    step = arc_deg / n_frames
    dt_s = math.radians(step) * radius_m / speed_m_s
    t0 = 1_700_000_000_000_000
    truth = [orbit_pose(altitude_m, radius_m, pitch, k * step) for k in range(n_frames)]
    times = [t0 + int(round(k * dt_s * 1e6)) for k in range(n_frames)]
    return truth, times


def render_orbit(out_dir: Path, n_frames: int = 60, width: int = 640, height: int = 480,
                 altitude_m: float = 15.0, radius_m: float = 20.0, hfov_deg: float = 70.0,
                 world_seed: int = 0, supersample: int = 2, texture_size: int = 4096,
                 texel_m: float = 0.025, arc_deg: float = 360.0, speed_m_s: float = 3.0
                 ) -> tuple[list[Path], Camera, list[np.ndarray], list[int]]:
    """Render an orbit looking at the scene centre; returns images, camera, true poses, times (unix µs)."""
    import cv2

    from sim.world import make_world

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    world = make_world(seed=world_seed, texture_size=texture_size, texel_m=texel_m)
    camera = Camera.from_fov(width, height, hfov_deg)
    truth, times = orbit_truth(n_frames, altitude_m, radius_m, arc_deg, speed_m_s)
    images = []
    for k, T in enumerate(truth):
        rgb = world.render(camera, T, supersample=supersample).rgb
        path = out_dir / f"{k:06d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        images.append(path)
    return images, camera, truth, times
