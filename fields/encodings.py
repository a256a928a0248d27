"""Spatial encodings behind one interface: a multiresolution hash grid and multiscale tri-planes.

Both take points normalised to the unit cube, ``x01`` (N, 3) in [0, 1] (the scene box mapped
by the field; points outside are clamped to the faces), and return features (N, out_dim).
Each has a slow, obviously-correct reference (``reference_forward``) that the tests compare with.

Hash grid (Instant-NGP): level l has per-axis resolution ``res[l]`` (cells; anisotropic, the
scene box is a flat slab), ``features`` values per vertex. A level whose (res+1)^3 vertices fit in
its table is stored densely (index = x + y*(rx+1) + z*(rx+1)*(ry+1)); otherwise vertices are
hashed with the XOR of coordinate * prime (int32 arithmetic, wrapping) modulo the table size.
The fast path computes all 8 corner indices of all levels in one go, gathers with
``F.embedding_bag(mode="sum", per_sample_weights=trilinear weights)`` and scatters the gradient
with a weighted ``bincount`` per feature on the CPU, ``index_add_`` on CUDA (custom autograd
function): no (N, L, 8, F) intermediate is kept for backward. On the CPU the corner arithmetic
(indices and weights), the hash grid's biggest cost in eager mode, is one ``torch.compile``-d
kernel when :func:`compiled_corners` allows it (the default; ``UAVSIM_COMPILE=0`` or a failed
compile: eager).

Tri-planes (K-Planes, static part): per scale three planes xy, xz, yz of ``features`` channels,
sampled bilinearly (``F.grid_sample``), multiplied across the planes and concatenated across
scales. Planes are initialised around 1 so the product starts informative.

A K-Planes time axis would add planes (xt, yt, zt) to :class:`TriPlanes`; the interface
(``forward(x01)``, ``out_dim``) stays the same, with ``x01`` gaining a 4th column.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

log = logging.getLogger(__name__)

#: Instant-NGP's primes (the first is 1 so that x is not scrambled); the others as int32.
PRIMES = (1, 2654435761 - 2**32, 805459861)


@dataclass
class HashGridConfig:
    """Hash grid layout. Resolutions are per level and per axis (x, y, z), in cells."""

    resolutions: list[tuple[int, int, int]] = field(default_factory=lambda: [(16, 16, 16), (32, 32, 32)])
    features: int = 2
    log2_table: int = 16
    init_scale: float = 1e-4


def _level_table_size(res: tuple[int, int, int], log2_table: int) -> tuple[int, bool]:
    verts = (res[0] + 1) * (res[1] + 1) * (res[2] + 1)
    cap = 2**log2_table
    return (verts, True) if verts <= cap else (cap, False)


class _EmbeddingBagSum(torch.autograd.Function):
    """out[n] = sum_k w[n,k] * table[idx[n,k]]; backward scatters into the table with index_add_."""

    @staticmethod
    def forward(ctx, table, idx, w):
        ctx.save_for_backward(idx, w)
        ctx.table_shape = table.shape
        return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")

    @staticmethod
    def backward(ctx, grad_out):
        idx, w = ctx.saved_tensors
        n_rows, n_feat = ctx.table_shape
        flat = idx.reshape(-1)
        if grad_out.is_cuda:
            grad_table = torch.zeros(ctx.table_shape, dtype=grad_out.dtype, device=grad_out.device)
            contrib = (w.unsqueeze(-1) * grad_out.unsqueeze(1)).reshape(-1, n_feat)
            return grad_table.index_add_(0, flat, contrib), None, None
        # CPU: one weighted bincount per feature is several times faster than index_add_
        cols = [torch.bincount(flat, weights=(w * grad_out[:, k:k + 1]).reshape(-1), minlength=n_rows)
                for k in range(n_feat)]
        return torch.stack(cols, dim=1).to(grad_out.dtype), None, None


def _corners(x01, res, res_i, hash_mask, offsets, n_dense: int):
    """Corner indices and trilinear weights of every point at every level.

    ``x01`` (N, 3) in [0, 1]; ``res`` / ``res_i`` (L, 3) cells per axis as float32 / int32;
    ``hash_mask`` (L,) table size - 1; ``offsets`` (L,) first row of each level in the table;
    the first ``n_dense`` levels are stored densely. Returns global table indices (N*L, 8) int64 and
    weights (N*L, 8), corner c = (dx, dy, dz) at position dx + 2 dy + 4 dz. Per-axis terms are
    computed once (N, L, 2) in int32 and combined by broadcasting, so nothing of shape
    (N, L, 8, 3) is built.
    """
    x = x01.float().clamp(0.0, 1.0)
    pos = x.unsqueeze(1) * res  # (N, L, 3) in cell units
    base_f = torch.minimum(pos.floor(), res - 1)  # keeps x=1 inside the last cell
    frac = pos - base_f
    base = base_f.to(torch.int32)
    b0 = torch.stack([base, base + 1], dim=-1)  # (N, L, 3, 2)
    wts = torch.stack([1 - frac, frac], dim=-1)  # (N, L, 3, 2)
    w = (wts[:, :, 2, :, None, None] * wts[:, :, 1, None, :, None] * wts[:, :, 0, None, None, :])
    # Dense levels (coarse) come first; each level computes only its own kind of index.
    k, n_levels = n_dense, res.shape[0]
    parts = []
    if k > 0:
        # dense: x + y*(rx+1) + z*(rx+1)*(ry+1), exact for the levels that fit
        bd = b0[:, :k]
        rx = res_i[:k, 0].view(1, -1, 1) + 1
        ry = res_i[:k, 1].view(1, -1, 1) + 1
        dx, dy, dz = bd[:, :, 0], bd[:, :, 1] * rx, bd[:, :, 2] * (rx * ry)
        parts.append(dz[:, :, :, None, None] + dy[:, :, None, :, None] + dx[:, :, None, None, :])
    if k < n_levels:
        # hashed: XOR of coordinate * prime, int32 wrapping; table sizes are powers of two -> mask
        bh = b0[:, k:]
        hx, hy, hz = bh[:, :, 0] * PRIMES[0], bh[:, :, 1] * PRIMES[1], bh[:, :, 2] * PRIMES[2]
        h = hz[:, :, :, None, None] ^ hy[:, :, None, :, None] ^ hx[:, :, None, None, :]
        parts.append(h & hash_mask[k:].view(1, -1, 1, 1, 1))
    idx = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
    idx = idx.to(torch.int64) + offsets.view(1, -1, 1, 1, 1)
    return idx.reshape(-1, 8), w.reshape(-1, 8)


#: below this many points the eager path is used (compiled graphs specialise on sizes 0 and 1,
#: and tiny batches gain nothing)
_COMPILE_MIN_POINTS = 64
_compiled = {"fn": None, "failed": False}


def compiled_corners() -> bool:
    """Whether the hash grid may use its ``torch.compile``-d corner kernel on the CPU.

    On unless ``UAVSIM_COMPILE=0`` is in the environment. The kernel is exact (same indices bit for
    bit) and the hash grid's forward + backward 1.0-1.6x faster in ``bench/hashgrid.py``; the first
    compile costs 1-20 s of a fit's budget, and a 300 s static fit still made 14-24 % more steps than
    eager and gained 0.4 dB held-out (bench/RESULTS.md, static sessions 12 and 13). Off for good in this
    process once a compile has failed (no C++ compiler, say), with a warning.
    """
    return os.environ.get("UAVSIM_COMPILE", "1") != "0" and not _compiled["failed"]


def _compiled_corners():
    if not compiled_corners():
        return None
    if _compiled["fn"] is None:
        # dynamic: one graph for every batch size (the occupancy sampler's live count varies)
        _compiled["fn"] = torch.compile(_corners, dynamic=True)
    return _compiled["fn"]


def _disable_compiled(err: Exception) -> None:
    _compiled["failed"] = True
    log.warning("torch.compile of the hash-grid corners failed (%s: %s); using the eager path",
                type(err).__name__, str(err).splitlines()[0] if str(err) else "")


class HashGrid(nn.Module):
    """Multiresolution hash encoding; see the module docstring."""

    def __init__(self, config: HashGridConfig):
        super().__init__()
        self.config = config
        sizes, dense, offsets = [], [], [0]
        for res in config.resolutions:
            n, is_dense = _level_table_size(tuple(res), config.log2_table)
            sizes.append(n)
            dense.append(is_dense)
            offsets.append(offsets[-1] + n)
        self.sizes, self.dense = sizes, dense
        # Levels small enough to store densely are the coarse ones, a prefix of the list.
        self.n_dense_prefix = next((i for i, d in enumerate(dense) if not d), len(dense))
        if any(dense[self.n_dense_prefix:]):
            raise ValueError(f"dense hash-grid levels must precede hashed ones (resolutions ascending), got {dense}")
        self.n_levels = len(sizes)
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.int64), persistent=False)
        self.register_buffer("res", torch.tensor(config.resolutions, dtype=torch.float32).reshape(-1, 3),
                             persistent=False)
        self.register_buffer("dense_mask", torch.tensor(dense), persistent=False)
        self.register_buffer("table_sizes", torch.tensor(sizes, dtype=torch.int64), persistent=False)
        self.register_buffer("res_i", torch.tensor(config.resolutions, dtype=torch.int32).reshape(-1, 3),
                             persistent=False)
        self.register_buffer("hash_mask", torch.tensor([n - 1 for n in sizes], dtype=torch.int32),
                             persistent=False)
        self.table = nn.Parameter(torch.empty(offsets[-1], config.features).uniform_(
            -config.init_scale, config.init_scale))

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.config.features

    def _indices_weights(self, x01: torch.Tensor):
        """Global table indices (N*L, 8) int64 and trilinear weights (N*L, 8); see :func:`_corners`.

        On the CPU the arithmetic runs as one ``torch.compile``-d kernel when :func:`compiled_corners`
        allows it (same values; 4x faster than eager, which builds a dozen (N, L, ...) temporaries).
        The weights carry no gradient to ``x01`` in either path.
        """
        args = (x01, self.res, self.res_i, self.hash_mask, self.offsets, self.n_dense_prefix)
        if x01.shape[0] >= _COMPILE_MIN_POINTS and not x01.is_cuda:
            fast = _compiled_corners()
            if fast is not None:
                with torch.no_grad():
                    try:
                        return fast(*args)
                    except Exception as err:  # a missing or broken C++ toolchain: stay correct, go slower
                        _disable_compiled(err)
        return _corners(*args)

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        n = x01.shape[0]
        idx, w = self._indices_weights(x01)
        out = _EmbeddingBagSum.apply(self.table, idx, w.to(self.table.dtype))
        return out.reshape(n, self.out_dim)

    def reference_forward(self, x01: torch.Tensor) -> torch.Tensor:
        """Slow and obvious: per level, per corner, Python-level hashing and plain indexing."""
        x = x01.float().clamp(0.0, 1.0)
        feats = []
        for lvl, res in enumerate(self.config.resolutions):
            r = torch.tensor(res, dtype=torch.float32)
            pos = x * r
            base = torch.minimum(pos.floor(), r - 1).long()
            frac = pos - base.float()
            acc = torch.zeros(x.shape[0], self.config.features)
            for dx in (0, 1):
                for dy in (0, 1):
                    for dz in (0, 1):
                        vx, vy, vz = base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz
                        if self.dense[lvl]:
                            i = vx + vy * (res[0] + 1) + vz * (res[0] + 1) * (res[1] + 1)
                        else:
                            # uint32 arithmetic done in int64 with an explicit mask
                            m = 0xFFFFFFFF
                            h = ((vx * 1) & m) ^ ((vy * 2654435761) & m) ^ ((vz * 805459861) & m)
                            h = torch.where(h >= 2**31, h - 2**32, h)  # reinterpret as int32
                            i = torch.remainder(h, self.sizes[lvl])
                        wx = frac[:, 0] if dx else 1 - frac[:, 0]
                        wy = frac[:, 1] if dy else 1 - frac[:, 1]
                        wz = frac[:, 2] if dz else 1 - frac[:, 2]
                        acc = acc + (wx * wy * wz)[:, None] * self.table[int(self.offsets[lvl]) + i]
            feats.append(acc)
        return torch.cat(feats, dim=-1)


@dataclass
class TriPlaneConfig:
    """Multiscale planes: ``resolutions`` per scale as (rx, ry, rz) grid points per axis."""

    resolutions: list[tuple[int, int, int]] = field(default_factory=lambda: [(64, 64, 16), (128, 128, 32)])
    features: int = 16
    init_low: float = 0.1
    init_high: float = 0.5


#: plane (a, b) pairs of coordinate axes: xy, xz, yz
PLANE_AXES = ((0, 1), (0, 2), (1, 2))


class TriPlanes(nn.Module):
    """Multiscale tri-planes; see the module docstring."""

    def __init__(self, config: TriPlaneConfig):
        super().__init__()
        self.config = config
        planes = []
        for res in config.resolutions:
            for a, b in PLANE_AXES:
                # grid_sample layout (1, C, H, W): W runs along axis a, H along axis b
                p = torch.empty(1, config.features, res[b], res[a]).uniform_(config.init_low, config.init_high)
                planes.append(nn.Parameter(p))
        self.planes = nn.ParameterList(planes)

    @property
    def out_dim(self) -> int:
        return len(self.config.resolutions) * self.config.features

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        g = x01.float().clamp(0.0, 1.0) * 2.0 - 1.0  # align_corners=True: -1/+1 at the outer texels
        outs = []
        for s in range(len(self.config.resolutions)):
            prod = None
            for k, (a, b) in enumerate(PLANE_AXES):
                grid = torch.stack([g[:, a], g[:, b]], dim=-1).view(1, -1, 1, 2).to(self.planes[0].dtype)
                f = F.grid_sample(self.planes[3 * s + k], grid, mode="bilinear", align_corners=True)
                f = f.view(self.config.features, -1)
                prod = f if prod is None else prod * f
            outs.append(prod.t())
        return torch.cat(outs, dim=-1)

    def reference_forward(self, x01: torch.Tensor) -> torch.Tensor:
        """Slow and obvious bilinear interpolation with explicit texel indexing."""
        x = x01.float().clamp(0.0, 1.0)
        outs = []
        for s, res in enumerate(self.config.resolutions):
            prod = torch.ones(x.shape[0], self.config.features)
            for k, (a, b) in enumerate(PLANE_AXES):
                plane = self.planes[3 * s + k][0]  # (C, Hb, Wa)
                u = x[:, a] * (res[a] - 1)
                v = x[:, b] * (res[b] - 1)
                u0 = torch.minimum(u.floor(), torch.tensor(res[a] - 2.0)).long().clamp_min(0)
                v0 = torch.minimum(v.floor(), torch.tensor(res[b] - 2.0)).long().clamp_min(0)
                fu, fv = u - u0, v - v0
                val = (plane[:, v0, u0] * (1 - fu) * (1 - fv) + plane[:, v0, u0 + 1] * fu * (1 - fv)
                       + plane[:, v0 + 1, u0] * (1 - fu) * fv + plane[:, v0 + 1, u0 + 1] * fu * fv)
                prod = prod * val.t()
            outs.append(prod)
        return torch.cat(outs, dim=-1)


def make_encoding(kind: str, resolutions, features: int, log2_table: int = 16) -> nn.Module:
    """Build an encoding by name: ``"hash"`` or ``"planes"``."""
    if kind == "hash":
        return HashGrid(HashGridConfig([tuple(r) for r in resolutions], features, log2_table))
    if kind == "planes":
        return TriPlanes(TriPlaneConfig([tuple(r) for r in resolutions], features))
    raise ValueError(f"unknown encoding {kind!r}; expected 'hash' or 'planes'")


def param_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def geometric_resolutions(coarsest: tuple[float, float, float], finest: tuple[float, float, float],
                          levels: int) -> list[tuple[int, int, int]]:
    """Per-level per-axis resolutions growing geometrically from ``coarsest`` to ``finest``."""
    out = []
    for lvl in range(levels):
        f = lvl / max(levels - 1, 1)
        out.append(tuple(max(1, int(round(math.exp((1 - f) * math.log(c) + f * math.log(fi)))))
                         for c, fi in zip(coarsest, finest, strict=True)))
    return out
