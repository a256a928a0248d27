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

Optional per-frame rows (``frame_t01``: the times of the frames that train) add one rotation vector
and one translation per such frame on top of the knots: the white per-frame jitter of telemetry (a
few cm, ~0.1 deg) that knots a second apart cannot follow. A row acts only through its part that the
finest knots cannot represent: the rows minus their least-squares fit by the finest level's
interpolation at the frames' times (:meth:`PoseDrift.frame_residual`). Without that, the rows of the
training frames soaked up the slow drift too (many free rows learn it as fast as the knots), and a
held-out frame, which has no row and gets the knots alone, lost what the knots did not learn: a
synthetic test doubled the held-out miss distance. Poses are matched to their row by time
(:meth:`PoseDrift.frame_row`); any other pose (a held-out frame, a novel view) gets the knots alone.
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


@torch.no_grad()
def corrected_cam_from_world(cam_from_world: np.ndarray, rotvec: torch.Tensor, trans: torch.Tensor) -> np.ndarray:
    """OpenCV ``cam_from_world`` (4x4) after a world-frame correction: the camera's axes rotated by
    ``rotvec`` (3,) (rad, about the camera centre) and its centre shifted by ``trans`` (3,) (ENU m), the
    same correction :meth:`PoseDrift.apply` makes to the camera's rays."""
    T = np.asarray(cam_from_world, dtype=np.float64)
    R_wc = T[:3, :3].T
    centre = -R_wc @ T[:3, 3]
    cols = torch.from_numpy(R_wc.T.copy()).to(rotvec)  # rows = the camera axes in the world
    R_new = rotate(rotvec.reshape(1, 3).expand(3, 3), cols).double().cpu().numpy().T  # columns rotated
    c_new = centre + trans.reshape(3).double().cpu().numpy()
    out = np.eye(4)
    out[:3, :3] = R_new.T
    out[:3, 3] = -R_new.T @ c_new
    return out


class PoseDrift(nn.Module):
    """``rot`` (K, 3): per knot a world-frame rotation vector (rad); ``trans`` (K, 3): a camera-centre
    translation (ENU m); ``coarse_rot`` / ``coarse_trans``: the same for each coarser level (K_l, 3);
    ``frame_rot`` / ``frame_trans`` (F, 3): raw per-frame rows, when ``frame_t01`` gives the normalised
    times of the F frames that have one (empty: none). All start at zero (the telemetry poses); a
    frame's correction is the sum over the levels plus its row's residual (:meth:`frame_residual`)."""

    #: two normalised times closer than this are the same frame (1e-6 of a 10 min flight is 0.6 ms)
    FRAME_TIME_TOL = 1e-6

    def __init__(self, knots: int, coarse_knots: Sequence[int] = (), frame_t01: Sequence[float] = ()):
        super().__init__()
        for k in (knots, *coarse_knots):
            if int(k) != k or k < 2:
                raise ValueError(f"every pose-drift level needs a whole number of at least 2 knots, got {k}")
        times = torch.as_tensor(np.asarray(frame_t01, dtype=np.float64).reshape(-1))
        if not bool(torch.isfinite(times).all()):
            raise ValueError("per-frame pose corrections need finite frame times")
        self.rot = nn.Parameter(torch.zeros(knots, 3))
        self.trans = nn.Parameter(torch.zeros(knots, 3))
        self.coarse_rot = nn.ParameterList([nn.Parameter(torch.zeros(int(k), 3)) for k in coarse_knots])
        self.coarse_trans = nn.ParameterList([nn.Parameter(torch.zeros(int(k), 3)) for k in coarse_knots])
        # without per-frame rows these are None, so the state dict is that of a knots-only drift
        rows = len(times) > 0
        self.register_buffer("frame_t01", times if rows else None)  # float64: matched to pose times to 1e-6
        self.register_parameter("frame_rot", nn.Parameter(torch.zeros(len(times), 3)) if rows else None)
        self.register_parameter("frame_trans", nn.Parameter(torch.zeros(len(times), 3)) if rows else None)
        # the projection onto what the finest knots can represent at the frames' times: B (F, K) holds
        # each frame's interpolation weights, fit = B @ (pinv(B) @ rows); derived from frame_t01, not saved
        basis = _interpolation_matrix(times, knots) if rows else None
        self.register_buffer("_row_basis", basis.float() if rows else None, persistent=False)
        self.register_buffer("_row_basis_pinv", torch.linalg.pinv(basis).float() if rows else None, persistent=False)

    @property
    def knots(self) -> int:
        """Knots of the finest level."""
        return self.rot.shape[0]

    @property
    def coarse_knots(self) -> list[int]:
        return [int(r.shape[0]) for r in self.coarse_rot]

    def translation_params(self) -> list[nn.Parameter]:
        """Every translation parameter (m): the finest knots, the coarser levels, the rows if any."""
        return [self.trans, *self.coarse_trans, *([self.frame_trans] if self.frames else [])]

    def rotation_params(self) -> list[nn.Parameter]:
        """Every rotation-vector parameter (rad), in the same order as :meth:`translation_params`."""
        return [self.rot, *self.coarse_rot, *([self.frame_rot] if self.frames else [])]

    @property
    def frames(self) -> int:
        """Recorded frames with a per-frame row (0: knots only)."""
        return 0 if self.frame_rot is None else int(self.frame_rot.shape[0])

    def frame_row(self, t01: float) -> int | None:
        """The per-frame row of the recorded frame taken at ``t01``, or None (no frame at that time)."""
        if not self.frames:
            return None
        gap = (self.frame_t01 - float(t01)).abs()
        row = int(gap.argmin())
        return row if float(gap[row]) <= self.FRAME_TIME_TOL else None

    def frame_residual(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The rows' effective corrections, rotation vectors and translations (F, 3) each: the raw rows
        minus their least-squares fit by the finest knots' interpolation at the frames' times, so a row
        holds only what the knots cannot (with no more frames than knots, nothing)."""
        B, pinv = self._row_basis, self._row_basis_pinv
        return self.frame_rot - B @ (pinv @ self.frame_rot), self.frame_trans - B @ (pinv @ self.frame_trans)

    def at(self, t01: torch.Tensor, frame: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation vectors (R, 3) and translations (R, 3) at times ``t01`` (R,), clamped to [0, 1]:
        the sum of every level's linear interpolation between its two neighbouring knots, plus, with
        ``frame`` (R,) per-frame row indices (long), those rows' residuals (:meth:`frame_residual`)."""
        rot, trans = _interpolate(self.rot, t01), _interpolate(self.trans, t01)
        for r, t in zip(self.coarse_rot, self.coarse_trans, strict=True):
            rot, trans = rot + _interpolate(r, t01), trans + _interpolate(t, t01)
        if frame is not None and self.frames:
            row_rot, row_trans = self.frame_residual()
            rot, trans = rot + row_rot[frame], trans + row_trans[frame]
        return rot, trans

    def apply(self, origins: torch.Tensor, dirs: torch.Tensor, t01: torch.Tensor,
              frame: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected rays: origins (camera centres, (R, 3) m) shifted, unit directions (R, 3)
        rotated about the centre; both world ENU. ``frame`` (R,): each ray's per-frame row index (None:
        the knots alone). Gradients reach the knots and the rows."""
        rot, trans = self.at(t01, frame)
        return origins + trans, rotate(rot, dirs)

    @torch.no_grad()
    def correct_cam_from_world(self, cam_from_world: np.ndarray, t01: float) -> np.ndarray:
        """The corrected OpenCV ``cam_from_world`` (4x4) of a telemetry pose taken at ``t01``; a recorded
        frame's own row applies when ``t01`` is its time (:meth:`frame_row`)."""
        T = np.asarray(cam_from_world, dtype=np.float64)
        dev = self.rot.device
        row = self.frame_row(t01)
        frame = None if row is None else torch.tensor([row], device=dev)
        rot, trans = self.at(torch.tensor([float(t01)], device=dev), frame)
        return corrected_cam_from_world(T, rot[0], trans[0])

    def _at_knots(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The summed correction at the finest level's knot times, (K, 3) each."""
        if not len(self.coarse_rot):
            return self.rot, self.trans
        return self.at(torch.linspace(0.0, 1.0, self.knots, device=self.rot.device))

    def penalty(self, rot_scale_m: float = 30.0) -> torch.Tensor:
        """Mean squared correction in metres at the finest knots' times: translation, and rotation as
        the shift it causes at ``rot_scale_m`` range (keeps the gauge — a shift of field and all
        poses together — anchored to the telemetry); plus the same of the per-frame rows' residuals."""
        rot, trans = self._at_knots()
        out = trans.square().sum(-1).mean() + (rot_scale_m ** 2) * rot.square().sum(-1).mean()
        if self.frames:
            row_rot, row_trans = self.frame_residual()
            out = out + row_trans.square().sum(-1).mean() + (rot_scale_m ** 2) * row_rot.square().sum(-1).mean()
        return out

    def summary(self) -> dict:
        """Size of the learned corrections at the finest knots' times: RMS / max translation (m) and
        rotation (deg); the knot count of each level; with per-frame rows, their count and their
        residuals' RMS translation (m) and rotation (deg)."""
        with torch.no_grad():
            rot, trans = self._at_knots()
            t = trans.norm(dim=-1)
            r = torch.rad2deg(rot.norm(dim=-1))
            out = {"knots": self.knots, "coarse_knots": self.coarse_knots,
                   "trans_rms_m": float(t.square().mean().sqrt()), "trans_max_m": float(t.max()),
                   "rot_rms_deg": float(r.square().mean().sqrt()), "rot_max_deg": float(r.max())}
            if self.frames:
                row_rot, row_trans = self.frame_residual()
                out.update(frames=self.frames, frame_trans_rms_m=float(row_trans.norm(dim=-1).square().mean().sqrt()),
                           frame_rot_rms_deg=float(torch.rad2deg(row_rot.norm(dim=-1)).square().mean().sqrt()))
        return out


def _interpolate(knots: torch.Tensor, t01: torch.Tensor) -> torch.Tensor:
    """Values (R, C) at times ``t01`` (R,) (clamped to [0, 1]) of knots (K, C) evenly spaced over [0, 1]."""
    n = knots.shape[0]
    x = t01.clamp(0.0, 1.0) * (n - 1)
    i0 = x.floor().long().clamp(max=n - 2)
    w = (x - i0.to(x.dtype))[:, None]
    return knots[i0] * (1 - w) + knots[i0 + 1] * w


def _interpolation_matrix(t01: torch.Tensor, knots: int) -> torch.Tensor:
    """(R, K) float64: row r holds the weights :func:`_interpolate` gives the K knots at time ``t01[r]``."""
    eye = torch.eye(knots, dtype=torch.float64)
    return _interpolate(eye, t01.double())


def warmup_scale(progress: float, delay: float) -> float:
    """Step-size factor of the pose knots at ``progress`` (share of training, 0..1): 0 while
    ``progress < delay``, then a linear ramp to 1 at ``2 * delay``; ``delay <= 0``: always 1.

    Adam moves every parameter by about its step size whatever the gradient's size, so knots that learn
    from the first steps' random field walk decimetres before the field shows a world to line the
    frames up to, and the field then fits the walk."""
    if delay <= 0:
        return 1.0
    return float(min(max((progress - delay) / delay, 0.0), 1.0))
