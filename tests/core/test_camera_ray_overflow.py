# SPDX-License-Identifier: Apache-2.0
"""Intrinsics whose pixel rays overflow float64 (a subnormal focal length such as 5e-324 from a
CameraInfo, or cx near the float64 limit) are an InputError, so a CameraInfo carrying them is a
counted ``bad_camera_info`` rejection. They passed ``fx > 0``; a depth frame of that camera gave
infinite points, and as the map's first frame it left non-finite Gaussians in the point store
(scipy ValueError) and anchored the voxel hash at garbage: every later frame was refused."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pugsd.core.camera import PinholeCamera
from pugsd.errors import DecodeError, InputError
from pugsd.wire import codec

FINITE = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=400, deadline=None, derandomize=True, database=None)
@given(FINITE, FINITE, FINITE, FINITE, st.integers(1, 4096), st.integers(1, 4096), FINITE)
def test_a_camera_either_is_refused_or_has_finite_rays(
    fx: float, fy: float, cx: float, cy: float, w: int, h: int, skew: float
) -> None:
    try:
        cam = PinholeCamera(fx, fy, cx, cy, min(w, 64), min(h, 64), skew)
    except InputError:
        return
    with np.errstate(all="ignore"):
        assert np.all(np.isfinite(cam.rays()))


@pytest.mark.parametrize(
    ("fx", "fy", "cx", "cy"),
    [(5e-324, 50.0, 15.5, 11.5), (50.0, 1e-310, 15.5, 11.5), (1e-3, 50.0, 1.7e308, 11.5)],
)
def test_a_camera_info_whose_rays_overflow_is_a_decode_error(
    fx: float, fy: float, cx: float, cy: float
) -> None:
    cam = PinholeCamera.__new__(PinholeCamera)  # as on the wire, without the validation
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": 32, "height": 24, "skew": 0.0}
    for name, v in values.items():
        object.__setattr__(cam, name, v)
    data = codec.encode_camera_info(cam, 1, "depth")
    with pytest.raises(DecodeError, match="rays overflow"):
        codec.decode_camera_info(data)


def test_ordinary_cameras_are_kept() -> None:
    for args in (
        (1e-3, 1e-3, 0.0, 0.0, 1, 1),
        (500.0, 500.0, 320.0, 240.0, 640, 480),
        (1e-9, 1e-9, 1e3, 1e3, 64, 64),
    ):
        assert np.all(np.isfinite(PinholeCamera(*args).rays()))
