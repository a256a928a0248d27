"""The dynamic model: a K-Planes field (stock or extended) + background + sampler, rendered along rays.

Like :class:`fields.model.StaticModel` but every ray carries a normalised scene time ``t01``
(:mod:`fields.dynamic_data`). Rays are world ENU metres with unit directions. Sampling: the shared
:class:`fields.samplers.StratifiedSampler` inside the ground slab (jittered in training); the
occupancy-grid sampler is not used here because its grid would have to change with time. The
slab floor is opaque and the shared :class:`fields.field.Background` colours what lies outside,
exactly as for the static model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from fields.field import Background
from fields.kplanes import KPlanesConfig, KPlanesField, KPlanesFieldConfig
from fields.model import SamplerConfig, make_sampler
from fields.pose_drift import PoseDrift
from fields.rendering import composite, distortion_loss, expected_depth, opacity, weights_from_density
from fields.samplers import sample_points

KINDS = ("kplanes", "kplanes-ext")


@dataclass
class PlaneSizing:
    base_resolution: tuple[int, int, int]
    multipliers: tuple[int, ...]
    finest_cell_m: float
    reasoning: list[str]


def plane_sizing(extent_m, finest_gsd_m: float, max_resolution: int = 256, cell_factor: float = 1.0,
                 multipliers: tuple[int, ...] = (1, 2, 4)) -> PlaneSizing:
    """Spatial plane resolutions: the finest scale's cell = the data's finest GSD x ``cell_factor``,
    no finer than ``longest side / max_resolution``; the base scale is ``max(multipliers)`` coarser.
    (Paper: base (128, 128, 64), multipliers 1, 2, 4 on a GPU; z is short for a ground slab anyway.)"""
    ext = np.asarray(extent_m, dtype=np.float64)
    if not (np.isfinite(ext).all() and (ext > 0).all()):
        raise ValueError(f"scene extent must be finite and positive, got {ext}")
    top = max(multipliers)
    cell = max(finest_gsd_m * cell_factor, float(ext.max()) / max_resolution, 1e-3)
    base = tuple(int(max(2, math.ceil(e / (cell * top)))) for e in ext)
    why = [f"extent {ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} m; finest cell {cell * 100:.1f} cm "
           f"(data GSD {finest_gsd_m * 100:.1f} cm x {cell_factor:g}, cap {max_resolution} per side)",
           f"base resolution {base}, multipliers {tuple(multipliers)}"]
    return PlaneSizing(base, tuple(multipliers), cell, why)


class DynamicModel(nn.Module):
    """K-Planes field, background and sampler; :meth:`render_rays` is the rendering entry point."""

    def __init__(self, kind: str, field_config: KPlanesFieldConfig, sampler_config: SamplerConfig, ground_z: float,
                 background_radius_m: float, t0_us: int = 0, span_us: int = 0, pose_knots: int = 0,
                 pose_coarse_knots: Sequence[int] = (), pose_frame_t01: Sequence[float] = ()):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"unknown dynamic kind {kind!r}; expected one of {KINDS}")
        if sampler_config.kind != "stratified":
            raise ValueError("the dynamic model samples rays with the stratified sampler only")
        if field_config.planes.extended != (kind == "kplanes-ext"):
            raise ValueError(f"kind {kind!r} does not match planes.extended={field_config.planes.extended}")
        self.kind = kind
        self.field_config, self.sampler_config = field_config, sampler_config
        self.t0_us, self.span_us = int(t0_us), int(span_us)
        self.field = KPlanesField(field_config)
        self.background = Background(ground_z, background_radius_m)
        self.sampler = make_sampler(sampler_config)
        #: learned time-smooth correction of the telemetry poses, with per-frame rows for the frames at
        #: ``pose_frame_t01`` if given (None: poses taken as given)
        self.pose_drift = PoseDrift(pose_knots, pose_coarse_knots, pose_frame_t01) if pose_knots else None

    @property
    def extended(self) -> bool:
        return self.field_config.planes.extended

    # ---- checkpoint ---------------------------------------------------------------------
    def describe(self) -> dict:
        drift = self.pose_drift
        return {"kind": self.kind, "field": self.field_config.to_json(),
                "sampler": {**asdict(self.sampler_config), "grid_shape": list(self.sampler_config.grid_shape)},
                "ground_z": self.background.ground_z, "background_radius_m": self.background.radius_m,
                "t0_us": self.t0_us, "span_us": self.span_us,
                "pose_knots": drift.knots if drift is not None else 0,
                "pose_coarse_knots": drift.coarse_knots if drift is not None else [],
                "pose_frame_t01": drift.frame_t01.tolist() if drift is not None and drift.frames else []}

    @classmethod
    def from_description(cls, d: dict) -> DynamicModel:
        s = dict(d["sampler"])
        s["grid_shape"] = tuple(s["grid_shape"])
        return cls(d["kind"], KPlanesFieldConfig.from_json(d["field"]), SamplerConfig(**s), d["ground_z"],
                   d["background_radius_m"], d.get("t0_us", 0), d.get("span_us", 0), d.get("pose_knots", 0),
                   d.get("pose_coarse_knots", ()), d.get("pose_frame_t01", ()))

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def field_pose(self, cam_from_world: np.ndarray, time01: float) -> np.ndarray:
        """The pose in the field's world of a *recorded* frame whose telemetry pose (OpenCV
        ``cam_from_world``) was taken at ``time01``: the learned drift correction applied, if any (with
        the frame's own per-frame row when ``time01`` is a recorded frame's time).
        Novel poses built around the scene are already in the field's world; do not pass them here."""
        if self.pose_drift is None:
            return np.asarray(cam_from_world, dtype=np.float64)
        return self.pose_drift.correct_cam_from_world(cam_from_world, time01)

    def time01(self, t_unix_us: int | None) -> float:
        """Normalised scene time of a capture time (None: the flight's first frame)."""
        if t_unix_us is None or self.span_us <= 0:
            return 0.0
        return float(min(max((int(t_unix_us) - self.t0_us) / self.span_us, 0.0), 1.0))

    # ---- rendering ----------------------------------------------------------------------
    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, times01: torch.Tensor,
                    image_idx: torch.Tensor | None = None, train: bool = False, with_mask: bool = True,
                    dynamic_gate: torch.Tensor | None = None, with_features: bool = False,
                    feature_points: int | None = None, generator=None, jitter_rows=None) -> dict:
        """Render R rays at times ``times01`` (R,): ``rgb`` (R,3), ``acc``, ``depth`` (R,1),
        ``weights`` (R,S), ``t_norm`` (R,S+1), ``mask_probs`` (R,C+1) with ``with_mask``; extended
        models add ``dynamic_prob`` (R,) (weight-composited mask channel, weights detached) and with
        ``with_features`` the per-sample plane features for ``L_cos`` (of the first ``feature_points``
        samples, in ray order; None: all). ``dynamic_gate`` (R,) in [0, 1]: 1 = the ray's pixel lies
        inside a person box (extended models only). ``jitter_rows`` (R,): see
        :meth:`fields.samplers.StratifiedSampler.edges`."""
        f = self.field
        edges = self.sampler.edges(origins, dirs, f.lo, f.hi, train=train, generator=generator,
                                   jitter_rows=jitter_rows)
        r, s1 = edges.shape
        s = s1 - 1
        mid, deltas, pts = sample_points(origins, dirs, edges)
        t_rep = times01.reshape(-1, 1).expand(r, s).reshape(-1)
        i_rep = None if image_idx is None else image_idx[:, None].expand(r, s).reshape(-1)
        g_rep = None
        if dynamic_gate is not None and self.extended:
            g_rep = dynamic_gate.reshape(-1, 1).float().expand(r, s).reshape(-1)
        out = f(pts, t_rep, None, i_rep, dynamic_gate=g_rep, with_mask=with_mask,
                space_points=feature_points if with_features else 0)
        sigma = out["sigma"].view(r, s)
        if self.sampler_config.opaque_floor:
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
            res["mask_probs"] = composite(w.detach(), probs, bg_class)
        if self.extended:
            # what the rays see is dynamic where the surfaces they stop at are (the air is not)
            res["dynamic_prob"] = (w.detach() * out["dynamic_prob"].view(r, s)).sum(-1).clamp(0.0, 1.0)
            if with_features:
                res["static_space"] = out["static_space"]
                res["dynamic_space"] = out["dynamic_space"]
        return res

    def distortion(self, res: dict) -> torch.Tensor:
        return distortion_loss(res["weights"], res["t_norm"]).mean()

    @torch.no_grad()
    def render_image(self, camera, cam_from_world: np.ndarray, time01: float, chunk: int = 8192,
                     with_mask: bool = True) -> dict:
        """A full frame at scene time ``time01``: ``rgb`` (H,W,3) in [0,1], ``mask`` (H,W) class ids,
        ``mask_probs`` (H,W,C+1) class probabilities (channel 0 background), ``acc``, ``depth`` (H,W);
        extended models also ``dynamic`` (H,W) probability. Mean appearance."""
        dev = self.field.lo.device
        uv = camera.pixel_grid().reshape(-1, 2)
        o, d = camera.rays_world(np.asarray(cam_from_world, np.float64), uv)
        o = torch.from_numpy(np.broadcast_to(o, d.shape).copy()).float().to(dev)
        d = torch.from_numpy(d).float().to(dev)
        outs: dict[str, list] = {"rgb": [], "acc": [], "depth": [], "mask": [], "mask_probs": [], "dynamic": []}
        for a in range(0, d.shape[0], chunk):
            n = min(chunk, d.shape[0] - a)
            t = torch.full((n,), float(time01), device=dev)
            res = self.render_rays(o[a:a + n], d[a:a + n], t, train=False, with_mask=with_mask)
            outs["rgb"].append(res["rgb"])
            outs["acc"].append(res["acc"][:, 0])
            outs["depth"].append(res["depth"][:, 0])
            if with_mask:
                outs["mask"].append(res["mask_probs"].argmax(-1))
                outs["mask_probs"].append(res["mask_probs"])
            if "dynamic_prob" in res:
                outs["dynamic"].append(res["dynamic_prob"])
        h, w = camera.height, camera.width
        return {k: torch.cat(v).view(h, w, -1 if k in ("rgb", "mask_probs") else 1).squeeze(-1).cpu().numpy()
                for k, v in outs.items() if v}


def make_field_config(kind: str, bounds, sizing: PlaneSizing, n_frames: int, n_images: int, n_classes: int,
                      features: int = 16, hidden: int = 64, appearance_dim: int = 8,
                      mask_init_background: float | None = None, mask_encoding: str = "geometry",
                      time_gate: bool = False, dynamic_z_top: float = 1.0,
                      init_optical_depth: float | None = None) -> KPlanesFieldConfig:
    """Field config for ``kind`` over the slab ``bounds``; time resolution = half the frames;
    ``time_gate``, ``dynamic_z_top``: see :class:`fields.kplanes.KPlanesConfig` (extended only).
    ``init_optical_depth``: the fresh field's optical depth along a vertical ray through the whole box
    (:func:`density_bias_for`); None: the field's default density bias."""
    from fields.dynamic_data import time_resolution

    planes = KPlanesConfig(base_resolution=sizing.base_resolution, multipliers=sizing.multipliers,
                           time_resolution=time_resolution(n_frames), features=features,
                           extended=(kind == "kplanes-ext"), time_gate=time_gate and kind == "kplanes-ext",
                           dynamic_z_top=dynamic_z_top if kind == "kplanes-ext" else 1.0)
    bias = (KPlanesFieldConfig.density_bias if init_optical_depth is None
            else density_bias_for(init_optical_depth, bounds.lo[2], bounds.hi[2]))
    return KPlanesFieldConfig(aabb_lo=tuple(bounds.lo), aabb_hi=tuple(bounds.hi), planes=planes, hidden=hidden,
                              n_images=n_images, appearance_dim=appearance_dim, n_classes=n_classes,
                              mask_init_background=mask_init_background, mask_encoding=mask_encoding,
                              density_bias=bias)


def density_bias_for(optical_depth: float, lo_z: float, hi_z: float) -> float:
    """The density bias (added to the density MLP's log-density output) that gives a fresh field, whose
    output is near 0, about ``optical_depth`` along a vertical ray from the box top ``hi_z`` to its
    floor ``lo_z`` (world ENU, m): ``log(optical_depth / height)``, density in 1/m. A small value starts
    the field transparent, so rays reach the ground from the first step."""
    height = float(hi_z) - float(lo_z)
    if not (optical_depth > 0 and math.isfinite(optical_depth)):
        raise ValueError(f"the initial optical depth must be positive and finite, got {optical_depth}")
    if not (height > 0 and math.isfinite(height)):
        raise ValueError(f"the box must have a positive, finite height, got {lo_z}..{hi_z} m")
    return math.log(optical_depth / height)
