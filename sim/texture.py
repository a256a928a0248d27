"""Procedural ground texture: grass, dirt patches and tracks, seamless, with a mip pyramid.

The texture is a square tile of ``size`` texels at ``texel_m`` metres per texel that repeats
across the infinite ground plane (world ENU, z = 0). It is built from periodic multi-scale value
noise so the tile has no seams, and is sampled with trilinear mip filtering so distant ground does
not alias. Colours are linear RGB in 0..1 (float32).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def _periodic_noise(rng: np.random.Generator, cells: int, size: int) -> np.ndarray:
    """Smooth periodic noise in [0, 1): a ``cells`` x ``cells`` random lattice, bicubic upsampled.

    Padding the lattice by wrap-around before resizing makes the result tile exactly.
    """
    lattice = rng.random((cells, cells), dtype=np.float32)
    pad = 2
    padded = np.pad(lattice, pad, mode="wrap")
    scale = size // cells
    big = cv2.resize(padded, ((cells + 2 * pad) * scale,) * 2, interpolation=cv2.INTER_CUBIC)
    return big[pad * scale : pad * scale + size, pad * scale : pad * scale + size]


def _fbm(rng: np.random.Generator, size: int, cells: list[int], gain: float = 0.55) -> np.ndarray:
    """Fractal sum of periodic noise octaves, normalised to zero mean and unit std."""
    total = np.zeros((size, size), np.float32)
    amp = 1.0
    for c in cells:
        total += amp * (_periodic_noise(rng, c, size) - 0.5)
        amp *= gain
    total -= total.mean()
    total /= max(float(total.std()), 1e-6)
    return total


def _blur_wrap(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of a periodic image (OpenCV's blur has no wrap-around border)."""
    pad = int(np.ceil(3 * sigma)) + 1
    padded = np.pad(img, pad, mode="wrap")
    return cv2.GaussianBlur(padded, (0, 0), sigma)[pad:-pad, pad:-pad]


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    y = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return y * y * (3.0 - 2.0 * y)


def _srgb_to_linear(c) -> np.ndarray:
    return (np.asarray(c, np.float32) / 255.0) ** 2.2


@dataclass
class GroundTexture:
    """A seamless ground tile and its mip levels (level k has ``size / 2**k`` texels a side)."""

    levels: list[np.ndarray]  # each (n, n, 3) float32 linear RGB
    texel_m: float

    @property
    def size(self) -> int:
        return self.levels[0].shape[0]

    @property
    def tile_m(self) -> float:
        return self.size * self.texel_m

    def sample(self, x: np.ndarray, y: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """Albedo (N,3) at world points (x, y) for sample footprints ``footprint_m`` (metres).

        The mip level is ``log2(footprint / texel)``, blended between the two nearest levels.
        Texel (0, 0) covers world x in [0, texel) and y in [0, texel) going north, so image rows
        follow +y.
        """
        n = len(x)
        out = np.zeros((n, 3), np.float32)
        if n == 0:
            return out
        inv_texel = np.float32(1.0 / self.texel_m)
        level = np.log2(np.maximum(np.asarray(footprint_m, np.float32) * inv_texel, np.float32(1e-9)))
        np.nan_to_num(level, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        np.clip(level, 0.0, len(self.levels) - 1.0, out=level)
        lo = level.astype(np.int32)  # floor: level >= 0
        frac = (level - lo).astype(np.float32)
        u0 = np.mod(np.asarray(x, np.float32) * inv_texel, np.float32(self.size))
        v0 = np.mod(np.asarray(y, np.float32) * inv_texel, np.float32(self.size))
        counts = np.bincount(lo, minlength=len(self.levels))
        for k in np.nonzero(counts)[0]:
            sel = slice(None) if counts[k] == n else np.flatnonzero(lo == k)
            a = self._sample_level(int(k), u0[sel], v0[sel])
            if k + 1 < len(self.levels):
                b = self._sample_level(int(k) + 1, u0[sel], v0[sel])
                f = frac[sel, None]
                a += (b - a) * f
            out[sel] = a
        return out

    def _sample_level(self, k: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        tex = self.levels[k]
        scale = 1.0 / (1 << k)
        # Texel centres at +0.5; remap's integer coordinates are texel centres.
        # remap's maps are limited in rows; fold long vectors into a 2-D block.
        n = len(u)
        cols = 1024
        rows = -(-n // cols)
        mu = np.empty(rows * cols, np.float32)
        mv = np.empty(rows * cols, np.float32)
        np.multiply(u, np.float32(scale), out=mu[:n])
        np.multiply(v, np.float32(scale), out=mv[:n])
        mu[:n] -= 0.5
        mv[:n] -= 0.5
        mu[n:] = 0.0
        mv[n:] = 0.0
        mu, mv = mu.reshape(rows, cols), mv.reshape(rows, cols)
        s = cv2.remap(tex, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        return s.reshape(-1, 3)[:n]


def make_ground_texture(seed: int, size: int = 4096, texel_m: float = 0.025) -> GroundTexture:
    """Grass with dirt patches, darker and drier areas, fine blade-scale noise and two tracks."""
    rng = np.random.default_rng(seed)
    size = int(size)
    if size & (size - 1):
        raise ValueError(f"texture size must be a power of two, got {size}")

    patch = _fbm(rng, size, [4, 8, 16, 32])  # metres-to-tens-of-metres variation
    dryness = _fbm(rng, size, [8, 16, 64])
    clumps = _fbm(rng, size, [128, 256, 512], gain=0.7)  # tufts, ~10-40 cm
    fine = rng.standard_normal((size, size), dtype=np.float32)  # blade scale, one texel
    fine = _blur_wrap(fine, 0.7)
    fine /= max(float(fine.std()), 1e-6)

    grass = _srgb_to_linear((72, 108, 44))
    grass_dry = _srgb_to_linear((128, 132, 70))
    grass_dark = _srgb_to_linear((44, 74, 30))
    dirt = _srgb_to_linear((122, 98, 70))
    track = _srgb_to_linear((158, 138, 108))

    w_dry = _smoothstep(-0.2, 1.2, dryness)[..., None]
    w_dark = _smoothstep(0.2, 1.5, -dryness + 0.5 * clumps)[..., None]
    colour = grass * (1 - w_dry) + grass_dry * w_dry
    colour = colour * (1 - 0.6 * w_dark) + grass_dark * 0.6 * w_dark
    w_dirt = _smoothstep(1.1, 1.6, patch + 0.25 * clumps)[..., None]
    colour = colour * (1 - w_dirt) + dirt * w_dirt

    # Tracks: smooth closed curves around the tile (periodic, so the tile still wraps).
    track_mask = np.zeros((size, size), np.float32)
    for _ in range(2):
        phase = rng.uniform(0, 2 * np.pi, 3)
        amp = rng.uniform(0.05, 0.15, 3) * size
        s = np.linspace(0, 1, 400)
        horizontal = rng.random() < 0.5
        base = rng.uniform(0, size)
        offset = base + sum(a * np.sin(2 * np.pi * (k + 1) * s + p)
                            for k, (a, p) in enumerate(zip(amp, phase, strict=True)))
        along = s * size
        pts = np.stack([along, offset], 1) if horizontal else np.stack([offset, along], 1)
        width_px = int(rng.uniform(1.8, 2.6) / texel_m)
        for shift_u in (-size, 0, size):
            for shift_v in (-size, 0, size):
                shifted = (pts + [shift_u, shift_v]).astype(np.int32).reshape(-1, 1, 2)
                cv2.polylines(track_mask, [shifted], False, 1.0, width_px, cv2.LINE_AA)
    track_mask = _blur_wrap(track_mask, 6.0)
    track_mask = np.clip(track_mask * (1.0 + 0.35 * clumps), 0.0, 1.0)[..., None]
    colour = colour * (1 - track_mask) + track * track_mask

    # Brightness variation: clumps and blades (stronger on grass than on bare tracks).
    texture_gain = 1.0 + (0.10 * clumps + 0.12 * fine)[..., None] * (1.0 - 0.6 * track_mask)
    colour = np.clip(colour * texture_gain, 0.0, 1.0).astype(np.float32)

    levels = [colour]
    while levels[-1].shape[0] > 16:
        prev = levels[-1]
        half = prev.shape[0] // 2
        levels.append(cv2.resize(prev, (half, half), interpolation=cv2.INTER_AREA))
    return GroundTexture(levels=levels, texel_m=float(texel_m))
