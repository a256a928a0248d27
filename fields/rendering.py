"""Volume rendering as pure functions (no fields, no encodings, no rays).

Conventions: samples along a ray are ordered front to back; ``sigma`` is density in 1/metre,
``deltas`` the interval lengths in metres (``inf`` allowed for an open last interval). Shapes are
``(..., S)`` for per-sample scalars and ``(..., S, C)`` for per-sample vectors.

Numerical contract (tested on hard numbers):
- alpha = -expm1(-sigma * delta), exact for tiny optical depths;
- transmittance is exp of an exclusive cumulative sum of optical depths (log space), so it never
  underflows into NaN and is exactly 1 at the first sample;
- sigma = 0, sigma = 1e9, delta = 0 and delta = inf all give finite weights in [0, 1] with finite
  gradients; NaN densities are treated as 0 (and logged by the caller, not here);
- the accumulated opacity (sum of weights) is <= 1.
"""

from __future__ import annotations

import torch

#: optical depth per interval is clamped here: exp(-60) ~ 1e-26 is "opaque" and keeps grads finite
MAX_OPTICAL_DEPTH = 60.0


def optical_depth(sigma: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """sigma * delta per interval, with NaN -> 0, negatives -> 0 and the product clamped.

    ``inf * 0`` (an open interval with zero density) is 0, not NaN.
    """
    sigma = torch.nan_to_num(sigma, nan=0.0, posinf=1e30).clamp_min(0.0)
    deltas = torch.nan_to_num(deltas, nan=0.0, posinf=1e30).clamp_min(0.0)
    tau = sigma * deltas
    return tau.clamp(0.0, MAX_OPTICAL_DEPTH)


def alpha_from_density(sigma: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Opacity of each interval, 1 - exp(-sigma * delta), in [0, 1]."""
    return -torch.expm1(-optical_depth(sigma, deltas))


def transmittance(sigma: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Light reaching each sample from the ray origin: exp(-sum_{j<i} sigma_j delta_j) (exclusive)."""
    tau = optical_depth(sigma, deltas)
    csum = torch.cumsum(tau, dim=-1)
    excl = torch.cat([torch.zeros_like(csum[..., :1]), csum[..., :-1]], dim=-1)
    return torch.exp(-excl)


def weights_from_density(sigma: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Rendering weights w_i = T_i * alpha_i (..., S); their sum along S is <= 1."""
    tau = optical_depth(sigma, deltas)
    csum = torch.cumsum(tau, dim=-1)
    excl = torch.cat([torch.zeros_like(csum[..., :1]), csum[..., :-1]], dim=-1)
    w = torch.exp(-excl) * -torch.expm1(-tau)
    return w


def accumulate(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Sum_i w_i * v_i: (..., S) weights and (..., S, C) values -> (..., C)."""
    return torch.sum(weights.unsqueeze(-1) * values, dim=-2)


def opacity(weights: torch.Tensor) -> torch.Tensor:
    """Accumulated opacity (..., 1), clamped to [0, 1] against float rounding."""
    return weights.sum(dim=-1, keepdim=True).clamp(0.0, 1.0)


def composite(weights: torch.Tensor, values: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Sum_i w_i v_i + (1 - opacity) * background; ``background`` broadcasts to (..., C)."""
    return accumulate(weights, values) + (1.0 - opacity(weights)) * background


def expected_depth(weights: torch.Tensor, t_mid: torch.Tensor, far: torch.Tensor | None = None) -> torch.Tensor:
    """Expected distance along the ray (..., 1); the remaining mass is placed at ``far`` if given."""
    d = torch.sum(weights * t_mid, dim=-1, keepdim=True)
    if far is not None:
        d = d + (1.0 - opacity(weights)) * far.reshape(d.shape)
    return d


def distortion_loss(weights: torch.Tensor, t_edges: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360 distortion loss per ray (...,), O(S) form.

    ``t_edges`` (..., S+1) are interval edges (finite; normalise them by the slab length before
    calling so the loss is scale-free). Penalises weight spread along the ray, i.e. floaters and
    semi-transparent fog in front of the surface.
    """
    mid = 0.5 * (t_edges[..., 1:] + t_edges[..., :-1])
    width = t_edges[..., 1:] - t_edges[..., :-1]
    w = weights
    # sum_{i,j} w_i w_j |m_i - m_j| via cumulative sums (samples are sorted)
    wm = w * mid
    w_cum = torch.cumsum(w, dim=-1)
    wm_cum = torch.cumsum(wm, dim=-1)
    w_excl = w_cum - w
    wm_excl = wm_cum - wm
    inter = 2.0 * torch.sum(w * (mid * w_excl - wm_excl), dim=-1)
    intra = torch.sum(w * w * width, dim=-1) / 3.0
    return inter + intra
