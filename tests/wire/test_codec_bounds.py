# SPDX-License-Identifier: Apache-2.0
"""Decoder bounds at their edges: an image with bytes beyond step*height, a cloud field that ends
beyond point_step, a covariance whose smallest eigenvalue is just below zero."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.errors import DecodeError
from pugsd.wire import codec
from pugsd.wire.types import IMAGE, POINT_CLOUD2


def _image(h: int, w: int, step: int, n: int) -> bytes:
    Image = codec.typestore().types[IMAGE]
    data = (np.arange(n) % 251).astype(np.uint8)
    return codec.serialize(
        Image(header=codec._header(1, "x"), height=h, width=w, encoding="mono8", is_bigendian=0,
              step=step, data=data), IMAGE)  # fmt: skip


def test_image_data_must_be_exactly_step_times_height() -> None:
    """4 x 4 mono8 with rows padded to 5 bytes: 20 bytes decode (the padding dropped), 19 and 21
    are refused as DecodeErrors (more data than the rows hold is no valid image either)."""
    img = codec.decode_image(_image(4, 4, 5, 20))
    np.testing.assert_array_equal(img.array, np.arange(20, dtype=np.uint8).reshape(4, 5)[:, :4])
    for n in (19, 21, 40):
        with pytest.raises(DecodeError, match=r"data has \d+ bytes, expected step\*height = 5\*4 = 20"):
            codec.decode_image(_image(4, 4, 5, n))


def test_a_cloud_field_must_end_within_the_point() -> None:
    """point_step 20 (x, y, z, sigma2_occ, pugs_confidence float32): a field at offset 16 reads the
    4 bytes of pugs_confidence; at 17 or 18 its last bytes lie beyond the point (the last point's
    beyond the buffer): refused."""
    pts = np.arange(9, dtype=np.float64).reshape(3, 3)
    good = codec.encode_cloud(pts, 1, pugs_confidence=np.array([0.25, 0.5, 0.75]))
    m = codec.deserialize(good, POINT_CLOUD2)
    assert int(m.point_step) == 20
    m.fields[0].offset = 16  # x read from pugs_confidence's bytes: the last valid offset
    c = codec.decode_cloud(codec.serialize(m, POINT_CLOUD2))
    np.testing.assert_array_equal(c.fields["x"], np.array([0.25, 0.5, 0.75], np.float32))
    for off in (17, 18, 20):
        m.fields[0].offset = off
        with pytest.raises(DecodeError, match=f"offset {off} beyond point_step"):
            codec.decode_cloud(codec.serialize(m, POINT_CLOUD2))


@pytest.mark.parametrize("excess", [1e-8, 1e-4])
def test_a_correlation_just_above_one_is_not_a_covariance(excess: float) -> None:
    """x and y correlated with coefficient 1 + excess: eigenvalue -excess (relative to the
    largest entry). Refused; exactly 1 (rank-deficient, PSD) is accepted."""
    T = np.eye(4)
    C = np.eye(6) * 1e-2
    C[0, 1] = C[1, 0] = 1e-2
    ok = codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, C))
    assert ok.cov is not None and np.array_equal(ok.cov, C)
    C[0, 1] = C[1, 0] = 1e-2 * (1.0 + excess)
    with pytest.raises(DecodeError, match="covariance is not positive semi-definite"):
        codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, C))
