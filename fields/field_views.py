"""Fitted fields as view renderers for synthesis: RGB plus per-pixel class probabilities.

Implements the ``render_view(camera, cam_from_world, t_unix_us)`` interface of
:mod:`fields.synthesis`: rays through every pixel centre, rendered in chunks without gradients;
novel views use the mean appearance embedding. The mask is the volume-rendered class distribution
(channel 0 background), so its blobs are soft at the edges, as the box rules expect. A static field
ignores the time; a dynamic (K-Planes) field renders at the pose's capture time ``t_unix_us`` (unix
µs; None: the flight's first frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from telemetry.camera import Camera


class FieldViewRenderer:
    """A static field (:class:`fields.model.StaticModel`): the time is ignored.

    ``n_classes``: the flight's mask classes, checked against the field's (None: not checked).
    """

    def __init__(self, model, n_classes: int | None = None, chunk: int = 4096):
        self.model = model.eval()
        self.n_classes = n_classes
        self.chunk = chunk

    def _render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, t_unix_us: int | None,
                     with_mask: bool, pixel_rad: float | None = None) -> dict:
        return self.model.render_rays(origins, dirs, None, train=False, with_mask=with_mask, pixel_rad=pixel_rad)

    def field_pose(self, cam_from_world: np.ndarray, t_unix_us: int | None) -> np.ndarray:
        """The field-world pose of a *recorded* frame's telemetry pose (OpenCV ``cam_from_world``) taken
        at ``t_unix_us``: unchanged for a static field (novel poses never need this)."""
        return np.asarray(cam_from_world, dtype=np.float64)

    def render_view(self, camera: Camera, cam_from_world: np.ndarray, t_unix_us: int | None = None,
                    with_mask: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """RGB (H,W,3) uint8 and class probabilities (H,W,C+1), channel 0 background (None without mask)."""
        rgb, prob, _ = self.render_view_depth(camera, cam_from_world, t_unix_us, with_mask)
        return rgb, prob

    @torch.no_grad()
    def render_view_depth(self, camera: Camera, cam_from_world: np.ndarray, t_unix_us: int | None = None,
                          with_mask: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """As :meth:`render_view`, plus the expected depth (H,W) float32, metres along each pixel's unit ray."""
        dev = self.model.field.lo.device
        uv = camera.pixel_grid().reshape(-1, 2)
        o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
        o_t = torch.from_numpy(np.broadcast_to(o, d.shape).astype(np.float32)).to(dev)
        d_t = torch.from_numpy(d.astype(np.float32)).to(dev)
        rgb, probs, depth = [], [], []
        for a in range(0, d_t.shape[0], self.chunk):
            res = self._render_rays(o_t[a:a + self.chunk], d_t[a:a + self.chunk], t_unix_us, with_mask,
                                    camera.pixel_rad)
            rgb.append(res["rgb"].float().cpu())
            depth.append(res["depth"].float().reshape(-1).cpu())
            if with_mask:
                probs.append(res["mask_probs"].float().cpu())
        h, w = camera.height, camera.width
        rgb_u8 = (torch.cat(rgb).clamp(0, 1).view(h, w, 3).numpy() * 255.0 + 0.5).astype(np.uint8)
        depth_m = torch.cat(depth).view(h, w).numpy()
        if not with_mask:
            return rgb_u8, None, depth_m
        prob = torch.cat(probs).view(h, w, -1).numpy()
        if self.n_classes is not None and prob.shape[-1] != self.n_classes + 1:
            raise ValueError(f"field has {prob.shape[-1] - 1} mask classes, the flight {self.n_classes}")
        return rgb_u8, prob, depth_m


class DynamicViewRenderer(FieldViewRenderer):
    """A dynamic field (:class:`fields.dynamic_model.DynamicModel`) rendered at the pose's time."""

    def _render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, t_unix_us: int | None,
                     with_mask: bool, pixel_rad: float | None = None) -> dict:
        times01 = torch.full((origins.shape[0],), self.model.time01(t_unix_us), device=origins.device)
        return self.model.render_rays(origins, dirs, times01, train=False, with_mask=with_mask)

    def field_pose(self, cam_from_world: np.ndarray, t_unix_us: int | None) -> np.ndarray:
        """The recorded pose with the field's learned pose-drift correction at its time, if any."""
        return self.model.field_pose(cam_from_world, self.model.time01(t_unix_us))


def load_view_renderer(checkpoint: str | Path | None, flight: str | Path,
                       n_classes: int | None = None) -> FieldViewRenderer:
    """The view renderer of a static or dynamic checkpoint. Default: ``FLIGHT/derived/fields/static.pt``,
    else ``dynamic.pt``; a dynamic field renders each pose at its ``t_unix_us`` (None: the flight's
    first frame time, DESIGN.md §3)."""
    from fields.dynamic_training import FORMAT, load_dynamic_checkpoint
    from fields.training import load_checkpoint

    if checkpoint is None:
        folder = Path(flight) / "derived" / "fields"
        checkpoint = folder / "static.pt"
        if not checkpoint.is_file() and (folder / "dynamic.pt").is_file():
            checkpoint = folder / "dynamic.pt"
    if Path(checkpoint).is_file() and torch.load(checkpoint, map_location="cpu", weights_only=False).get(
            "format") == FORMAT:
        return DynamicViewRenderer(load_dynamic_checkpoint(checkpoint)[0], n_classes)
    return FieldViewRenderer(load_checkpoint(checkpoint)[0], n_classes)
