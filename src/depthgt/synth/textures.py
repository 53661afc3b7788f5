"""Procedural albedo textures for the synthetic indoor scenes.

Every texture is a tileable (S, S, 3) float32 image in [0, 1] that covers
``period_m`` metres of surface; surfaces look it up by planar texture coordinates
(see :mod:`depthgt.synth.scene`). Textures are generated once per scene from a numpy
``Generator`` so a scene is deterministic per seed.

The patterns (wood rings and grain, floor tiles, striped carpet, plaster, posters,
book spines) carry detail down to a few millimetres, so that an RGB feature encoder
finds texture to register frames on. They are written here because no installed
library generates procedural material textures; OpenCV does the filtering, the
resizing and the drawing.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["TEXTURE_KINDS", "fbm", "make_texture"]

TEXTURE_KINDS = ("wood", "tiles", "carpet", "plaster", "poster", "books", "metal", "fabric", "dark")


def fbm(rng: np.random.Generator, size: int, octaves: int = 6, base_cells: int = 4, gain: float = 0.55) -> np.ndarray:
    """Tileable fractal value noise.

    Each octave is a random (cells x cells) lattice, wrap-padded and cubic-upsampled
    to ``size`` (so the result tiles seamlessly); octave k has ``base_cells * 2**k``
    cells and amplitude ``gain**k``.

    Returns:
        (size, size) float32, zero mean, unit standard deviation.
    """
    out = np.zeros((size, size), np.float32)
    amp = 1.0
    for k in range(octaves):
        cells = min(base_cells * 2**k, size)
        lat = rng.standard_normal((cells, cells)).astype(np.float32)
        pad = np.pad(lat, 2, mode="wrap")
        scale = size / cells
        big = cv2.resize(pad, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        off = int(round(2 * scale))
        out += amp * big[off : off + size, off : off + size]
        amp *= gain
    out -= out.mean()
    return out / max(float(out.std()), 1e-6)


def _mix(c0: np.ndarray, c1: np.ndarray, t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)[..., None]
    return (1.0 - t) * np.asarray(c0, np.float32) + t * np.asarray(c1, np.float32)


def _wood(rng, s):
    y, x = np.mgrid[0:s, 0:s].astype(np.float32) / s
    warp = fbm(rng, s, octaves=4, base_cells=2)
    # rings: stretched along x (the grain direction), a whole number of periods so it tiles
    n_rings = int(rng.integers(10, 22))
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (n_rings * y + 0.35 * warp))
    grain = fbm(rng, s, octaves=3, base_cells=8)
    grain = cv2.resize(grain[:, : s // 8], (s, s), interpolation=cv2.INTER_LINEAR)  # streaks along x
    base = rng.uniform([0.45, 0.28, 0.12], [0.72, 0.50, 0.28]).astype(np.float32)
    dark = base * rng.uniform(0.55, 0.75)
    tex = _mix(base, dark, rings**3 + 0.15 * grain)
    return tex * (1 + 0.06 * fbm(rng, s, octaves=6, base_cells=16))[..., None]


def _tiles(rng, s):
    n = int(rng.integers(3, 6))  # tiles per texture period
    y, x = np.mgrid[0:s, 0:s].astype(np.float32) * n / s
    iy, ix = np.floor(y).astype(int), np.floor(x).astype(int)
    fx, fy = x - ix, y - iy
    base = rng.uniform([0.55, 0.5, 0.45], [0.85, 0.82, 0.78]).astype(np.float32)
    per_tile = rng.uniform(0.85, 1.1, size=(n, n)).astype(np.float32)
    tex = base * per_tile[iy % n, ix % n][..., None]
    tex *= (1 + 0.12 * fbm(rng, s, octaves=6, base_cells=8))[..., None]
    grout = np.minimum(np.minimum(fx, 1 - fx), np.minimum(fy, 1 - fy)) < 0.025 * n / 4
    tex[grout] = base * 0.45
    return tex


def _carpet(rng, s):
    n_stripes = int(rng.integers(40, 90))
    y, x = np.mgrid[0:s, 0:s].astype(np.float32) / s
    stripe_val = rng.uniform(0, 1, n_stripes).astype(np.float32)
    idx = np.floor((y + 0.01 * fbm(rng, s, 3, 4)) * n_stripes).astype(int) % n_stripes
    c0 = rng.uniform(0.1, 0.3, 3).astype(np.float32)
    c1 = rng.uniform(0.4, 0.7, 3).astype(np.float32)
    tex = _mix(c0, c1, stripe_val[idx] + 0.25 * fbm(rng, s, 6, 32))
    return tex


def _plaster(rng, s):
    base = rng.uniform([0.6, 0.6, 0.55], [0.9, 0.9, 0.85]).astype(np.float32)
    tint = rng.uniform(0.85, 1.0, 3).astype(np.float32)
    n = fbm(rng, s, octaves=7, base_cells=4)
    tex = base * tint * (1 + 0.07 * n)[..., None]
    # faint spots and scuffs give the wall features to match
    spots = fbm(rng, s, octaves=3, base_cells=32)
    tex *= (1 - 0.12 * (spots > 1.6))[..., None]
    return tex


def _poster(rng, s):
    tex = np.empty((s, s, 3), np.float32)
    tex[:] = rng.uniform(0.2, 0.95, 3)
    for _ in range(int(rng.integers(25, 45))):
        col = tuple(float(c) for c in rng.uniform(0, 1, 3))
        kind = rng.integers(0, 3)
        p = rng.integers(0, s, 2)
        if kind == 0:
            q = p + rng.integers(8, s // 3, 2)
            cv2.rectangle(tex, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), col, -1)
        elif kind == 1:
            cv2.circle(tex, (int(p[0]), int(p[1])), int(rng.integers(5, s // 6)), col, -1)
        else:
            q = rng.integers(0, s, 2)
            cv2.line(tex, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), col, int(rng.integers(2, 7)))
    return tex * (1 + 0.05 * fbm(rng, s, 5, 16))[..., None]


def _books(rng, s):
    n = int(rng.integers(20, 35))
    widths = rng.uniform(0.5, 1.5, n)
    edges = np.concatenate([[0], np.cumsum(widths)]) / widths.sum() * s
    x = np.arange(s)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n - 1)
    cols = rng.uniform(0.08, 0.85, (n, 3)).astype(np.float32)
    tex = np.repeat(cols[idx][None], s, axis=0)
    # a light label band on some spines
    band = (np.arange(s) > s * 0.3) & (np.arange(s) < s * 0.4)
    tex[band] = tex[band] * 0.4 + 0.55 * (rng.uniform(0, 1, n)[idx] > 0.5)[None, :, None]
    return tex * (1 + 0.08 * fbm(rng, s, 5, 16))[..., None]


def _metal(rng, s):
    base = rng.uniform(0.45, 0.7) * np.ones(3, np.float32)
    brushed = cv2.resize(fbm(rng, s, 4, 16)[:, : s // 16], (s, s), interpolation=cv2.INTER_LINEAR)
    return base * (1 + 0.1 * brushed)[..., None] * np.ones((s, s, 3), np.float32)


def _fabric(rng, s):
    base = rng.uniform(0.15, 0.75, 3).astype(np.float32)
    y, x = np.mgrid[0:s, 0:s].astype(np.float32)
    weave = 0.5 + 0.25 * (np.sin(2 * np.pi * x * 64 / s) + np.sin(2 * np.pi * y * 64 / s))
    return base * (0.85 + 0.15 * weave + 0.08 * fbm(rng, s, 5, 8))[..., None]


def _dark(rng, s):
    # black counter tops, screens: low albedo (and low IR return, see noise.py)
    base = rng.uniform(0.03, 0.08) * np.ones(3, np.float32)
    speck = (fbm(rng, s, 2, 64) > 1.8).astype(np.float32)
    return base * (1 + 0.3 * fbm(rng, s, 5, 8))[..., None] + 0.25 * speck[..., None]


_MAKERS = {
    "wood": _wood,
    "tiles": _tiles,
    "carpet": _carpet,
    "plaster": _plaster,
    "poster": _poster,
    "books": _books,
    "metal": _metal,
    "fabric": _fabric,
    "dark": _dark,
}


def make_texture(kind: str, rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A tileable albedo texture of kind ``kind`` (one of :data:`TEXTURE_KINDS`).

    Returns:
        (size, size, 3) float32 RGB albedo in [0, 1].
    """
    if kind not in _MAKERS:
        raise ValueError(f"unknown texture kind {kind!r}; known: {', '.join(TEXTURE_KINDS)}")
    if size < 64:
        raise ValueError(f"texture size must be >= 64, got {size}")
    return np.clip(_MAKERS[kind](rng, size), 0.0, 1.0).astype(np.float32)
