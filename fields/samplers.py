"""Where along each ray to evaluate the field: ray/box intersection and two samplers.

- :class:`StratifiedSampler`: ``n`` intervals spread evenly between the ray's entry and exit of
  the scene box (the ground slab), jittered while training.
- :class:`OccupancySampler`: a coarse 3D grid of density over the box (an exponential moving
  maximum of the field's density, refreshed a fraction of the cells at a time while training)
  acts as the proposal: its transmittance-weighted distribution along each ray is inverted to
  place the ``n`` intervals near the first surface (Nerfacto's proposal idea with a grid instead
  of a network; no extra network to train).

Both return interval edges ``t_edges`` (R, n+1) in metres along unit directions; rays that miss
the box get zero-length intervals (weight 0 everywhere, i.e. pure background).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from fields.rendering import weights_from_density


def ray_box(origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Entry and exit distances (R,) of rays with the box [lo, hi]; ``hit`` (R,) bool.

    Rays starting inside get ``t_near = 0``; rays that miss get ``t_near = t_far = 0``. Direction
    components of exactly 0 (rays parallel to a face) are handled without NaN.
    """
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12) * torch.where(dirs < 0, -1.0, 1.0), dirs)
    inv = 1.0 / safe
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    hit = t_far > t_near
    zero = torch.zeros_like(t_near)
    return torch.where(hit, t_near, zero), torch.where(hit, t_far, zero), hit


class StratifiedSampler:
    """Evenly spaced (jittered in training) intervals inside the scene box."""

    def __init__(self, n_samples: int = 48):
        self.n_samples = int(n_samples)

    def edges(self, origins, dirs, lo, hi, train: bool, generator=None) -> torch.Tensor:
        near, far, _ = ray_box(origins, dirs, lo, hi)
        n = self.n_samples
        u = torch.linspace(0.0, 1.0, n + 1, device=origins.device).expand(origins.shape[0], n + 1)
        if train:
            jitter = (torch.rand(origins.shape[0], n, device=origins.device, generator=generator) - 0.5) / n
            u = torch.cat([u[:, :1], (u[:, 1:-1] + jitter[:, 1:]).clamp(0, 1), u[:, -1:]], dim=-1)
        return near[:, None] + (far - near)[:, None] * u

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


def sample_pdf(edges: torch.Tensor, weights: torch.Tensor, n_edges: int, train: bool,
               generator=None) -> torch.Tensor:
    """Inverse-CDF resampling: ``n_edges`` sorted new edges distributed like ``weights`` over ``edges``."""
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1).clamp(max=1.0)
    r = edges.shape[0]
    if train:
        u = (torch.arange(n_edges, device=edges.device) + torch.rand(r, n_edges, device=edges.device,
                                                                   generator=generator)) / n_edges
    else:
        u = (torch.arange(n_edges, device=edges.device) + 0.5).expand(r, n_edges) / n_edges
    u = u.contiguous().clamp(0.0, 1.0)
    idx = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e0, e1 = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-9)).clamp(0, 1)
    out = e0 + frac * (e1 - e0)
    # keep the segment's end points so the whole [near, far] stays covered
    out = torch.cat([edges[:, :1], out[:, 1:-1], edges[:, -1:]], dim=-1)
    return torch.sort(out, dim=-1).values


class OccupancySampler:
    """Occupancy-grid-guided importance sampling; see the module docstring."""

    def __init__(self, grid_shape: tuple[int, int, int], n_samples: int = 32, n_coarse: int = 96,
                 decay: float = 0.9, update_fraction: float = 1 / 8):
        self.grid_shape = tuple(int(g) for g in grid_shape)
        self.n_samples, self.n_coarse = int(n_samples), int(n_coarse)
        self.decay, self.update_fraction = decay, update_fraction
        # start "everything may be occupied": the sampler is stratified until the grid learns
        self.grid = torch.full(self.grid_shape, 1.0)
        self._cursor = 0

    def state_dict(self) -> dict:
        return {"grid": self.grid.clone(), "cursor": self._cursor}

    def load_state_dict(self, state: dict) -> None:
        self.grid = state["grid"].clone()
        self._cursor = int(state["cursor"])

    def to(self, device) -> OccupancySampler:
        self.grid = self.grid.to(device)
        return self

    @torch.no_grad()
    def update(self, density_fn, lo: torch.Tensor, hi: torch.Tensor, generator=None) -> None:
        """Refresh a slice of the cells: density at a random point per cell, moving maximum."""
        gx, gy, gz = self.grid_shape
        n_cells = gx * gy * gz
        k = max(1, int(n_cells * self.update_fraction))
        idx = (torch.arange(k, device=self.grid.device) + self._cursor) % n_cells
        self._cursor = int((self._cursor + k) % n_cells)
        iz = idx % gz
        iy = (idx // gz) % gy
        ix = idx // (gy * gz)
        cell = torch.stack([ix, iy, iz], -1).float()
        jitter = torch.rand(k, 3, device=self.grid.device, generator=generator)
        size = torch.tensor(self.grid_shape, device=self.grid.device, dtype=torch.float32)
        pts = lo + (cell + jitter) / size * (hi - lo)
        sig = torch.cat([density_fn(p) for p in pts.split(65536)])
        flat = self.grid.view(-1)
        flat[idx] = torch.maximum(flat[idx] * self.decay, sig.float())

    def _lookup(self, pts: torch.Tensor, lo, hi) -> torch.Tensor:
        """Grid density at points (R, S, 3), trilinear between cell centres."""
        g = self.grid[None, None]  # (1, 1, gx, gy, gz)
        x = (pts - lo) / (hi - lo) * 2 - 1  # grid_sample wants (z-, y-, x-) order of the last dims
        grid = torch.stack([x[..., 2], x[..., 1], x[..., 0]], -1).view(1, -1, 1, 1, 3)
        v = F.grid_sample(g, grid, mode="bilinear", align_corners=False, padding_mode="border")
        return v.view(pts.shape[:-1])

    def edges(self, origins, dirs, lo, hi, train: bool, generator=None) -> torch.Tensor:
        coarse = StratifiedSampler(self.n_coarse).edges(origins, dirs, lo, hi, train=False)
        mid = 0.5 * (coarse[:, 1:] + coarse[:, :-1])
        sig = self._lookup(origins[:, None] + mid[..., None] * dirs[:, None], lo, hi)
        # cap the proposal density at ~1 optical depth per cell so the samples spread over the
        # cell where the surface starts and the next one, not only its upper edge
        cell = float(((hi - lo) / torch.tensor(self.grid_shape, device=lo.device, dtype=lo.dtype)).min())
        w = weights_from_density(sig.clamp_max(1.0 / cell), coarse[:, 1:] - coarse[:, :-1])
        return sample_pdf(coarse, w, self.n_samples + 1, train, generator)


def sample_points(origins, dirs, edges):
    """Midpoints of the intervals ``edges`` (R,S+1, metres along unit ``dirs``) as 3-D points.

    Returns (mid (R,S), deltas (R,S), points (R*S,3)) in the frame of ``origins``/``dirs``.
    """
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    deltas = edges[:, 1:] - edges[:, :-1]
    pts = (origins[:, None, :] + mid[..., None] * dirs[:, None, :]).reshape(-1, 3)
    return mid, deltas, pts
