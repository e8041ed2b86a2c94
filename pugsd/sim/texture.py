# SPDX-License-Identifier: Apache-2.0
"""Procedural 3D texture: multi-octave value noise on hashed lattice points.

The texture is a function of the world point only, so the left and right views of a surface see the
same pattern (what stereo matching needs) and the ground truth stays exact.
"""

from __future__ import annotations

import numpy as np

_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xBF58476D1CE4E5B9)
_M3 = np.uint64(0x94D049BB133111EB)


def _hash3(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """A value in [0, 1) per integer lattice point (splitmix64 of the packed coordinates)."""
    with np.errstate(over="ignore"):
        h = (
            ix.astype(np.uint64) * np.uint64(73856093)
            ^ iy.astype(np.uint64) * np.uint64(19349663)
            ^ iz.astype(np.uint64) * np.uint64(83492791)
            ^ (np.uint64(seed) * _M1)
        )
        h = (h ^ (h >> np.uint64(30))) * _M2
        h = (h ^ (h >> np.uint64(27))) * _M3
        h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / float(1 << 53))


def value_noise(points: np.ndarray, cell_m: float, seed: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1) with lattice spacing ``cell_m`` at ``points`` (N, 3)."""
    p = np.asarray(points, dtype=np.float64) / cell_m
    base = np.floor(p)
    f = p - base
    f = f * f * (3.0 - 2.0 * f)  # smoothstep
    b = base.astype(np.int64)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        wx = f[:, 0] if dx else 1.0 - f[:, 0]
        for dy in (0, 1):
            wy = f[:, 1] if dy else 1.0 - f[:, 1]
            for dz in (0, 1):
                wz = f[:, 2] if dz else 1.0 - f[:, 2]
                out += wx * wy * wz * _hash3(b[:, 0] + dx, b[:, 1] + dy, b[:, 2] + dz, seed)
    return out


def fractal_texture(
    points: np.ndarray, base_cell_m: float = 0.03, octaves: int = 4, seed: int = 0
) -> np.ndarray:
    """Multi-octave value noise in [0, 1]: cells ``base_cell_m``, /2, /4, ... (weights 1, 0.6, 0.36, ...)."""
    total = np.zeros(np.asarray(points).shape[0])
    norm = 0.0
    for o in range(octaves):
        w = 0.6**o
        total += w * value_noise(points, base_cell_m / (2.0**o), seed + 101 * o)
        norm += w
    t = total / norm
    # stretch the contrast (sums of noise concentrate around 0.5)
    return np.clip(0.5 + 2.2 * (t - 0.5), 0.0, 1.0)
