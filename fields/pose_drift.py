"""Time-smooth corrections of telemetry camera poses, learned jointly with a field (nerfstudio's camera
optimiser, made smooth in time).

Telemetry poses carry a slowly wandering GNSS/IMU error (Gauss–Markov drift, tau 5–30 s) on top of
small per-frame jitter. A field with one static scene (extended K-Planes' static planes, a static
field) cannot explain a background that slides with the drift; a field with time planes (stock
K-Planes) absorbs it into the time planes instead, and then renders the drift at held-out times.
:class:`PoseDrift` models only the slow part: ``K`` knots evenly spaced over the flight's normalised
time ``t01`` in [0, 1], each a world-frame rotation vector (rad, about the camera centre) and a
world-frame translation of the camera centre (ENU metres). A frame at time ``t01`` gets the linear
interpolation of its two neighbouring knots, so

- the correction is smooth in time and pools the rays of every frame near a knot (a per-frame
  correction would get a few rays per frame per step);
- held-out frames get a correction from the *training* frames around them in time, without ever
  seeing their own pixels — what a fair held-out evaluation needs.

Frames: the correction maps the telemetry camera-to-world pose to the field's world:
``R_world_cam' = exp(rot) @ R_world_cam``, ``centre' = centre + trans``. Zero knots = the telemetry poses.

Optional coarser knot levels (``coarse_knots``) add their own interpolated corrections to the fine
one's. They add no new shapes of correction (the fine knots alone can take any of them) but change
how the optimiser moves: a coarse knot pools the rays of every frame across its wider span, so the
slow part of the drift gets a gradient with less noise, and the fine knots are left the residual
(a hierarchical spline's preconditioning).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn


def knot_count(span_s: float, spacing_s: float) -> int:
    """Knots for a flight of ``span_s`` seconds at one per ``spacing_s`` (at least 2, both ends)."""
    if not (math.isfinite(span_s) and span_s >= 0):
        raise ValueError(f"flight span must be a finite non-negative number of seconds, got {span_s}")
    if not (math.isfinite(spacing_s) and spacing_s > 0):
        raise ValueError(f"knot spacing must be a positive number of seconds, got {spacing_s}")
    return max(2, int(math.ceil(span_s / spacing_s)) + 1)


def rotate(rotvec: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v`` (..., 3) by rotation vectors ``rotvec`` (..., 3) (axis x angle, rad):
    Rodrigues ``v + a (w x v) + b w x (w x v)`` with ``a = sin(t)/t``, ``b = (1 - cos t)/t^2``;
    finite value and gradient at ``w = 0`` (the knots start there)."""
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    safe = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(safe)) / safe2)
    wxv = torch.cross(rotvec.expand_as(v), v, dim=-1)
    return v + a * wxv + b * torch.cross(rotvec.expand_as(v), wxv, dim=-1)


class PoseDrift(nn.Module):
    """``rot`` (K, 3): per knot a world-frame rotation vector (rad); ``trans`` (K, 3): a camera-centre
    translation (ENU m); ``coarse_rot`` / ``coarse_trans``: the same for each coarser level (K_l, 3).
    All start at zero (the telemetry poses); a frame's correction is the sum over the levels."""

    def __init__(self, knots: int, coarse_knots: Sequence[int] = ()):
        super().__init__()
        for k in (knots, *coarse_knots):
            if int(k) != k or k < 2:
                raise ValueError(f"every pose-drift level needs a whole number of at least 2 knots, got {k}")
        self.rot = nn.Parameter(torch.zeros(knots, 3))
        self.trans = nn.Parameter(torch.zeros(knots, 3))
        self.coarse_rot = nn.ParameterList([nn.Parameter(torch.zeros(int(k), 3)) for k in coarse_knots])
        self.coarse_trans = nn.ParameterList([nn.Parameter(torch.zeros(int(k), 3)) for k in coarse_knots])

    @property
    def knots(self) -> int:
        """Knots of the finest level."""
        return self.rot.shape[0]

    @property
    def coarse_knots(self) -> list[int]:
        return [int(r.shape[0]) for r in self.coarse_rot]

    def at(self, t01: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation vectors (R, 3) and translations (R, 3) at times ``t01`` (R,), clamped to [0, 1]:
        the sum of every level's linear interpolation between its two neighbouring knots."""
        rot, trans = _interpolate(self.rot, t01), _interpolate(self.trans, t01)
        for r, t in zip(self.coarse_rot, self.coarse_trans, strict=True):
            rot, trans = rot + _interpolate(r, t01), trans + _interpolate(t, t01)
        return rot, trans

    def apply(self, origins: torch.Tensor, dirs: torch.Tensor, t01: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected rays: origins (camera centres, (R, 3) m) shifted, unit directions (R, 3)
        rotated about the centre; both world ENU. Gradients reach the knots."""
        rot, trans = self.at(t01)
        return origins + trans, rotate(rot, dirs)

    @torch.no_grad()
    def correct_cam_from_world(self, cam_from_world: np.ndarray, t01: float) -> np.ndarray:
        """The corrected OpenCV ``cam_from_world`` (4x4) of a telemetry pose taken at ``t01``."""
        T = np.asarray(cam_from_world, dtype=np.float64)
        dev = self.rot.device
        rot, trans = self.at(torch.tensor([float(t01)], device=dev))
        R_wc = T[:3, :3].T
        centre = -R_wc @ T[:3, 3]
        cols = torch.from_numpy(R_wc.T.copy()).float().to(dev)  # rows = the camera axes in the world
        R_new = rotate(rot.expand(3, 3), cols).double().cpu().numpy().T  # columns rotated
        c_new = centre + trans[0].double().cpu().numpy()
        out = np.eye(4)
        out[:3, :3] = R_new.T
        out[:3, 3] = -R_new.T @ c_new
        return out

    def _at_knots(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The summed correction at the finest level's knot times, (K, 3) each."""
        if not len(self.coarse_rot):
            return self.rot, self.trans
        return self.at(torch.linspace(0.0, 1.0, self.knots, device=self.rot.device))

    def penalty(self, rot_scale_m: float = 30.0) -> torch.Tensor:
        """Mean squared correction in metres at the finest knots' times: translation, and rotation as
        the shift it causes at ``rot_scale_m`` range (keeps the gauge — a shift of field and all
        poses together — anchored to the telemetry)."""
        rot, trans = self._at_knots()
        return trans.square().sum(-1).mean() + (rot_scale_m ** 2) * rot.square().sum(-1).mean()

    def summary(self) -> dict:
        """Size of the learned corrections at the finest knots' times: RMS / max translation (m) and
        rotation (deg); the knot count of each level."""
        with torch.no_grad():
            rot, trans = self._at_knots()
            t = trans.norm(dim=-1)
            r = torch.rad2deg(rot.norm(dim=-1))
        return {"knots": self.knots, "coarse_knots": self.coarse_knots,
                "trans_rms_m": float(t.square().mean().sqrt()), "trans_max_m": float(t.max()),
                "rot_rms_deg": float(r.square().mean().sqrt()), "rot_max_deg": float(r.max())}


def _interpolate(knots: torch.Tensor, t01: torch.Tensor) -> torch.Tensor:
    """Values (R, C) at times ``t01`` (R,) (clamped to [0, 1]) of knots (K, C) evenly spaced over [0, 1]."""
    n = knots.shape[0]
    x = t01.clamp(0.0, 1.0) * (n - 1)
    i0 = x.floor().long().clamp(max=n - 2)
    w = (x - i0.to(x.dtype))[:, None]
    return knots[i0] * (1 - w) + knots[i0 + 1] * w


def warmup_scale(progress: float, delay: float) -> float:
    """Step-size factor of the pose knots at ``progress`` (share of training, 0..1): 0 while
    ``progress < delay``, then a linear ramp to 1 at ``2 * delay``; ``delay <= 0``: always 1.

    Adam moves every parameter by about its step size whatever the gradient's size, so knots that learn
    from the first steps' random field walk decimetres before the field shows a world to line the
    frames up to, and the field then fits the walk."""
    if delay <= 0:
        return 1.0
    return float(min(max((progress - delay) / delay, 0.0), 1.0))
