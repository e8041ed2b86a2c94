# SPDX-License-Identifier: Apache-2.0
"""A finite pose covariance near the float64 limit: the frame check must not overflow it into an
infinite covariance, and Eq. 3 must not hand a non-finite Gaussian to the point store.

A PoseWithCovarianceStamped whose covariance was ``1.5e308 * I`` passed the wire decoder (which
judges it scaled), then ``check_covariance`` returned ``0.5 * (C + C^T)`` = inf, and integrating
the frame wrote non-finite means and covariances into the point store before a scipy ValueError
(an internal error, not a counted rejection): every later frame failed until a reset.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pugsd.config import CoreConfig, ObservationConfig
from pugsd.core.camera import PinholeCamera
from pugsd.core.observation import Observation
from pugsd.core.pipeline import PugsPipeline
from pugsd.core.types import DepthFrame, check_covariance
from pugsd.errors import CovarianceError
from pugsd.wire import codec

_CAM = PinholeCamera(50.0, 50.0, 15.5, 11.5, 32, 24)


def _depth_frame(stamp_ns: int, pose_cov: np.ndarray, depth_m: float = 1.0) -> DepthFrame:
    T = np.eye(4)
    T[:3, 3] = (0.3, -0.2, 0.1)
    return DepthFrame(stamp_ns, np.full((24, 32), depth_m, np.float32), _CAM, T, pose_cov=pose_cov)


@settings(max_examples=300, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(
    arrays(np.float64, (6, 6), elements=st.floats(-1.0, 1.0)),
    st.floats(1e-300, 1.7976931348623157e308),
)
def test_check_covariance_never_returns_a_non_finite_matrix(A: np.ndarray, scale: float) -> None:
    """Any finite matrix: a CovarianceError or a finite symmetric result (never inf from overflow)."""
    for C in (A * scale, (A @ A.T) / 6.0 * scale, np.diag(np.abs(np.diag(A))) * scale):
        try:
            out = check_covariance(C, 6, "pose_cov")
        except CovarianceError:
            continue
        assert np.all(np.isfinite(out)) and np.array_equal(out, out.T)


def test_a_covariance_at_the_float64_limit_stays_finite() -> None:
    for C in (np.eye(6) * 1.5e308, np.full((6, 6), 1.0e308)):
        out = check_covariance(C, 6, "pose_cov")
        assert np.all(np.isfinite(out)) and np.allclose(out / 1e308, C / 1e308)


def test_a_wire_covariance_that_overflows_eq3_is_refused_and_the_store_is_kept() -> None:
    data = codec.encode_pose_with_covariance(2, np.eye(4), np.eye(6) * 1.5e308)
    huge = codec.decode_pose_with_covariance(data).cov
    assert huge is not None
    frame = _depth_frame(2, huge)  # the frame check keeps it finite
    assert np.all(np.isfinite(frame.pose_cov))
    with pytest.raises(CovarianceError, match="non-finite covariance"):
        Observation(ObservationConfig(), 0.001).backproject(frame)

    pipe = PugsPipeline(CoreConfig())
    good = np.eye(6) * 1e-6
    pipe.integrate(_depth_frame(1, good))
    n = pipe.store._n
    with pytest.raises(CovarianceError):
        pipe.integrate(frame)
    assert pipe.store._n == n
    for name in ("_mu", "_cov", "_prec", "_logdet"):
        assert np.all(np.isfinite(getattr(pipe.store, name)[:n])), name
    assert pipe.integrate(_depth_frame(3, good, depth_m=1.01)) > 0  # the map goes on
