"""Colours (the named palette, sRGB <-> linear) and the procedural albedo textures."""

from __future__ import annotations

import math
from typing import Dict, Tuple

import numpy as np

PALETTE: Dict[str, Tuple[int, int, int]] = {
    "red": (200, 40, 40),
    "orange": (235, 130, 30),
    "yellow": (230, 200, 40),
    "green": (60, 160, 60),
    "teal": (30, 150, 150),
    "blue": (40, 80, 200),
    "purple": (130, 60, 170),
    "pink": (230, 120, 170),
    "white": (235, 235, 228),
    "brown": (130, 80, 40),
    "black": (35, 35, 38),
    "grey": (140, 140, 140),
}


def srgb_to_linear(srgb_uint8: np.ndarray) -> np.ndarray:
    c = np.asarray(srgb_uint8, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb_uint8(linear: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    s = np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1.0 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def _shade(srgb: Tuple[int, int, int], factor: float) -> Tuple[int, int, int]:
    """Darker (factor < 1) or lighter (factor > 1, towards white) variant of a colour."""
    c = np.asarray(srgb, dtype=np.float64)
    out = c * factor if factor <= 1.0 else c + (255.0 - c) * (factor - 1.0)
    r, g, b = (int(v) for v in np.clip(np.round(out), 0, 255))
    return r, g, b


def _value_noise(rng: np.random.Generator, size: Tuple[int, int], cells: int) -> np.ndarray:
    """Smooth tileable noise in [0,1] (bilinear interpolation of a periodic random grid)."""
    h, w = size
    grid = rng.random((cells, cells))
    ys = np.arange(h) * cells / h
    xs = np.arange(w) * cells / w
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    fy, fx = (ys - y0)[:, None], (xs - x0)[None, :]
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    y1, x1 = (y0 + 1) % cells, (x0 + 1) % cells
    a = grid[y0][:, x0]
    b = grid[y0][:, x1]
    c = grid[y1][:, x0]
    d = grid[y1][:, x1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def make_texture(rng: np.random.Generator, size: Tuple[int, int], base_a, base_b, checks: int, dots: int) -> np.ndarray:
    """A feature-rich, tileable albedo texture: two-tone checker, smooth noise and coloured dots."""
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    checker = ((yy * checks // h + xx * checks // w) % 2).astype(bool)
    img = np.where(checker[..., None], np.asarray(base_b, np.float32), np.asarray(base_a, np.float32))
    noise = 0.75 + 0.5 * (0.6 * _value_noise(rng, size, 8) + 0.4 * _value_noise(rng, size, 32))
    img = img * noise[..., None].astype(np.float32)
    for _ in range(dots):
        cy, cx = rng.random(2) * (h, w)
        radius = rng.uniform(0.006, 0.02) * min(h, w)
        colour = rng.uniform(30, 230, size=3)
        reach = int(math.ceil(radius)) + 1
        rows = np.arange(int(cy) - reach, int(cy) + reach + 1)
        cols = np.arange(int(cx) - reach, int(cx) + reach + 1)
        disc = (rows[:, None] - cy) ** 2 + (cols[None, :] - cx) ** 2 <= radius * radius
        window = img[np.ix_(rows % h, cols % w)]
        window[disc] = colour
        img[np.ix_(rows % h, cols % w)] = window
    # stored like an 8-bit sRGB texture file, then linearised for the renderer
    lut = srgb_to_linear(np.arange(256)).astype(np.float32)
    return lut[np.clip(np.round(img), 0, 255).astype(np.uint8)]
