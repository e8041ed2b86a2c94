# SPDX-License-Identifier: Apache-2.0
"""``pugsd.sim.texture``: value noise interpolates its lattice values, is smooth (C1)
across cell faces, stays in [0, 1); the fractal texture stays in [0, 1] and is seeded."""

from __future__ import annotations

import numpy as np

from pugsd.sim.texture import _hash3, fractal_texture, value_noise

CELL_M = 0.02


def test_value_noise_takes_the_lattice_value_at_a_lattice_point() -> None:
    """At ``k * cell`` every interpolation weight is 0 or 1: the noise is the hash of k there."""
    k = np.random.default_rng(0).integers(-50, 50, (200, 3))
    got = value_noise(k * CELL_M, CELL_M, seed=3)
    np.testing.assert_allclose(got, _hash3(k[:, 0], k[:, 1], k[:, 2], 3), rtol=0, atol=1e-12)


def test_value_noise_is_smooth_across_cell_faces() -> None:
    """Crossing a cell face (x = k cell) the noise is continuous with zero slope along x (smoothstep
    weights): the values 1e-5 cells either side differ by O(1e-10), not O(1e-5) as linear weights
    would give, nor O(1) as a jump would. Half a cell in it is continuous too (at most 1.5 x the
    step, with its slope of at most 1.5 per cell) and not flat (the test would pass on a constant)."""
    rng = np.random.default_rng(1)
    face = np.c_[rng.integers(-20, 20, 500) * CELL_M, rng.uniform(-0.3, 0.3, (500, 2))]
    e = np.array([1e-5 * CELL_M, 0.0, 0.0])
    jump = np.abs(value_noise(face + e, CELL_M) - value_noise(face - e, CELL_M))
    assert jump.max() < 1e-8
    mid = face + np.array([0.5 * CELL_M, 0.0, 0.0])
    slope = np.abs(value_noise(mid + e, CELL_M) - value_noise(mid - e, CELL_M))
    assert np.median(slope) > 1e-6 and slope.max() < 1.5 * 2e-5 * (1 + 1e-6)


def test_textures_stay_in_range_and_depend_on_the_seed() -> None:
    """Value noise lies in [0, 1) and spreads over it; the contrast-stretched fractal texture is
    clipped to [0, 1] and reaches both ends; another seed gives another texture, the same seed the
    same one."""
    p = np.random.default_rng(2).uniform(-1.0, 1.0, (20_000, 3))
    v = value_noise(p, CELL_M, seed=5)
    assert v.min() >= 0.0 and v.max() < 1.0 and v.min() < 0.1 and v.max() > 0.9
    t = fractal_texture(p, base_cell_m=0.05, octaves=5, seed=5)
    assert t.min() == 0.0 and t.max() == 1.0
    assert 0.4 < t.mean() < 0.6
    np.testing.assert_array_equal(fractal_texture(p, 0.05, 5, seed=5), t)
    assert np.abs(fractal_texture(p, 0.05, 5, seed=6) - t).mean() > 0.1
