"""Where along each ray to evaluate the field: ray/box intersection and two samplers.

- :class:`StratifiedSampler`: ``n`` intervals spread evenly between the ray's entry and exit of
  the scene box (the ground slab), jittered while training.
- :class:`OccupancySampler`: a coarse 3D grid of density over the box (an exponential moving
  maximum of the field's density, refreshed a fraction of the cells at a time while training;
  Instant-NGP's occupancy grid) marks cells as occupied (optical depth across a cell >= 1 %,
  dilated by one cell). Along each ray the ``n`` intervals are spread evenly over the occupied
  stretches, with a small share (``empty_share`` of the weight per metre) left in empty cells so a
  cell the grid wrongly empties can still be learned back. A fresh grid is all occupied, i.e.
  stratified. Evenly over *all* occupied stretches, not transmittance-weighted: a
  semi-transparent person and the ground behind it both keep samples.

Both return interval edges ``t_edges`` (R, n+1) in metres along unit directions; rays that miss
the box get zero-length intervals (weight 0 everywhere, i.e. pure background).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


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


def grid_lookup(grid: torch.Tensor, pts: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Value of the cell of a grid over the box [lo, hi] (cells along x, y, z) that holds each point
    of ``pts`` (..., 3); points outside the box read the nearest edge cell."""
    shape = torch.tensor(grid.shape, device=pts.device)
    ijk = torch.minimum(((pts - lo) / (hi - lo)).clamp(0, 1).mul(shape).long(), shape - 1)
    return grid[ijk[..., 0], ijk[..., 1], ijk[..., 2]]


class StratifiedSampler:
    """Evenly spaced (jittered in training) intervals inside the scene box."""

    def __init__(self, n_samples: int = 48):
        self.n_samples = int(n_samples)

    def edges(self, origins, dirs, lo, hi, train: bool, generator=None, jitter_rows=None) -> torch.Tensor:
        """(R, n+1) interval edges along each ray (distances from its origin, metres). ``jitter_rows`` (R,)
        long: ray i takes row ``jitter_rows[i]`` of the jitter drawn for the batch, so rays reordered after
        they were drawn keep the jitter they were drawn with (None: row i)."""
        near, far, _ = ray_box(origins, dirs, lo, hi)
        n = self.n_samples
        u = torch.linspace(0.0, 1.0, n + 1, device=origins.device).expand(origins.shape[0], n + 1)
        if train:
            jitter = (torch.rand(origins.shape[0], n, device=origins.device, generator=generator) - 0.5) / n
            if jitter_rows is not None:
                jitter = jitter[jitter_rows]
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
    # evenly spaced quantiles from 0 to 1 (jittered inside while training, as the stratified sampler
    # does): a uniform ``weights`` gives exactly the stratified edges
    u = torch.linspace(0.0, 1.0, n_edges, device=edges.device).expand(r, n_edges)
    if train and n_edges > 2:
        jitter = (torch.rand(r, n_edges - 2, device=edges.device, generator=generator) - 0.5) / (n_edges - 1)
        u = torch.cat([u[:, :1], u[:, 1:-1] + jitter, u[:, -1:]], dim=-1)
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
    """Occupancy-grid-guided sampling; see the module docstring.

    ``grid_shape`` (x, y, z cells over the box); ``n_coarse``: evenly spaced probes per ray at which
    the grid is read; ``decay``: factor on a cell's value each time it is refreshed (moving
    maximum); ``update_fraction``: share of the cells refreshed per :meth:`update`;
    ``empty_share``: sampling weight per metre of an empty stretch relative to an occupied one.
    """

    #: density of a cell never refreshed ("may be occupied")
    FRESH = torch.finfo(torch.float32).max

    def __init__(self, grid_shape: tuple[int, int, int], n_samples: int = 32, n_coarse: int = 96,
                 decay: float = 0.9, update_fraction: float = 1 / 8, empty_share: float = 0.05):
        self.grid_shape = tuple(int(g) for g in grid_shape)
        self.n_samples, self.n_coarse = int(n_samples), int(n_coarse)
        self.decay, self.update_fraction, self.empty_share = decay, update_fraction, float(empty_share)
        # start "everything may be occupied": the sampler is stratified until the grid learns
        self.grid = torch.full(self.grid_shape, self.FRESH)
        self._cursor = 0
        self._occ = None  # occupied(), cached until the grid changes (the box lo/hi is fixed per model)

    def state_dict(self) -> dict:
        return {"grid": self.grid.clone(), "cursor": self._cursor}

    def load_state_dict(self, state: dict) -> None:
        self.grid = state["grid"].clone()
        self._cursor = int(state["cursor"])
        self._occ = None

    def to(self, device) -> OccupancySampler:
        self.grid = self.grid.to(device)
        self._occ = None
        return self

    @torch.no_grad()
    def update(self, density_fn, lo: torch.Tensor, hi: torch.Tensor, generator=None, full: bool = False) -> None:
        """Refresh a slice of the cells (every cell with ``full``, replacing the old values): density
        (1/m) at a random point per cell, kept as a moving maximum. The first refresh of a fresh grid
        is always full: its "may be occupied" must not linger for the ~1/decay sweeps a moving
        maximum would take to forget it."""
        full = full or bool((self.grid == self.FRESH).all())
        gx, gy, gz = self.grid_shape
        n_cells = gx * gy * gz
        k = n_cells if full else max(1, int(n_cells * self.update_fraction))
        idx = (torch.arange(k, device=self.grid.device) + self._cursor) % n_cells
        self._cursor = int((self._cursor + k) % n_cells)
        iz = idx % gz
        iy = (idx // gz) % gy
        ix = idx // (gy * gz)
        cell = torch.stack([ix, iy, iz], -1).float()
        jitter = torch.rand(k, 3, device=self.grid.device, generator=generator)
        size = torch.tensor(self.grid_shape, device=self.grid.device, dtype=torch.float32)
        pts = lo + (cell + jitter) / size * (hi - lo)
        sig = torch.cat([density_fn(p) for p in pts.split(65536)]).float()
        flat = self.grid.view(-1)
        flat[idx] = sig if full else torch.maximum(flat[idx] * self.decay, sig)
        self._occ = None

    def occupied(self, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
        """(gx, gy, gz) bool: optical depth across a cell >= 0.01 at the grid's density, dilated by one cell."""
        if self._occ is None:
            cell = float(((hi - lo) / torch.tensor(self.grid_shape, device=lo.device, dtype=lo.dtype)).min())
            occ = (self.grid >= 0.01 / cell).float()[None, None]
            self._occ = F.max_pool3d(occ, 3, stride=1, padding=1)[0, 0] > 0
        return self._occ

    def edges(self, origins, dirs, lo, hi, train: bool, generator=None) -> torch.Tensor:
        coarse = StratifiedSampler(self.n_coarse).edges(origins, dirs, lo, hi, train=False)
        mid = 0.5 * (coarse[:, 1:] + coarse[:, :-1])
        occ = grid_lookup(self.occupied(lo, hi), origins[:, None] + mid[..., None] * dirs[:, None], lo, hi)
        share = torch.where(occ, 1.0, self.empty_share)
        return sample_pdf(coarse, share * (coarse[:, 1:] - coarse[:, :-1]), self.n_samples + 1, train, generator)


def sample_points(origins, dirs, edges):
    """Midpoints of the intervals ``edges`` (R,S+1, metres along unit ``dirs``) as 3-D points.

    Returns (mid (R,S), deltas (R,S), points (R*S,3)) in the frame of ``origins``/``dirs``.
    """
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    deltas = edges[:, 1:] - edges[:, :-1]
    pts = (origins[:, None, :] + mid[..., None] * dirs[:, None, :]).reshape(-1, 3)
    return mid, deltas, pts
