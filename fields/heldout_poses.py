"""Test-time pose alignment of held-out frames against a trained, frozen dynamic field.

A held-out frame's telemetry pose carries its own white jitter (a few cm, ~0.1 deg) that no field can
know: the learned drift knots (:mod:`fields.pose_drift`) interpolate the training frames around it, so
the held-out render starts misregistered by that jitter whatever the field's quality. Evaluations of
fields trained on noisy poses (BARF, NeRF--, CamP) therefore also report held-out PSNR after a short
photometric alignment of each held-out frame's pose with the field frozen. This module does that:
one world-frame rotation vector (rad, about the camera centre) and one camera-centre translation (ENU
m) per frame, the correction :class:`fields.pose_drift.PoseDrift` applies, fitted by Adam to the
frame's own pixels *outside* the label boxes (the static background: a walking person at the wrong
place is the field's error, not the pose's). Six numbers per frame cannot repaint a frame, but they do
fit its pixels and so absorb some of the field's error as well: on the bench flights the corrections
grew with the steps past the true jitter (150 steps: 5-6 cm, 0.25-0.35 deg rms; 400 steps: 9 cm,
0.3-0.4 deg; the truth 5 cm, 0.15 deg; bench/RESULTS.md, Table III session 20). The aligned PSNR is an
upper bound: report it next to the plain held-out PSNR, never instead of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fields.data import RayBank
from fields.pose_drift import corrected_cam_from_world, rotate


@dataclass
class AlignmentOptions:
    """``steps`` Adam steps over all frames at once, ``batch_rays`` rays per step drawn uniformly over
    (frame, background pixel); step sizes in metres and radians, decayed to ``lr_final`` times over
    the steps."""

    steps: int = 150
    batch_rays: int = 2048
    lr_m: float = 2e-3
    lr_rad: float = 2e-4
    lr_final: float = 0.1
    seed: int = 0


def align_heldout_poses(model, camera, cam_from_world: list[np.ndarray], t01: list[float], images: torch.Tensor,
                        background: torch.Tensor | None = None, options: AlignmentOptions | None = None
                        ) -> tuple[list[np.ndarray], dict]:
    """Aligned OpenCV ``cam_from_world`` (4x4) of F frames and a report.

    ``model``: a :class:`fields.dynamic_model.DynamicModel` (left unchanged; its parameters are frozen
    for the alignment and restored after). ``cam_from_world``: the start poses in the field's world
    (e.g. ``model.field_pose`` of the telemetry). ``t01`` (F,): the frames' normalised times. ``images``
    (F, H, W, 3) uint8. ``background`` (F, H, W) bool: the pixels that drive the alignment (None: all).
    The report holds the loss (MSE over the batch) at the start and the end and the corrections' RMS
    size (m, deg)."""
    opts = options or AlignmentOptions()
    n = len(cam_from_world)
    if n == 0:
        return [], {"frames": 0}
    if len(t01) != n or images.shape[0] != n:
        raise ValueError("one time and one image per pose, please")
    dev = model.field.lo.device
    bank = RayBank(camera, cam_from_world, dev)
    hw = bank.hw
    colours = images.reshape(n, hw, 3).to(dev)
    if background is None:
        frame_of, pixel_of = torch.arange(n, device=dev).repeat_interleave(hw), torch.arange(hw, device=dev).repeat(n)
    else:
        frame_of, pixel_of = torch.nonzero(background.reshape(n, hw).to(dev), as_tuple=True)
    if frame_of.numel() == 0:
        raise ValueError("no background pixel to align the frames with")
    times = torch.as_tensor(np.asarray(t01, dtype=np.float32), device=dev)
    rot = torch.zeros(n, 3, device=dev, requires_grad=True)
    trans = torch.zeros(n, 3, device=dev, requires_grad=True)
    optim = torch.optim.Adam([{"params": [trans], "lr": opts.lr_m}, {"params": [rot], "lr": opts.lr_rad}])
    base_lr = [opts.lr_m, opts.lr_rad]
    gen = torch.Generator(device=dev).manual_seed(opts.seed)
    frozen = [(p, p.requires_grad) for p in model.parameters()]
    was_training = model.training
    losses = []
    try:
        for p, _ in frozen:
            p.requires_grad_(False)
        model.eval()
        for step in range(max(int(opts.steps), 0)):
            decay = opts.lr_final ** (step / max(opts.steps - 1, 1))
            for g, lr in zip(optim.param_groups, base_lr, strict=True):
                g["lr"] = lr * decay
            k = torch.randint(frame_of.numel(), (opts.batch_rays,), device=dev, generator=gen)
            fi, pi = frame_of[k], pixel_of[k]
            o, d = bank.rays(fi, pi)
            o, d = o + trans[fi], rotate(rot[fi], d)
            res = model.render_rays(o, d, times[fi], train=False, with_mask=False)
            loss = ((res["rgb"] - colours[fi, pi].float() / 255.0) ** 2).mean()
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            losses.append(float(loss.detach()))
    finally:
        for p, flag in frozen:
            p.requires_grad_(flag)
        model.train(was_training)
    rot, trans = rot.detach(), trans.detach()
    poses = [corrected_cam_from_world(T, rot[i], trans[i]) for i, T in enumerate(cam_from_world)]
    head = losses[: max(1, len(losses) // 10)]
    tail = losses[-max(1, len(losses) // 10):]
    report = {"frames": n, "steps": len(losses), "batch_rays": opts.batch_rays,
              "loss_start": float(np.mean(head)) if losses else None,
              "loss_end": float(np.mean(tail)) if losses else None,
              "trans_rms_m": float(trans.square().sum(-1).mean().sqrt()),
              "rot_rms_deg": float(np.degrees(float(rot.square().sum(-1).mean().sqrt())))}
    return poses, report


def align_flight_frames(model, dd, indices: list[int], options: AlignmentOptions | None = None
                        ) -> tuple[dict[int, np.ndarray], dict]:
    """:func:`align_heldout_poses` for the frames ``indices`` of a dynamic flight
    (:class:`fields.dynamic_data.DynamicFlightData`), started from their drift-corrected telemetry poses
    (``model.field_pose``) and driven by the pixels outside their label boxes (all pixels of a frame
    without labels). Returns frame index -> aligned ``cam_from_world``, and the report."""
    data = dd.data
    t01 = dd.t01()
    idx = [int(i) for i in indices]
    start = [model.field_pose(data.cam_from_world[i], float(t01[i])) for i in idx]
    images = data.images[idx]
    background = data.masks[idx] == 0
    background[~data.has_mask[idx].bool()] = True
    poses, report = align_heldout_poses(model, data.camera, start, [float(t01[i]) for i in idx], images,
                                        background, options)
    return dict(zip(idx, poses, strict=True)), report
