"""A fitted static field as a view renderer for synthesis: RGB plus per-pixel class probabilities.

Implements the ``render_view(camera, cam_from_world, t_unix_us)`` interface of
:mod:`fields.synthesis`: rays through every pixel centre, rendered in chunks without gradients;
novel views use the mean appearance embedding. The mask is the volume-rendered class distribution
(channel 0 background), so its blobs are soft at the edges, as the box rules expect.
"""

from __future__ import annotations

import numpy as np
import torch

from telemetry.camera import Camera


class FieldViewRenderer:
    def __init__(self, model, n_classes: int, chunk: int = 4096):
        self.model = model.eval()
        self.n_classes = n_classes
        self.chunk = chunk

    @torch.no_grad()
    def render_view(self, camera: Camera, cam_from_world: np.ndarray, t_unix_us: int | None = None):
        dev = self.model.field.lo.device
        uv = camera.pixel_grid().reshape(-1, 2)
        o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
        o_t = torch.from_numpy(np.broadcast_to(o, d.shape).astype(np.float32)).to(dev)
        d_t = torch.from_numpy(d.astype(np.float32)).to(dev)
        rgb, probs = [], []
        for a in range(0, d_t.shape[0], self.chunk):
            res = self.model.render_rays(o_t[a:a + self.chunk], d_t[a:a + self.chunk], None, train=False,
                                         with_mask=True)
            rgb.append(res["rgb"].float().cpu())
            probs.append(res["mask_probs"].float().cpu())
        h, w = camera.height, camera.width
        rgb_u8 = (torch.cat(rgb).clamp(0, 1).view(h, w, 3).numpy() * 255.0 + 0.5).astype(np.uint8)
        prob = torch.cat(probs).view(h, w, -1).numpy()
        if prob.shape[-1] != self.n_classes + 1:
            raise ValueError(f"field has {prob.shape[-1] - 1} mask classes, the flight {self.n_classes}")
        return rgb_u8, prob
