"""K-Planes for dynamic scenes: stock (six planes) and the paper's extended variant.

Coordinates: points are normalised to the scene box, ``x01`` in [0, 1]^3, and time to ``t01`` in
[0, 1] over the flight. A plane (a, b) is a learnable grid of features over two of the four
coordinates (x, y, z, t); a point reads it by bilinear interpolation (``F.grid_sample``,
``align_corners=True``: grid point 0 at coordinate 0 and point R - 1 at coordinate 1).

Stock K-Planes (Fridovich-Keil et al.): six planes xy, xz, yz, xt, yt, zt per scale; a point's
feature is the Hadamard product over the six planes, concatenated over scales. Time planes start
at 1 (a static scene needs no change over time), spatial planes uniform in [0.1, 0.5].

Extended K-Planes (UAV-Sim): per scale three *static* spatial planes ``C_s`` and six *dynamic*
planes ``C_d``, multiplied separately into ``f_s`` and ``f_d``; each dynamic time plane stores
D + 1 channels, the extra one a mask value (is this point part of a moving object now?). An MLP
fuses ``f_s``, ``f_d`` and the three mask values into a D-dim feature. Training adds
``L_cos = sum_c |cos(f_s,c, f_d,c)|`` over the spatial planes c (keeps the two sets of planes
apart) and gates gradients by the box mask: pixels on static background update only the static
planes, pixels inside the boxes of moving people only the dynamic planes (:class:`GateGrad`).

The time gate (``KPlanesConfig.time_gate``; ours, not the paper's; the fit's default on SfM-refined
poses): the time planes act on ``f_d`` only as far as the mask value says the point is dynamic. A time
plane is shared along a line (zt: every point at one height), so without the gate every person's rays at instant t
changed ``f_d`` at background points too, a per-instant pattern the fusion MLP learned to fit the
training frames with and that the held-out instants in between did not share.

The dynamic layer (``KPlanesConfig.dynamic_z_top``; ours): people walk on the ground, so the extended
variant's dynamic planes may span only the lowest part of the box, with as many z grid points as that part
needs; above it a point is static (``f_d`` = 0, its mask values "static").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from fields.field import init_background_bias

#: coordinate index pairs of the spatial planes (x=0, y=1, z=2) and the time planes (t=3)
SPACE_PLANES = ((0, 1), (0, 2), (1, 2))
TIME_PLANES = ((0, 3), (1, 3), (2, 3))


class GateGrad(torch.autograd.Function):
    """Identity forward; backward multiplies the incoming gradient by ``gate`` (broadcast).

    ``gate`` is 1 where gradients may flow and 0 where they are blocked (values in between scale
    them). It receives no gradient itself.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(gate)
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (gate,) = ctx.saved_tensors
        return grad * gate.to(grad.dtype), None


def gate_grad(x: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
    """Pass ``x`` unchanged; let only ``gate``-weighted gradients back (see :class:`GateGrad`)."""
    return GateGrad.apply(x, gate)


def cosine_separation(f_static: list[torch.Tensor], f_dynamic: list[torch.Tensor],
                      eps: float = 1e-8) -> torch.Tensor:
    """``L_cos``: sum over planes c of the mean over points of ``|cos(f_s,c, f_d,c)|``.

    Each list holds one (N, D) tensor per spatial plane (static and dynamic, same order).
    """
    if len(f_static) != len(f_dynamic):
        raise ValueError("static and dynamic feature lists must pair up plane by plane")
    total = torch.zeros((), dtype=torch.float32, device=f_static[0].device if f_static else None)
    for a, b in zip(f_static, f_dynamic, strict=True):
        # work on (D, N): the encoding's features are transposed views of contiguous (D, N)
        # tensors, and norms over a strided last dim were 15 % of a training step
        a, b = a.float().t(), b.float().t()
        dot = (a * b).sum(0)
        na = a.pow(2).sum(0).sqrt().clamp_min(eps)
        nb = b.pow(2).sum(0).sqrt().clamp_min(eps)
        total = total + (dot / (na * nb)).abs().mean()
    return total


def _time_gate_prob(masks: list[torch.Tensor]) -> torch.Tensor:
    """The dynamic probability (1, N), detached, from the time planes' mask channels (each (1, N)):
    sigmoid of their mean, as :class:`KPlanesField` reports ``dynamic_prob``."""
    return torch.sigmoid(torch.cat(masks, dim=0).mean(dim=0, keepdim=True)).detach()


def _dynamic_features(dyn: torch.Tensor, times: torch.Tensor | None, p: torch.Tensor | None) -> torch.Tensor:
    """``f_d`` of one scale: ``dyn`` already holds the whole product without the time gate
    (``times`` None); with it, ``dyn`` is ``S_d`` and ``times`` is ``T_d``: ``S_d * (1 + p * (T_d - 1))``."""
    return dyn if times is None else dyn * (1.0 + p * (times - 1.0))


def _spread(x: torch.Tensor | None, keep: torch.Tensor | None, width: int) -> torch.Tensor | None:
    """Columns ``x`` (C, K) read at the columns ``keep`` (K,) of a run ``width`` wide, as (C, width) with
    zeros elsewhere (differentiable in ``x``); ``keep`` None: ``x`` is the whole run already."""
    if x is None or keep is None:
        return x
    return x.new_zeros(x.shape[0], width).index_copy(1, keep, x)


def coarse_to_fine_weights(n_scales: int, progress: float, until: float) -> torch.Tensor:
    """Per-scale feature weights (n_scales,) at ``progress`` in [0, 1] of training, as BARF fades in
    positional-encoding bands: the coarsest scale always 1; scale ``s >= 1`` rises from 0 to 1 along
    ``(1 - cos(pi * clamp(b - s + 1, 0, 1))) / 2`` with ``b = (n_scales - 1) * progress / until``, so the
    finest scale is at full weight from ``progress = until`` on. ``until <= 0``: all ones (off).

    While a finer scale is faded out it receives (almost) no colour gradient: the field and the learned
    pose corrections first agree on the coarse scene, where a few decimetres of pose error are a fraction
    of a cell, before the fine planes can fit each frame's misregistration.
    """
    if until <= 0 or n_scales <= 1:
        return torch.ones(max(n_scales, 0))
    b = (n_scales - 1) * min(max(progress, 0.0), 1.0) / until
    s = torch.arange(n_scales, dtype=torch.float32)
    ramp = (b - s + 1.0).clamp(0.0, 1.0)
    w = 0.5 * (1.0 - torch.cos(torch.pi * ramp))
    w[0] = 1.0
    return w


def sample_plane_cn(plane: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear features (C, N), contiguous, of ``plane`` (1, C, Rv, Ru) at ``u, v`` in [0, 1].

    Channel-first is what ``grid_sample`` produces; products of such tensors stay contiguous (the
    (N, C) transpose made every Hadamard product a strided copy, ~2x slower on CPU)."""
    grid = torch.stack([u * 2 - 1, v * 2 - 1], dim=-1).view(1, -1, 1, 2).to(plane.dtype)
    return F.grid_sample(plane, grid, mode="bilinear", align_corners=True).view(plane.shape[1], grid.shape[1])


def sample_plane(plane: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear features (N, C) of ``plane`` (1, C, Rv, Ru) at coordinates ``u, v`` in [0, 1]."""
    return sample_plane_cn(plane, u, v).t()


def sample_plane_reference(plane: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Slow, explicit bilinear interpolation; the reference :func:`sample_plane` is tested against."""
    _, c, rv, ru = plane.shape
    x = u.clamp(0, 1) * (ru - 1)
    y = v.clamp(0, 1) * (rv - 1)
    x0 = x.floor().long().clamp(0, max(ru - 2, 0))
    y0 = y.floor().long().clamp(0, max(rv - 2, 0))
    x1 = (x0 + 1).clamp(max=ru - 1)
    y1 = (y0 + 1).clamp(max=rv - 1)
    fx, fy = (x - x0).unsqueeze(1), (y - y0).unsqueeze(1)
    p = plane[0]
    return (p[:, y0, x0].t() * (1 - fx) * (1 - fy) + p[:, y0, x1].t() * fx * (1 - fy)
            + p[:, y1, x0].t() * (1 - fx) * fy + p[:, y1, x1].t() * fx * fy)


@dataclass
class KPlanesConfig:
    """Sizes of a K-Planes encoding. Resolutions are grid points along (x, y, z) per scale."""

    #: spatial base resolution (paper: 128, 128, 64 — z halved, cameras look down) and multipliers
    base_resolution: tuple[int, int, int] = (32, 32, 16)
    multipliers: tuple[int, ...] = (1, 2, 4)
    #: time resolution: half the number of frames (paper)
    time_resolution: int = 16
    features: int = 16
    extended: bool = False
    init_low: float = 0.1
    init_high: float = 0.5
    #: extended only: a point's dynamic time features enter ``f_d`` in proportion to its dynamic
    #: probability ``p`` (sigmoid of the mean mask channel, detached):
    #: ``f_d = S_d * (1 + p * (T_d - 1))`` with ``S_d``, ``T_d`` the products of the dynamic spatial and
    #: time planes. Where nobody walks (p -> 0) ``f_d`` is the time-invariant ``S_d``, not a pattern that
    #: a time plane, shared along a line, picks up from every person's rays at that instant.
    time_gate: bool = False
    #: extended only: the dynamic planes span the normalised heights [0, ``dynamic_z_top``] of the box, the
    #: layer people walk in, with their z resolution cut to match (cells as tall as the static planes').
    #: Above it a point is static: ``f_d`` = 0, mask values "static" (logit :data:`STATIC_LOGIT`), no
    #: gradient to the dynamic planes from it (``L_cos`` still reads their top row there). 1: the whole box
    dynamic_z_top: float = 1.0

    def resolutions(self) -> list[tuple[int, int, int]]:
        return [tuple(int(r * m) for r in self.base_resolution) for m in self.multipliers]

    def dynamic_resolutions(self) -> list[tuple[int, int, int]]:
        """Grid points along (x, y, z) of the dynamic planes per scale: z over the dynamic layer only."""
        zt = self.layer_top()
        return [(rx, ry, rz if zt >= 1.0 else max(2, math.ceil(rz * zt))) for rx, ry, rz in self.resolutions()]

    def layer_top(self) -> float:
        """``dynamic_z_top`` checked: in (0, 1]; stock K-Planes always 1 (one set of planes for everything)."""
        zt = float(self.dynamic_z_top)
        if not (0.0 < zt <= 1.0):
            raise ValueError(f"dynamic_z_top must be in (0, 1], got {zt}")
        return zt if self.extended else 1.0

    def to_json(self) -> dict:
        return asdict(self)


#: the mask logit a point above the dynamic layer reports: sigmoid(-30) ~ 1e-13, static
STATIC_LOGIT = -30.0


def _plane(channels: int, rv: int, ru: int, value: float | None, low: float, high: float) -> nn.Parameter:
    p = torch.empty(1, channels, rv, ru)
    if value is None:
        p.uniform_(low, high)
    else:
        p.fill_(value)
    return nn.Parameter(p)


class KPlanesEncoding(nn.Module):
    """Stock or extended K-Planes features of (x01, t01); see the module docstring.

    ``forward`` returns a dict: ``features`` (N, out_dim) always; for the extended variant also
    ``mask_values`` (N, 3 * scales) raw mask channels of the time planes, and the per-plane
    spatial features ``static_space``/``dynamic_space`` (lists of (N, D)) for ``L_cos``.
    With ``dynamic_gate`` (N,) in [0, 1] (1 = pixel inside a moving person's box) gradients of
    static planes are scaled by ``1 - gate`` and of dynamic planes by ``gate``.
    """

    def __init__(self, config: KPlanesConfig):
        super().__init__()
        self.config = config
        d, lo, hi = config.features, config.init_low, config.init_high
        T = config.time_resolution
        self.static_planes = nn.ParameterList()
        self.dynamic_planes = nn.ParameterList()
        for res, dres in zip(config.resolutions(), config.dynamic_resolutions(), strict=True):
            if config.extended:
                for a, b in SPACE_PLANES:
                    self.static_planes.append(_plane(d, res[b], res[a], None, lo, hi))
            for a, b in SPACE_PLANES:
                self.dynamic_planes.append(_plane(d, dres[b], dres[a], None, lo, hi))
            extra = 1 if config.extended else 0
            for a, _ in TIME_PLANES:
                p = _plane(d + extra, T, dres[a], 1.0, lo, hi)
                if extra:
                    with torch.no_grad():
                        p[:, d:] = 0.0  # mask logit 0 = undecided
                self.dynamic_planes.append(p)

        # coarse-to-fine (:func:`coarse_to_fine_weights`): each scale's colour features are multiplied by
        # its weight; all ones (the default, and after training) leave the encoding as it is
        self.register_buffer("scale_weights", torch.ones(len(config.multipliers)), persistent=False)
        self._every_scale_full = True  # kept beside the buffer so the common case costs no device sync

    def set_scale_weights(self, weights: torch.Tensor) -> None:
        """Set the per-scale weights (n_scales,), e.g. from :func:`coarse_to_fine_weights`; all ones: off."""
        weights = torch.as_tensor(weights, dtype=torch.float32).cpu()
        self._every_scale_full = bool((weights == 1).all())
        self.scale_weights.copy_(weights)

    @property
    def n_scales(self) -> int:
        return len(self.config.multipliers)

    def _weighted(self, out: dict) -> dict:
        """``out`` with each scale's feature columns times its ``scale_weights`` (mask columns as they are)."""
        if self._every_scale_full:
            return out
        per_scale = self.config.features * (2 if self.config.extended else 1)
        w = self.scale_weights.repeat_interleave(per_scale)
        n_mask = out["features"].shape[1] - w.numel()
        w = torch.cat([w, w.new_ones(n_mask)]).to(out["features"].dtype)
        return {**out, "features": out["features"] * w}

    @property
    def out_dim(self) -> int:
        per_scale = self.config.features * (2 if self.config.extended else 1)
        return per_scale * self.n_scales + (3 * self.n_scales if self.config.extended else 0)

    def space_planes(self) -> list[nn.Parameter]:
        """All spatial planes (static and dynamic) — for total variation."""
        out = list(self.static_planes)
        for s in range(self.n_scales):
            out += list(self.dynamic_planes[6 * s: 6 * s + 3])
        return out

    def time_planes(self) -> list[nn.Parameter]:
        return [self.dynamic_planes[6 * s + 3 + k] for s in range(self.n_scales) for k in range(3)]

    def forward(self, x01: torch.Tensor, t01: torch.Tensor, dynamic_gate: torch.Tensor | None = None,
                space_points: int | None = None) -> dict:
        """Features of points ``x01`` (N, 3) at times ``t01`` (N,); see the class docstring.

        ``space_points``: return ``static_space``/``dynamic_space`` for the first this-many points only
        (None: all), the ones ``L_cos`` reads. With a hard 0/1 ``dynamic_gate`` under autograd, each
        plane is sampled with gradients only at the points whose gradient the gate lets through
        (:meth:`_forward_split`): the same values and gradients as gating, 5-13 % faster per training
        step (bench/RESULTS.md, Table III session 8).
        """
        x = x01.float().clamp(0.0, 1.0)
        t = t01.float().reshape(-1).clamp(0.0, 1.0)
        coords = torch.cat([x, t[:, None]], dim=-1)
        if (self.split_hard_gate and self.config.extended and dynamic_gate is not None and torch.is_grad_enabled()
                and bool(((dynamic_gate == 0) | (dynamic_gate == 1)).all())):
            return self._weighted(self._forward_split(coords, dynamic_gate.reshape(-1) > 0.5, space_points))
        out = self._forward_gated(coords, dynamic_gate)
        if self.config.extended and space_points is not None:
            out["static_space"] = [f[:space_points] for f in out["static_space"]]
            out["dynamic_space"] = [f[:space_points] for f in out["dynamic_space"]]
        return self._weighted(out)

    #: use :meth:`_forward_split` for hard gates (False: always :meth:`_forward_gated`, the reference)
    split_hard_gate = True

    def _layer(self, coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The coordinates (N, 4) the dynamic planes read (z stretched over the dynamic layer,
        ``KPlanesConfig.dynamic_z_top``) and which points lie in the layer, (1, N) bool; when the layer
        is the whole box: ``coords`` and None."""
        zt = self.config.layer_top()
        if zt >= 1.0:
            return coords, None
        z = coords[:, 2]
        stretched = (z / zt).clamp(max=1.0)
        return torch.cat([coords[:, :2], stretched[:, None], coords[:, 3:]], dim=1), (z <= zt).reshape(1, -1)

    @staticmethod
    def _outside_layer(values: list[torch.Tensor], fusion_inputs: list[torch.Tensor],
                       inside: torch.Tensor | None) -> tuple[list, list]:
        """The time planes' mask channels (each (1, N)) as mask values (above the layer:
        :data:`STATIC_LOGIT`) and as fusion inputs (above the layer: 0)."""
        if inside is None:
            return values, fusion_inputs
        return ([torch.where(inside, m, STATIC_LOGIT) for m in values],
                [torch.where(inside, m, 0.0) for m in fusion_inputs])

    def _forward_gated(self, coords: torch.Tensor, dynamic_gate: torch.Tensor | None) -> dict:
        """Every plane sampled at every point; the gate scales gradients afterwards (:func:`gate_grad`)."""
        x = coords[:, :3]
        d = self.config.features
        dcoords, inside = self._layer(coords)
        # features are (C, N) inside: contiguous products; one transpose at the end
        feats, masks, stat_space, dyn_space = [], [], [], []
        time_gate = self.config.extended and self.config.time_gate
        dyn_parts, stats = [], []  # per scale: (f_d, None), or (S_d, T_d) for the time gate; f_s
        for s in range(self.n_scales):
            dyn = times = None
            for k, (a, b) in enumerate(SPACE_PLANES + TIME_PLANES):
                f = sample_plane_cn(self.dynamic_planes[6 * s + k], dcoords[:, a], dcoords[:, b])
                if k >= 3 and self.config.extended:
                    masks.append(f[d:])
                    f = f[:d]
                if k < 3 and self.config.extended:
                    dyn_space.append(f.t())
                if time_gate and k >= 3:
                    times = f if times is None else times * f
                else:
                    dyn = f if dyn is None else dyn * f
            dyn_parts.append((dyn, times))
            if self.config.extended:
                stat = None
                for k, (a, b) in enumerate(SPACE_PLANES):
                    f = sample_plane_cn(self.static_planes[3 * s + k], coords[:, a], coords[:, b])
                    stat_space.append(f.t())
                    stat = f if stat is None else stat * f
                stats.append(stat)
        masks, layer_masks = self._outside_layer(masks, masks, inside)
        p = _time_gate_prob(masks) if time_gate else None
        dyns = [_dynamic_features(dyn, times, p) for dyn, times in dyn_parts]
        if inside is not None:
            dyns = [torch.where(inside, f, 0.0) for f in dyns]
        if self.config.extended:
            for stat, dyn in zip(stats, dyns, strict=True):
                if dynamic_gate is not None:
                    g = dynamic_gate.reshape(1, -1).to(stat.dtype)
                    stat = gate_grad(stat, 1.0 - g)
                    dyn = gate_grad(dyn, g)
                feats += [stat, dyn]
        else:
            feats = dyns
        mask_feats = layer_masks
        if self.config.extended and dynamic_gate is not None:
            # the mask channel lives on the dynamic time planes: the colour loss of static pixels
            # must not move it either (its own box supervision reads ``mask_values``, ungated)
            g = dynamic_gate.reshape(1, -1).to(x.dtype)
            mask_feats = [gate_grad(m, g) for m in layer_masks]
        out = {"features": torch.cat(feats + mask_feats, dim=0).t()}
        if self.config.extended:
            out["mask_values"] = torch.cat(masks, dim=0).t()
            out["static_space"] = stat_space
            out["dynamic_space"] = dyn_space
        return out

    def _forward_split(self, coords: torch.Tensor, dynamic: torch.Tensor, space_points: int | None) -> dict:
        """Extended K-Planes under a hard gate ``dynamic`` (N,) bool, without sampling for blocked gradients.

        The points fall into three runs: A = the first ``space_points`` points (``L_cos`` needs their
        spatial features with gradients on both sides, so they keep :func:`gate_grad`), B = the other
        static points, C = the other dynamic points. Static planes carry gradients on A and B and are
        read without autograd on C; dynamic planes the other way round, except the time planes' mask
        channel, whose box supervision (``mask_values``) is ungated: it is sampled with gradients on B
        too. A gate of 0 or 1 scales a gradient to zero or leaves it, so values and gradients equal
        :meth:`_forward_gated`'s (up to the order of float sums).

        Points that already come as A, B, C (the trainer orders its rays so with ``gate_ray_runs``)
        are used in place; any other order is permuted into it and the outputs back: a gather of the
        (N, out_dim) features and its backward, without which a training step is 6-11 % faster on CPU
        (bench/RESULTS.md, Table III session 26).

        With a dynamic layer (``KPlanesConfig.dynamic_z_top`` < 1) the dynamic planes are read on B and C
        only inside the layer: above it their values are replaced anyway (:meth:`_outside_layer`, ``f_d`` 0).
        """
        n = coords.shape[0]
        n_a = n if space_points is None else min(int(space_points), n)
        rest = dynamic[n_a:]
        n_c = int(rest.sum())
        n_b = n - n_a - n_c
        inv = None
        cp = coords
        if bool(rest[:n_b].any()):  # not in run order: permute into A, B, C
            idx = torch.arange(n_a, n, device=coords.device)
            perm = torch.cat([torch.arange(n_a, device=coords.device), idx[~rest], idx[rest]])
            cp = coords[perm]
            inv = torch.empty_like(perm)
            inv[perm] = torch.arange(n, device=perm.device)
        end_b = n_a + n_b
        g_a = dynamic[:n_a].to(coords.dtype).reshape(1, -1)
        dcp, inside = self._layer(cp)  # in run order
        stat_rows, stat_blocked = cp[:end_b], cp[end_b:]  # A, B carry the static planes' gradients; C not
        dyn_rows = torch.cat([dcp[:n_a], dcp[end_b:]])  # A, C carry the dynamic planes' gradients
        dyn_blocked = dcp[n_a:end_b]  # B
        n_g = n - n_b
        keep_g = keep_n = None  # with a layer: the columns of (A, C) and of B that read the dynamic planes
        if inside is not None:  # every A point (``L_cos`` reads it), and B and C inside the layer
            keep_g = torch.cat([torch.arange(n_a, device=cp.device), n_a + inside[0, end_b:].nonzero().squeeze(1)])
            keep_n = inside[0, n_a:end_b].nonzero().squeeze(1)
            dyn_rows, dyn_blocked = dyn_rows[keep_g], dyn_blocked[keep_n]
        d = self.config.features
        time_gate = self.config.time_gate
        feats, masks, mask_feats, stat_space, dyn_space = [], [], [], [], []
        stat_parts, dyn_parts = [], []
        for s in range(self.n_scales):
            dyn_g = dyn_n = time_g = time_n = None  # products over the planes on rows A, C (g) and B (n)
            for k, (a, b) in enumerate(SPACE_PLANES + TIME_PLANES):
                plane = self.dynamic_planes[6 * s + k]
                f = sample_plane_cn(plane, dyn_rows[:, a], dyn_rows[:, b])
                with torch.no_grad():
                    f_n = sample_plane_cn(plane, dyn_blocked[:, a], dyn_blocked[:, b])
                if k >= 3:
                    m_b = _spread(sample_plane_cn(plane[:, d:], dyn_blocked[:, a], dyn_blocked[:, b]), keep_n, n_b)
                    m = _spread(f[d:], keep_g, n_g)
                    masks.append(torch.cat([m[:, :n_a], m_b, m[:, n_a:]], dim=1))
                    mask_feats.append(torch.cat([gate_grad(m[:, :n_a], g_a), m_b.detach(), m[:, n_a:]], dim=1))
                    f, f_n = f[:d], f_n[:d]
                else:
                    dyn_space.append(f[:, :n_a].t())
                if time_gate and k >= 3:
                    time_g = f if time_g is None else time_g * f
                    time_n = f_n if time_n is None else time_n * f_n
                else:
                    dyn_g = f if dyn_g is None else dyn_g * f
                    dyn_n = f_n if dyn_n is None else dyn_n * f_n
            dyn_parts.append((_spread(dyn_g, keep_g, n_g), _spread(dyn_n, keep_n, n_b),
                              _spread(time_g, keep_g, n_g), _spread(time_n, keep_n, n_b)))
            stat_g = stat_n = None
            for k, (a, b) in enumerate(SPACE_PLANES):
                plane = self.static_planes[3 * s + k]
                f = sample_plane_cn(plane, stat_rows[:, a], stat_rows[:, b])
                with torch.no_grad():
                    f_n = sample_plane_cn(plane, stat_blocked[:, a], stat_blocked[:, b])
                stat_space.append(f[:, :n_a].t())
                stat_g = f if stat_g is None else stat_g * f
                stat_n = f_n if stat_n is None else stat_n * f_n
            stat_parts.append(torch.cat([gate_grad(stat_g[:, :n_a], 1.0 - g_a), stat_g[:, n_a:], stat_n], dim=1))
        masks, mask_feats = self._outside_layer(masks, mask_feats, inside)
        # above the layer B and C columns are zeros already (:func:`_spread`); A was read whole: zero it there
        in_g = None if inside is None else torch.cat([inside[:, :n_a], inside[:, end_b:]], dim=1)
        p_n = p_g = None
        if time_gate:
            p = _time_gate_prob(masks)  # (1, n) in run order A, B, C
            p_n, p_g = p[:, n_a:end_b], torch.cat([p[:, :n_a], p[:, end_b:]], dim=1)
        for stat, (dyn_g, dyn_n, time_g, time_n) in zip(stat_parts, dyn_parts, strict=True):
            dyn_g, dyn_n = _dynamic_features(dyn_g, time_g, p_g), _dynamic_features(dyn_n, time_n, p_n)
            if in_g is not None:
                dyn_g = torch.where(in_g, dyn_g, 0.0)
            feats += [stat, torch.cat([gate_grad(dyn_g[:, :n_a], g_a), dyn_n, dyn_g[:, n_a:]], dim=1)]
        features, mask_values = torch.cat(feats + mask_feats, dim=0).t(), torch.cat(masks, dim=0).t()
        if inv is not None:
            features, mask_values = features[inv], mask_values[inv]
        return {"features": features, "mask_values": mask_values, "static_space": stat_space,
                "dynamic_space": dyn_space}

    # ---- regularisers (K-Planes) ----------------------------------------------------------
    def total_variation(self) -> torch.Tensor:
        """Mean squared difference of neighbouring grid points on the spatial planes."""
        tv = torch.zeros(())
        for p in self.space_planes():
            tv = tv + (p[..., 1:, :] - p[..., :-1, :]).pow(2).mean() + (p[..., :, 1:] - p[..., :, :-1]).pow(2).mean()
        return tv

    def time_smoothness(self) -> torch.Tensor:
        """Mean squared second difference along t of the time planes (smooth motion)."""
        sm = torch.zeros(())
        for p in self.time_planes():
            q = p[:, : self.config.features]
            if q.shape[2] >= 3:
                sm = sm + (q[:, :, 2:] - 2 * q[:, :, 1:-1] + q[:, :, :-2]).pow(2).mean()
        return sm

    def time_l1(self) -> torch.Tensor:
        """Mean |1 - value| of the time planes: static content keeps them at 1."""
        l1 = torch.zeros(())
        for p in self.time_planes():
            l1 = l1 + (1.0 - p[:, : self.config.features]).abs().mean()
        return l1


@dataclass
class KPlanesFieldConfig:
    aabb_lo: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    aabb_hi: tuple[float, float, float] = (1.0, 1.0, 1.0)
    planes: KPlanesConfig = field(default_factory=KPlanesConfig)
    hidden: int = 64
    geo_features: int = 15
    n_images: int = 1
    appearance_dim: int = 8
    n_classes: int = 3
    #: added to the density MLP's output before exp (density in 1/m): the fresh field's log-density. The
    #: dynamic fit sets it from the box (:func:`fields.dynamic_model.density_bias_for`); -1 is ~0.37 /m
    density_bias: float = -1.0
    #: background probability of the fresh class-mask head (None: torch's default, ~uniform, i.e.
    #: every place starts 75 % "person"; see :func:`fields.field.init_background_bias`)
    mask_init_background: float | None = None
    #: what the class-mask head reads: "geometry" (the detached geometry features; the people must
    #: be in the density first) or "planes" (its own small stock K-Planes of ``mask_features`` at the
    #: main planes' resolutions x ``mask_multipliers``, beside the detached geometry features, trained
    #: by the mask loss only: it can follow a person in (x, y, t) before the density has them)
    mask_encoding: str = "geometry"
    mask_features: int = 4
    mask_multipliers: tuple[int, ...] = (2, 4)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> KPlanesFieldConfig:
        d = dict(d)
        p = dict(d.pop("planes"))
        p["base_resolution"] = tuple(p["base_resolution"])
        p["multipliers"] = tuple(p["multipliers"])
        d["aabb_lo"], d["aabb_hi"] = tuple(d["aabb_lo"]), tuple(d["aabb_hi"])
        if "mask_multipliers" in d:
            d["mask_multipliers"] = tuple(d["mask_multipliers"])
        return cls(planes=KPlanesConfig(**p), **d)


class KPlanesField(nn.Module):
    """Density, colour and mask logits at world points and times (same outputs as the static field).

    ``times01`` (N,) is the scene time normalised over the flight. For the extended variant the
    output also carries ``dynamic_prob`` (N,) from the time planes' mask channel and the per-plane
    features for ``L_cos`` (``static_space``, ``dynamic_space``).
    """

    def __init__(self, config: KPlanesFieldConfig):
        super().__init__()
        self.config = config
        self.register_buffer("lo", torch.tensor(config.aabb_lo, dtype=torch.float32))
        self.register_buffer("hi", torch.tensor(config.aabb_hi, dtype=torch.float32))
        self.encoding = KPlanesEncoding(config.planes)
        h, d = config.hidden, config.planes.features
        enc_dim = self.encoding.out_dim
        if config.planes.extended:
            # fuse f_s, f_d and the mask values into one D-dim feature, as the paper does
            self.fuse = nn.Sequential(nn.Linear(enc_dim, h), nn.ReLU(), nn.Linear(h, d * self.encoding.n_scales))
            enc_dim = d * self.encoding.n_scales
        self.geo_mlp = nn.Sequential(nn.Linear(enc_dim, h), nn.ReLU(), nn.Linear(h, 1 + config.geo_features))
        self.appearance = nn.Embedding(max(1, config.n_images), config.appearance_dim)
        nn.init.zeros_(self.appearance.weight)
        self.color_mlp = nn.Sequential(nn.Linear(config.geo_features + config.appearance_dim, h), nn.ReLU(),
                                       nn.Linear(h, h), nn.ReLU(), nn.Linear(h, 3))
        # the mask head reads the geometry features but cannot change them (detached input): a mask
        # loss reaching the shared features carved the density in the static field (bench/RESULTS.md)
        mask_in = config.geo_features
        self.mask_planes = None
        if config.mask_encoding == "planes":  # built after density and colour: those start as without it
            pc = config.planes
            self.mask_planes = KPlanesEncoding(KPlanesConfig(
                base_resolution=pc.base_resolution, multipliers=tuple(config.mask_multipliers),
                time_resolution=pc.time_resolution, features=config.mask_features,
                init_low=pc.init_low, init_high=pc.init_high))
            mask_in += self.mask_planes.out_dim
        elif config.mask_encoding != "geometry":
            raise ValueError(f"unknown mask_encoding {config.mask_encoding!r}; expected 'geometry' or 'planes'")
        self.mask_head = nn.Sequential(nn.Linear(mask_in, h), nn.ReLU(), nn.Linear(h, config.n_classes + 1))
        if config.mask_init_background is not None:
            init_background_bias(self.mask_head[-1], config.mask_init_background)

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        return (points - self.lo) / (self.hi - self.lo)

    def mask_logits(self, x01: torch.Tensor, times01: torch.Tensor, geo: torch.Tensor) -> torch.Tensor:
        """Class-mask logits (N, C+1) at normalised points ``x01`` (N,3) and times (N,), from the
        geometry features ``geo`` (N,G), detached: the mask reads the geometry, never changes it."""
        inputs = geo.detach()
        if self.mask_planes is not None:
            inputs = torch.cat([inputs, self.mask_planes(x01, times01)["features"]], dim=-1)
        return self.mask_head(inputs).float()

    def _geometry(self, points, times01, dynamic_gate=None, space_points: int | None = None):
        """Normalised points, the encoding's outputs, density (1/m, 0 outside the box) and the
        geometry features of world points ``points`` (N,3) at times ``times01`` (N,)."""
        x01 = self.normalise(points)
        inside = ((x01 >= 0) & (x01 <= 1)).all(dim=-1)
        enc = self.encoding(x01, times01, dynamic_gate, space_points)
        feat = enc["features"]
        if self.config.planes.extended:
            feat = self.fuse(feat)
        hgeo = self.geo_mlp(feat).float()
        sigma = torch.exp(torch.clamp(hgeo[:, 0] + self.config.density_bias, max=15.0)) * inside
        return x01, enc, sigma, hgeo[:, 1:]

    def density(self, points: torch.Tensor, times01: torch.Tensor) -> torch.Tensor:
        """Density (1/m) alone at world points (N,3) and times (N,): no colour or mask heads, and
        for the extended variant no per-plane features kept for ``L_cos``."""
        return self._geometry(points, times01, space_points=0)[2]

    def forward(self, points, times01, dirs=None, image_idx=None, dynamic_gate=None, with_mask=True,
                space_points: int | None = None) -> dict:
        """``space_points``: how many leading points' per-plane spatial features to return (None: all)."""
        x01, enc, sigma, geo = self._geometry(points, times01, dynamic_gate, space_points)
        if image_idx is None:
            app = self.appearance.weight.mean(0, keepdim=True).expand(points.shape[0], -1)
        else:
            app = self.appearance(image_idx)
        rgb = torch.sigmoid(self.color_mlp(torch.cat([geo, app], dim=-1)).float())
        out = {"sigma": sigma, "rgb": rgb}
        if with_mask:
            out["mask_logits"] = self.mask_logits(x01, times01, geo)
        if self.config.planes.extended:
            out["dynamic_prob"] = torch.sigmoid(enc["mask_values"].mean(dim=-1))
            out["static_space"] = enc["static_space"]
            out["dynamic_space"] = enc["dynamic_space"]
        return out
