# SPDX-License-Identifier: Apache-2.0
"""``pugsd.core.camera``: the downsampled camera (``PinholeCamera.scaled``) against the
pixel-centre convention, with skew and an off-centre principal point."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.core.camera import PinholeCamera


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_a_scaled_pixel_sees_the_ray_through_the_centre_of_its_block(factor: int) -> None:
    """Pixel (v', u') of the image downsampled by ``factor`` averages the full-resolution block
    ``[f u', f u' + f) x [f v', f v' + f)``, whose centre is ``(f u' + (f - 1) / 2, f v' + (f - 1) / 2)``:
    the scaled camera's ray there is the full camera's ray through that centre, for every pixel,
    with skew, fx != fy and a principal point off the image centre (odd sizes: the last partial
    block is dropped, ``W // f``)."""
    cam = PinholeCamera(fx=523.0, fy=497.0, cx=301.7, cy=255.2, width=641, height=483, skew=13.0)
    sc = cam.scaled(factor)
    assert (sc.width, sc.height) == (641 // factor, 483 // factor)
    v, u = np.mgrid[0 : sc.height, 0 : sc.width].astype(np.float64)
    c = (factor - 1) / 2.0
    expected = cam.rays_at(factor * v + c, factor * u + c)
    np.testing.assert_allclose(sc.rays(), expected, rtol=1e-12, atol=1e-12)
    # the skew is in pixels: it scales with the focal lengths
    assert sc.skew == pytest.approx(13.0 / factor, rel=1e-15)
