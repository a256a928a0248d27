"""The static field: at world points, density, colour and mask class scores (no rays here).

Geometry: encoding(x01) -> small MLP -> raw density + a geometry feature vector. Density is
``trunc_exp(raw)`` (exp forward, gradient computed with the exponent clamped at 15, as Nerfacto).
Colour: geometry feature + per-image appearance embedding (+ optional spherical-harmonics view
direction, degree 2) -> MLP -> sigmoid RGB in [0, 1] (linear in the stored 8-bit sRGB values).
Mask: logits over ``n_classes + 1`` classes, index 0 = background, ``k + 1`` = object class ``k``
(classes.txt order), from either
- ``mask_encoding="grid"`` (default): its own small hash grid read at the same points + a small MLP, or
- ``mask_encoding="geometry"``: a small MLP on the (detached) geometry feature.
Either way the mask loss cannot change the density (the model composites the mask with detached
weights), so image and mask come from one geometry (this replaces the paper's second field)
while the mask has capacity of its own (measured in bench/RESULTS.md: the head on geometry
features alone did not learn the people).

Optionally (``FieldConfig.footprint_cells``) each hash level's features are damped where the training
frames saw the ground coarser than the level's cells (:mod:`fields.footprint`), a function of the
point's position only.

Points are world ENU metres; the field maps them into its scene box (``aabb`` lo, hi) to [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from fields.encodings import make_encoding
from fields.footprint import level_weights


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=30.0))

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-15.0, 15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """exp(x) with a gradient that stays finite for large x."""
    return _TruncExp.apply(x)


def sh_encoding_deg2(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics up to degree 2 (9 values) of unit directions (N, 3)."""
    x, y, z = d.unbind(-1)
    return torch.stack([
        torch.full_like(x, 0.28209479), 0.48860251 * y, 0.48860251 * z, 0.48860251 * x,
        1.09254843 * x * y, 1.09254843 * y * z, 0.31539157 * (3 * z * z - 1), 1.09254843 * x * z,
        0.54627421 * (x * x - y * y)], dim=-1)


@dataclass
class FieldConfig:
    """Everything needed to rebuild a :class:`StaticField` (stored in the checkpoint)."""

    #: scene box, world ENU metres: (x, y, z) lower and upper corners
    aabb_lo: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    aabb_hi: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: "hash" or "planes"
    encoding: str = "hash"
    #: per level (hash) / per scale (planes) resolutions along x, y, z
    resolutions: list = field(default_factory=lambda: [(16, 16, 4), (64, 64, 16)])
    features: int = 2
    log2_table: int = 16
    hidden: int = 64
    geo_features: int = 15
    n_images: int = 1
    appearance_dim: int = 8
    view_dependent: bool = False
    n_classes: int = 3
    #: added to the raw density before trunc_exp (1/m after it): -1 is ~0.37 /m, an optical depth of ~4 down
    #: the bench's 11 m box, so the fresh field is a fog, not empty. A transparent start (-4) gained nothing
    #: here, unlike the dynamic fields (bench/RESULTS.md, Table III session 32); kept
    density_bias: float = -1.0
    #: "grid" (own hash grid for the mask) or "geometry" (head on the detached geometry features)
    mask_encoding: str = "grid"
    mask_resolutions: list = field(default_factory=lambda: [(16, 16, 4), (64, 64, 16)])
    mask_features: int = 2
    mask_log2_table: int = 16
    #: background probability of a fresh mask head (its output bias, classes equal), e.g. 0.99: what no
    #: mask ray has reached yet stays background. None: torch's default init, ~uniform over the C + 1
    #: outputs, i.e. every untrained place starts as foreground 0.75 (bench/RESULTS.md, Session 3)
    mask_init_background: float | None = None
    #: (cx, cy) cells of a map of the finest training footprint over the box's xy that damps each hash
    #: level where the data was coarser than its cells (:mod:`fields.footprint`); None: every level at
    #: full weight everywhere. The map itself is a buffer (in the checkpoint), set by ``set_footprint``
    footprint_cells: tuple[int, int] | None = None

    def to_json(self) -> dict:
        d = asdict(self)
        d["resolutions"] = [list(r) for r in self.resolutions]
        d["mask_resolutions"] = [list(r) for r in self.mask_resolutions]
        return d

    @classmethod
    def from_json(cls, d: dict) -> FieldConfig:
        d = dict(d)
        d.setdefault("mask_encoding", "geometry")  # checkpoints from before the mask grid
        d["resolutions"] = [tuple(r) for r in d["resolutions"]]
        if "mask_resolutions" in d:
            d["mask_resolutions"] = [tuple(r) for r in d["mask_resolutions"]]
        d["aabb_lo"], d["aabb_hi"] = tuple(d["aabb_lo"]), tuple(d["aabb_hi"])
        if d.get("footprint_cells") is not None:
            d["footprint_cells"] = tuple(d["footprint_cells"])
        return cls(**d)


def init_background_bias(layer: nn.Linear, p_background: float) -> None:
    """Set a mask head's output bias so that its softmax starts at ``p_background`` on channel 0
    (background) and shares the rest equally among the classes; the weights are left as they are,
    so the start is that distribution plus the head's small random variation."""
    n_classes = layer.out_features - 1
    p0 = min(max(float(p_background), 1e-6), 1.0 - 1e-6)
    with torch.no_grad():
        layer.bias.zero_()
        layer.bias[0] = math.log(p0 * n_classes / (1.0 - p0))


class StaticField(nn.Module):
    """Density, colour and mask logits at world points; see the module docstring."""

    def __init__(self, config: FieldConfig):
        super().__init__()
        self.config = config
        self.register_buffer("lo", torch.tensor(config.aabb_lo, dtype=torch.float32))
        self.register_buffer("hi", torch.tensor(config.aabb_hi, dtype=torch.float32))
        self.encoding = make_encoding(config.encoding, config.resolutions, config.features, config.log2_table)
        h = config.hidden
        self.geo_mlp = nn.Sequential(nn.Linear(self.encoding.out_dim, h), nn.ReLU(),
                                     nn.Linear(h, 1 + config.geo_features))
        self.appearance = nn.Embedding(max(1, config.n_images), config.appearance_dim)
        nn.init.zeros_(self.appearance.weight)
        in_c = config.geo_features + config.appearance_dim + (9 if config.view_dependent else 0)
        self.color_mlp = nn.Sequential(nn.Linear(in_c, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(),
                                       nn.Linear(h, 3))
        if config.mask_encoding == "grid":
            self.mask_grid = make_encoding("hash", config.mask_resolutions, config.mask_features,
                                           config.mask_log2_table)
            mask_in = self.mask_grid.out_dim
        elif config.mask_encoding == "geometry":
            self.mask_grid = None
            mask_in = config.geo_features
        else:
            raise ValueError(f"unknown mask_encoding {config.mask_encoding!r}; expected 'grid' or 'geometry'")
        self.mask_head = nn.Sequential(nn.Linear(mask_in, 32), nn.ReLU(), nn.Linear(32, config.n_classes + 1))
        if config.mask_init_background is not None:
            init_background_bias(self.mask_head[-1], config.mask_init_background)
        log_fp = cell_m = None
        if config.footprint_cells is not None:
            if config.encoding != "hash":
                raise ValueError("footprint_cells damps hash-grid levels: it needs encoding='hash'")
            cx, cy = config.footprint_cells
            ext = [h - lo for lo, h in zip(config.aabb_lo, config.aabb_hi, strict=True)]
            # a level's horizontal cell: geometric mean of its x and y cell sizes, metres
            cell = [math.sqrt(ext[0] / r[0] * ext[1] / r[1]) for r in config.resolutions]
            log_fp, cell_m = torch.zeros(cy, cx), torch.tensor(cell, dtype=torch.float32)
        self.register_buffer("log_footprint", log_fp)  # None (off) is not stored in the checkpoint
        self.register_buffer("level_cell_m", cell_m, persistent=False)

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        """World ENU metres -> [0, 1]^3 of the scene box (not clamped)."""
        return (points - self.lo) / (self.hi - self.lo)

    def set_footprint(self, footprint_m) -> None:
        """Store the finest training footprint (cy, cx) metres over the box's xy
        (:func:`fields.footprint.footprint_map`); needs ``FieldConfig.footprint_cells``."""
        if self.log_footprint is None:
            raise ValueError("this field has no footprint map (FieldConfig.footprint_cells is None)")
        fp = torch.as_tensor(np.asarray(footprint_m), dtype=torch.float32)
        if fp.shape != self.log_footprint.shape or not torch.isfinite(fp).all() or (fp <= 0).any():
            raise ValueError(f"footprint map must be {tuple(self.log_footprint.shape)}, finite and > 0")
        self.log_footprint.copy_(fp.log())

    def encode(self, x01: torch.Tensor) -> torch.Tensor:
        """Geometry features of the encoding at box-normalised points (N, 3), each hash level damped
        where the data was coarser than its cells when the field has a footprint map."""
        feats = self.encoding(x01)
        if self.log_footprint is None:
            return feats
        w = level_weights(x01[:, :2], self.log_footprint, self.level_cell_m)  # (N, L)
        n, n_levels = w.shape
        return (feats.view(n, n_levels, -1) * w[:, :, None].to(feats.dtype)).view(n, -1)

    def geometry(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density (N,) in 1/m (0 outside the box) and geometry features (N, G)."""
        x01 = self.normalise(points)
        inside = ((x01 >= 0) & (x01 <= 1)).all(dim=-1)
        h = self.geo_mlp(self.encode(x01)).float()
        sigma = trunc_exp(h[:, 0] + self.config.density_bias) * inside
        return sigma, h[:, 1:]

    def density(self, points: torch.Tensor) -> torch.Tensor:
        return self.geometry(points)[0]

    def appearance_code(self, image_idx: torch.Tensor | None, n: int) -> torch.Tensor:
        """Per-image embedding; ``None`` (novel views) -> the mean over the training images."""
        if image_idx is None:
            return self.appearance.weight.mean(0, keepdim=True).expand(n, -1)
        return self.appearance(image_idx)

    def color(self, geo: torch.Tensor, dirs=None, image_idx=None) -> torch.Tensor:
        """RGB (N, 3) in [0, 1] from geometry features (N, G), directions and image indices."""
        parts = [geo, self.appearance_code(image_idx, geo.shape[0])]
        if self.config.view_dependent:
            if dirs is None:
                raise ValueError("this field is view dependent: pass ray directions")
            parts.append(sh_encoding_deg2(dirs))
        return torch.sigmoid(self.color_mlp(torch.cat(parts, dim=-1)).float())

    def mask_logits(self, points: torch.Tensor, geo: torch.Tensor) -> torch.Tensor:
        """Class logits (N, C+1) at world points; ``geo`` their geometry features (used detached)."""
        if self.mask_grid is not None:
            return self.mask_head(self.mask_grid(self.normalise(points))).float()
        # detached: the head reads the geometry features but its loss cannot change them
        # (measured: through the shared features the mask loss stalled RGB at 16.7 dB vs 28.1 dB)
        return self.mask_head(geo.detach()).float()

    def forward(self, points, dirs=None, image_idx=None, with_mask: bool = True) -> dict:
        """``points`` (N, 3), ``dirs`` (N, 3) unit or None, ``image_idx`` (N,) long or None."""
        sigma, geo = self.geometry(points)
        out = {"sigma": sigma, "rgb": self.color(geo, dirs, image_idx)}
        if with_mask:
            out["mask_logits"] = self.mask_logits(points, geo)
        return out


class Background(nn.Module):
    """Cheap colour for what lies beyond the scene box (no density, no floaters).

    Rays pointing below the horizon hit the ground plane ``z = ground_z``; their ground point is
    contracted (mip-NeRF 360 style, ``xy / r`` scaled to ``2 - 1/|u|`` beyond ``radius_m``, ``xy`` ENU
    metres about the world origin) and looked up in an RGB texture. Rays at or above the horizon get
    a learned sky colour.

    ``mip=True`` makes the lookup footprint-aware (a learned mip map): the texture's colours are
    average-pooled into a pyramid, and each ray reads the level whose texel matches its pixel's
    footprint on the ground (the longer axis of the footprint ellipse, foreshortened by the grazing
    angle and scaled by the contraction), blending the two nearest levels. A grazing training ray
    then teaches the area average it saw to a coarse level, shared by all the fine texels under it,
    instead of one fine texel that a steeper view would read out of context. Without ``pixel_rad``
    (radians per pixel) in :meth:`forward` the finest level is read.
    """

    def __init__(self, ground_z: float, radius_m: float, resolution: int = 64, mip: bool = False):
        super().__init__()
        self.ground_z = float(ground_z)
        self.radius_m = float(radius_m)
        self.mip = bool(mip)
        if mip and (resolution < 8 or resolution & (resolution - 1)):
            raise ValueError(f"a mip-mapped background needs a power-of-two resolution >= 8, got {resolution}")
        self.texture = nn.Parameter(torch.zeros(1, 3, resolution, resolution))
        self.sky = nn.Parameter(torch.zeros(3))

    def _ground(self, origins: torch.Tensor, dirs: torch.Tensor):
        """Per ray: below the horizon (bool), distance to the ground (m along the unit ray, 0 if not
        down), ground point xy (ENU m) and its contracted texture coordinate in [-1, 1]^2."""
        dz = dirs[:, 2]
        down = dz < -1e-6
        t = torch.where(down, (self.ground_z - origins[:, 2]) / torch.where(down, dz, -torch.ones_like(dz)),
                        torch.zeros_like(dz)).clamp_min(0.0)
        xy = origins[:, :2] + t[:, None] * dirs[:, :2]
        u = xy / self.radius_m
        r = u.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        g = torch.where(r <= 1, u, (2 - 1 / r) * u / r) / 2  # |g| < 1 after contraction
        return down, t, xy, g

    def level_of_detail(self, origins: torch.Tensor, dirs: torch.Tensor, pixel_rad: float) -> torch.Tensor:
        """Per ray, the (fractional) pyramid level whose texel spans the longer axis of the pixel's
        ground footprint: 0 = the full-resolution texture, each level up halves the resolution."""
        down, t, xy, _ = self._ground(origins, dirs)
        short = t * float(pixel_rad)  # across the ray, metres
        long = short / dirs[:, 2].abs().clamp_min(0.05)  # along the ray's ground track, foreshortened
        r = (xy.norm(dim=-1) / self.radius_m).clamp_min(1e-9)
        beyond = r > 1
        # texture units (the full [-1, 1] span = 2) per metre, radially and tangentially
        s_r = torch.where(beyond, 1 / (2 * r * r), torch.full_like(r, 0.5)) / self.radius_m
        s_t = torch.where(beyond, (2 - 1 / r) / (2 * r), torch.full_like(r, 0.5)) / self.radius_m
        track = dirs[:, :2] / dirs[:, :2].norm(dim=-1, keepdim=True).clamp_min(1e-9)
        radial = xy / xy.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        cos = (track * radial).sum(-1).abs().clamp(max=1.0)
        sin = (1 - cos * cos).clamp_min(0.0).sqrt()
        long_tex = long * torch.sqrt((cos * s_r) ** 2 + (sin * s_t) ** 2)
        short_tex = short * torch.sqrt((sin * s_r) ** 2 + (cos * s_t) ** 2)
        texel = 2.0 / self.texture.shape[-1]
        lod = torch.log2(torch.maximum(long_tex, short_tex).clamp_min(1e-12) / texel)
        levels = int(math.log2(self.texture.shape[-1])) - 2  # down to 4 x 4 texels
        return torch.where(down, lod.clamp(0.0, float(levels)), torch.zeros_like(lod))

    def forward(self, origins: torch.Tensor, dirs: torch.Tensor, pixel_rad: float | None = None) -> torch.Tensor:
        """RGB (R, 3) in [0, 1] of R rays (world ENU origins and unit directions) that leave the
        box; ``pixel_rad``: the camera's radians per pixel (used only by a mip-mapped texture)."""
        down, _, _, g = self._ground(origins, dirs)
        grid = g.view(1, -1, 1, 2)
        if not self.mip:
            tex = nn.functional.grid_sample(self.texture, grid, align_corners=False,
                                            padding_mode="border").view(3, -1).t()
            colour = torch.sigmoid(tex)
        else:
            level = torch.sigmoid(self.texture)
            if pixel_rad is None:
                colour = nn.functional.grid_sample(level, grid, align_corners=False,
                                                   padding_mode="border").view(3, -1).t()
            else:
                lod = self.level_of_detail(origins, dirs, pixel_rad)
                reads = []
                for k in range(int(lod.max().ceil().item()) + 1):
                    if k:
                        level = nn.functional.avg_pool2d(level, 2)
                    reads.append(nn.functional.grid_sample(level, grid, align_corners=False,
                                                           padding_mode="border").view(3, -1).t())
                reads = torch.stack(reads)  # (K, R, 3)
                i0 = lod.floor().long().clamp(max=reads.shape[0] - 1)
                i1 = (i0 + 1).clamp(max=reads.shape[0] - 1)
                w = (lod - i0.to(lod.dtype))[:, None]
                rows = torch.arange(lod.shape[0], device=lod.device)
                colour = reads[i0, rows] * (1 - w) + reads[i1, rows] * w
        return torch.where(down[:, None], colour, torch.sigmoid(self.sky).expand_as(colour))
