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
from fields.samplers import OccupancySampler, StratifiedSampler, grid_lookup, ray_box, sample_points


@dataclass
class SamplerConfig:
    """``kind``: "stratified" or "occupancy"; grid shape only for the occupancy grid (x, y, z cells)."""

    kind: str = "stratified"
    n_samples: int = 48
    n_coarse: int = 96
    grid_shape: tuple[int, int, int] = (128, 128, 16)
    #: rays that exit through the slab's floor end opaque there (no background seen through the ground)
    opaque_floor: bool = True
    #: rendering only: density (1/m) below which a skip-grid cell counts as empty (0: no skipping)
    skip_threshold: float = 1e-2
    #: colour and mask are evaluated only at samples with at least this rendering weight
    min_weight: float = 1e-4


def make_sampler(cfg: SamplerConfig):
    if cfg.kind == "stratified":
        return StratifiedSampler(cfg.n_samples)
    if cfg.kind == "occupancy":
        return OccupancySampler(tuple(cfg.grid_shape), cfg.n_samples, cfg.n_coarse)
    raise ValueError(f"unknown sampler {cfg.kind!r}; expected 'stratified' or 'occupancy'")


class StaticModel(nn.Module):
    """Field, background and sampler; :meth:`render_rays` is the only entry point for rendering."""

    def __init__(self, field_config: FieldConfig, sampler_config: SamplerConfig, ground_z: float,
                 background_radius_m: float, background_resolution: int = 64, background_mip: bool = False):
        super().__init__()
        self.field_config, self.sampler_config = field_config, sampler_config
        self.field = StaticField(field_config)
        self.background = Background(ground_z, background_radius_m, background_resolution, background_mip)
        self.sampler = make_sampler(sampler_config)
        self.skip_grid: torch.Tensor | None = None

    # ---- checkpoint ---------------------------------------------------------------------
    def describe(self) -> dict:
        return {"field": self.field_config.to_json(), "sampler": {**asdict(self.sampler_config),
                                                                  "grid_shape": list(self.sampler_config.grid_shape)},
                "ground_z": self.background.ground_z, "background_radius_m": self.background.radius_m,
                "background_resolution": self.background.texture.shape[-1], "background_mip": self.background.mip}

    @classmethod
    def from_description(cls, d: dict) -> StaticModel:
        s = dict(d["sampler"])
        s["grid_shape"] = tuple(s["grid_shape"])
        if "skip_threshold" not in s:  # checkpoints from before the skip grid: render exactly as then
            s["skip_threshold"], s["min_weight"] = 0.0, 0.0
        return cls(FieldConfig.from_json(d["field"]), SamplerConfig(**s), d["ground_z"], d["background_radius_m"],
                   d.get("background_resolution", 64), d.get("background_mip", False))

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    # ---- rendering ----------------------------------------------------------------------
    def train(self, mode: bool = True):
        if mode:
            self.skip_grid = None  # the field changes while training: rebuild before the next render
        return super().train(mode)

    @torch.no_grad()
    def build_skip_grid(self, threshold: float | None = None) -> torch.Tensor:
        """Occupancy of the field for rendering (not training): (gx, gy, gz) bool over the scene box.

        Density is evaluated at every cell corner; a cell is occupied when any of its 8 corners has
        ``sigma >= threshold`` (default ``SamplerConfig.skip_threshold``), then dilated by one cell
        in every direction so thin or small objects between corners are not lost. Samples in empty
        cells are skipped (density 0) by :meth:`render_rays` in eval mode.
        """
        thr = self.sampler_config.skip_threshold if threshold is None else threshold
        gx, gy, gz = self.sampler_config.grid_shape
        f = self.field
        axes = [torch.linspace(0.0, 1.0, n + 1, device=f.lo.device) for n in (gx, gy, gz)]
        corners = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).view(-1, 3)
        pts = f.lo + corners * (f.hi - f.lo)
        sig = torch.cat([f.density(p) for p in pts.split(65536)]).view(gx + 1, gy + 1, gz + 1)
        occ = (sig >= thr).float()[None, None]
        occ = torch.nn.functional.max_pool3d(occ, 2, stride=1)  # any corner of the cell
        occ = torch.nn.functional.max_pool3d(occ, 3, stride=1, padding=1)  # dilate by one cell
        self.skip_grid = occ[0, 0] > 0
        return self.skip_grid

    def _occupied(self, pts: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the skip grid's cell of each point (N, 3) is occupied (outside the box: False)."""
        f = self.field
        x = (pts - f.lo) / (f.hi - f.lo)
        inside = ((x >= 0) & (x <= 1)).all(-1)
        return inside & grid_lookup(self.skip_grid, pts, f.lo, f.hi)

    def _weights(self, origins: torch.Tensor, dirs: torch.Tensor, train: bool, skip: bool,
                 generator=None) -> tuple:
        """Samples and rendering weights of R rays: ``(edges (R,S+1), mid (R,S), pts (R*S,3),
        geo (R*S,G), w (R,S))``. ``skip``: samples in cells the skip grid marks empty get density 0
        and zero features, without evaluating the field (built on first use, eval mode only)."""
        f = self.field
        edges = self.sampler.edges(origins, dirs, f.lo, f.hi, train=train, generator=generator)
        r, s1 = edges.shape
        s = s1 - 1
        mid, deltas, pts = sample_points(origins, dirs, edges)
        if skip and self.sampler_config.skip_threshold > 0:
            if self.skip_grid is None:
                self.build_skip_grid()
            occ = self._occupied(pts).view(r, s)
            occ[:, -1] = True  # the last interval may be the opaque floor: its colour must be real
            keep = occ.view(-1).nonzero()[:, 0]
            sig_k, geo_k = f.geometry(pts[keep])
            sigma = torch.zeros(r * s, device=pts.device).index_copy_(0, keep, sig_k)
            geo = torch.zeros(r * s, geo_k.shape[1], device=pts.device).index_copy_(0, keep, geo_k)
        else:
            sigma, geo = f.geometry(pts)
        sigma = sigma.view(r, s)
        if self.sampler_config.opaque_floor:
            # rays leaving the slab through its floor must end in the field: an opaque last interval
            # (else "all transparent + background texture" is a blurry local minimum, measured 16.8 dB)
            floor = (origins[:, 2] + edges[:, -1] * dirs[:, 2]) <= f.lo[2] + 1e-3
            last = torch.where(floor, torch.full_like(sigma[:, -1], 1e4), sigma[:, -1])
            sigma = torch.cat([sigma[:, :-1], last[:, None]], dim=-1)
        return edges, mid, pts, geo, weights_from_density(sigma, deltas)

    def _mask_probs(self, w: torch.Tensor, pts: torch.Tensor, geo: torch.Tensor) -> torch.Tensor:
        """Composited class probabilities (R, C+1) with *detached* weights ``w`` (R,S): the mask reads
        the geometry but cannot carve it (else "background" is cheapest to explain by making the
        ground transparent). Evaluated only at samples with weight >= ``min_weight``."""
        return self.composite_mask(*self._live_samples(w.detach(), pts, geo))

    def _live_samples(self, w: torch.Tensor, pts: torch.Tensor, geo: torch.Tensor) -> tuple:
        """The samples with weight >= ``min_weight`` of R rays: ``(ray (L,) long, weight (L,),
        point (L,3), geometry feature (L,G), rest (R,))``, ``rest`` = 1 - the ray's total weight."""
        r, s = w.shape
        live = (w.reshape(-1) >= self.sampler_config.min_weight).nonzero()[:, 0]
        return live // s, w.reshape(-1)[live], pts[live], geo[live], 1.0 - w.sum(-1)

    def composite_mask(self, ray: torch.Tensor, w: torch.Tensor, pts: torch.Tensor, geo: torch.Tensor,
                       rest: torch.Tensor) -> torch.Tensor:
        """Class probabilities (R, C+1) of R rays from their live samples (see :meth:`_live_samples`):
        sum of weight x softmax(mask logits) per ray, plus ``rest`` on the background class (what the
        ray sees beyond the field is background)."""
        n_cls = self.field.config.n_classes + 1
        out = torch.zeros(rest.shape[0], n_cls, device=rest.device)
        if len(ray):
            probs = torch.softmax(self.field.mask_logits(pts, geo), dim=-1)
            out = out.index_add(0, ray, w[:, None] * probs)
        return torch.cat([out[:, :1] + rest[:, None], out[:, 1:]], dim=-1)

    @torch.no_grad()
    def mask_samples(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple:
        """Live samples of R rays for training the mask on a frozen geometry (no gradients, no
        jitter, no skip grid): ``(ray, weight, point, geometry feature, rest)`` as
        :meth:`composite_mask` takes them."""
        *_, pts, geo, w = self._weights(origins, dirs, False, False)
        return self._live_samples(w, pts, geo)

    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, image_idx: torch.Tensor | None = None,
                    train: bool = False, with_mask: bool = True, generator=None,
                    pixel_rad: float | None = None) -> dict:
        """Render R rays: ``rgb`` (R,3), ``acc`` (R,1), ``depth`` (R,1), ``mask_probs`` (R,C+1),
        and for the losses ``weights`` (R,S), ``sample_z`` (R,S) (the samples' ENU height, m) and
        ``t_norm`` (R,S+1) (edges scaled to [0,1] per ray).

        In eval mode without gradients (rendering), three shortcuts, each bounded by a stated error:
        samples in cells the skip grid marks empty get density 0 (:meth:`build_skip_grid`), and
        colour and mask are evaluated only at samples whose weight is >= ``SamplerConfig.min_weight``
        (so samples behind the surface, where transmittance has died, cost only their density).
        The mask is always evaluated only at such samples (its loss never needs the others).
        """
        f = self.field
        fast = not train and not torch.is_grad_enabled() and not self.training
        edges, mid, pts, geo, w = self._weights(origins, dirs, train, fast, generator)
        r, s = w.shape
        d_rep = dirs[:, None, :].expand(r, s, 3).reshape(-1, 3)
        i_rep = None if image_idx is None else image_idx[:, None].expand(r, s).reshape(-1)
        if fast:
            live = (w.view(-1) >= self.sampler_config.min_weight).nonzero()[:, 0]
            rgb = torch.zeros(r * s, 3, device=pts.device).index_copy_(
                0, live, f.color(geo[live], d_rep[live], None if i_rep is None else i_rep[live]))
        else:
            rgb = f.color(geo, d_rep, i_rep)
        bg = self.background(origins, dirs, pixel_rad)
        res = {"rgb": composite(w, rgb.view(r, s, 3), bg), "acc": opacity(w),
               "depth": expected_depth(w, mid, edges[:, -1]), "weights": w, "sample_z": pts.view(r, s, 3)[..., 2]}
        res["t_norm"] = _normalised_edges(edges)
        if with_mask:
            res["mask_probs"] = self._mask_probs(w, pts, geo)
        return res

    def distortion(self, res: dict) -> torch.Tensor:
        return distortion_loss(res["weights"], res["t_norm"]).mean()

    def geometry_distortion(self, origins: torch.Tensor, dirs: torch.Tensor, generator=None) -> torch.Tensor:
        """Mean distortion loss of R rays (world ENU, unit directions) from the density alone (no
        colour, mask or background): for rays no camera took, e.g. :func:`topdown_rays`."""
        edges, _, _, _, w = self._weights(origins, dirs, True, False, generator)
        return distortion_loss(w, _normalised_edges(edges)).mean()

    @torch.no_grad()
    def render_image(self, camera, cam_from_world: np.ndarray, chunk: int = 4096, with_mask: bool = True,
                     image_idx: int | None = None) -> dict:
        """Render a full frame: ``rgb`` (H,W,3) float in [0,1], ``mask`` (H,W) class ids (0 background),
        ``mask_probs`` (H,W,C+1) class probabilities (channel 0 background),
        ``acc`` (H,W), ``depth`` (H,W) metres along the ray. Novel views use the mean appearance.
        Call in eval mode for the rendering shortcuts of :meth:`render_rays`."""
        dev = self.field.lo.device
        uv = camera.pixel_grid().reshape(-1, 2)
        o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
        o = torch.from_numpy(np.broadcast_to(o, d.shape).copy()).float().to(dev)
        d = torch.from_numpy(d).float().to(dev)
        outs = {"rgb": [], "acc": [], "depth": [], "mask": [], "mask_probs": []}
        for a in range(0, d.shape[0], chunk):
            idx = None if image_idx is None else torch.full((min(chunk, d.shape[0] - a),), image_idx,
                                                            dtype=torch.long, device=dev)
            res = self.render_rays(o[a:a + chunk], d[a:a + chunk], idx, train=False, with_mask=with_mask,
                                   pixel_rad=camera.pixel_rad)
            outs["rgb"].append(res["rgb"])
            outs["acc"].append(res["acc"][:, 0])
            outs["depth"].append(res["depth"][:, 0])
            if with_mask:
                outs["mask"].append(res["mask_probs"].argmax(-1))
                outs["mask_probs"].append(res["mask_probs"])
        h, w = camera.height, camera.width
        result = {k: torch.cat(v).view(h, w, -1 if k in ("rgb", "mask_probs") else 1).squeeze(-1).cpu().numpy()
                  for k, v in outs.items() if v}
        return result

    def rays_hit_box(self, origins, dirs) -> torch.Tensor:
        return ray_box(origins, dirs, self.field.lo, self.field.hi)[2]


def _normalised_edges(edges: torch.Tensor) -> torch.Tensor:
    """Interval edges (R, S+1) of each ray scaled to [0, 1] over its own span (the distortion loss's input)."""
    span = (edges[:, -1:] - edges[:, :1]).clamp_min(1e-6)
    return (edges - edges[:, :1]) / span


def topdown_rays(lo: torch.Tensor, hi: torch.Tensor, n: int, max_tilt_deg: float, generator=None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` rays looking down into the scene box [lo, hi] (world ENU, m) as a higher camera would:
    origins 1 m above the box top, uniform over its xy; unit directions within ``max_tilt_deg`` of
    nadir (tilt uniform in angle, azimuth uniform). Returns origins (n, 3) and directions (n, 3)."""
    u = torch.rand(n, 4, device=lo.device, generator=generator)
    xy = lo[:2] + u[:, :2] * (hi[:2] - lo[:2])
    origins = torch.cat([xy, (hi[2] + 1.0).expand(n, 1)], dim=-1)
    tilt = torch.deg2rad(torch.as_tensor(max_tilt_deg, device=lo.device)) * u[:, 2]
    az = 2 * torch.pi * u[:, 3]
    dirs = torch.stack([torch.sin(tilt) * torch.cos(az), torch.sin(tilt) * torch.sin(az), -torch.cos(tilt)], -1)
    return origins, dirs
