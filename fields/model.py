"""The static model: field + background + sampler wired into ray rendering, and image rendering.

Knows rays (world ENU metres, unit directions) but not images on disk or training. The sampler
is plain state (not an ``nn.Module``); :meth:`StaticModel.extra_state` carries it in checkpoints.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from fields.field import Background, FieldConfig, StaticField
from fields.rendering import composite, distortion_loss, expected_depth, opacity, weights_from_density
from fields.samplers import OccupancySampler, StratifiedSampler, ray_box


@dataclass
class SamplerConfig:
    """``kind``: "stratified" or "occupancy"; grid shape only for the occupancy grid (x, y, z cells)."""

    kind: str = "stratified"
    n_samples: int = 48
    n_coarse: int = 96
    grid_shape: tuple[int, int, int] = (128, 128, 16)
    #: rays that exit through the slab's floor end opaque there (no background seen through the ground)
    opaque_floor: bool = True


def make_sampler(cfg: SamplerConfig):
    if cfg.kind == "stratified":
        return StratifiedSampler(cfg.n_samples)
    if cfg.kind == "occupancy":
        return OccupancySampler(tuple(cfg.grid_shape), cfg.n_samples, cfg.n_coarse)
    raise ValueError(f"unknown sampler {cfg.kind!r}; expected 'stratified' or 'occupancy'")


class StaticModel(nn.Module):
    """Field, background and sampler; :meth:`render_rays` is the only entry point for rendering."""

    def __init__(self, field_config: FieldConfig, sampler_config: SamplerConfig, ground_z: float,
                 background_radius_m: float):
        super().__init__()
        self.field_config, self.sampler_config = field_config, sampler_config
        self.field = StaticField(field_config)
        self.background = Background(ground_z, background_radius_m)
        self.sampler = make_sampler(sampler_config)

    # ---- checkpoint ---------------------------------------------------------------------
    def describe(self) -> dict:
        return {"field": self.field_config.to_json(), "sampler": {**asdict(self.sampler_config),
                                                                  "grid_shape": list(self.sampler_config.grid_shape)},
                "ground_z": self.background.ground_z, "background_radius_m": self.background.radius_m}

    @classmethod
    def from_description(cls, d: dict) -> StaticModel:
        s = dict(d["sampler"])
        s["grid_shape"] = tuple(s["grid_shape"])
        return cls(FieldConfig.from_json(d["field"]), SamplerConfig(**s), d["ground_z"], d["background_radius_m"])

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    # ---- rendering ----------------------------------------------------------------------
    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, image_idx: torch.Tensor | None = None,
                    train: bool = False, with_mask: bool = True, generator=None) -> dict:
        """Render R rays: ``rgb`` (R,3), ``acc`` (R,1), ``depth`` (R,1), ``mask_probs`` (R,C+1),
        and for the losses ``weights`` (R,S) and ``t_norm`` (R,S+1) (edges scaled to [0,1] per ray)."""
        f = self.field
        edges = self.sampler.edges(origins, dirs, f.lo, f.hi, train=train, generator=generator)
        r, s1 = edges.shape
        s = s1 - 1
        mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
        deltas = edges[:, 1:] - edges[:, :-1]
        pts = (origins[:, None, :] + mid[..., None] * dirs[:, None, :]).reshape(-1, 3)
        d_rep = dirs[:, None, :].expand(r, s, 3).reshape(-1, 3)
        i_rep = None if image_idx is None else image_idx[:, None].expand(r, s).reshape(-1)
        out = f(pts, d_rep, i_rep, with_mask=with_mask)
        sigma = out["sigma"].view(r, s)
        if self.sampler_config.opaque_floor:
            # rays leaving the slab through its floor must end in the field: an opaque last interval
            # (else "all transparent + background texture" is a blurry local minimum, measured 16.8 dB)
            floor = (origins[:, 2] + edges[:, -1] * dirs[:, 2]) <= f.lo[2] + 1e-3
            last = torch.where(floor, torch.full_like(sigma[:, -1], 1e4), sigma[:, -1])
            sigma = torch.cat([sigma[:, :-1], last[:, None]], dim=-1)
        w = weights_from_density(sigma, deltas)
        bg = self.background(origins, dirs)
        res = {"rgb": composite(w, out["rgb"].view(r, s, 3), bg), "acc": opacity(w),
               "depth": expected_depth(w, mid, edges[:, -1]), "weights": w}
        span = (edges[:, -1:] - edges[:, :1]).clamp_min(1e-6)
        res["t_norm"] = (edges - edges[:, :1]) / span
        if with_mask:
            probs = torch.softmax(out["mask_logits"].view(r, s, -1), dim=-1)
            bg_class = torch.zeros(probs.shape[-1], device=probs.device)
            bg_class[0] = 1.0
            # weights detached: the mask reads the geometry (shared features) but cannot carve it
            # (else "background" is cheapest to explain by making the ground transparent)
            res["mask_probs"] = composite(w.detach(), probs, bg_class)
        return res

    def distortion(self, res: dict) -> torch.Tensor:
        return distortion_loss(res["weights"], res["t_norm"]).mean()

    @torch.no_grad()
    def render_image(self, camera, cam_from_world: np.ndarray, chunk: int = 16384, with_mask: bool = True,
                     image_idx: int | None = None) -> dict:
        """Render a full frame: ``rgb`` (H,W,3) float in [0,1], ``mask`` (H,W) class ids (0 background),
        ``acc`` (H,W), ``depth`` (H,W) metres along the ray. Novel views use the mean appearance."""
        dev = self.field.lo.device
        uv = camera.pixel_grid().reshape(-1, 2)
        o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
        o = torch.from_numpy(np.broadcast_to(o, d.shape).copy()).float().to(dev)
        d = torch.from_numpy(d).float().to(dev)
        outs = {"rgb": [], "acc": [], "depth": [], "mask": []}
        for a in range(0, d.shape[0], chunk):
            idx = None if image_idx is None else torch.full((min(chunk, d.shape[0] - a),), image_idx,
                                                            dtype=torch.long, device=dev)
            res = self.render_rays(o[a:a + chunk], d[a:a + chunk], idx, train=False, with_mask=with_mask)
            outs["rgb"].append(res["rgb"])
            outs["acc"].append(res["acc"][:, 0])
            outs["depth"].append(res["depth"][:, 0])
            if with_mask:
                outs["mask"].append(res["mask_probs"].argmax(-1))
        h, w = camera.height, camera.width
        result = {k: torch.cat(v).view(h, w, *([3] if k == "rgb" else [])).cpu().numpy()
                  for k, v in outs.items() if v}
        return result

    def rays_hit_box(self, origins, dirs) -> torch.Tensor:
        return ray_box(origins, dirs, self.field.lo, self.field.hi)[2]
