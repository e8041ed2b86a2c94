# SPDX-License-Identifier: Apache-2.0
"""Eq. 7-8 do not depend on where the map's origin is.

The SVGP runs in float32 by default. Fed world coordinates as they are, a map 10 km from its
frame's origin (a UTM-like world frame, which the point store's relative voxel keys are built to
handle) is modelled on a 1 mm float32 grid, and its inducing points, kernel distances and the
sub-millimetre sigma points of Algorithm 1 lose their precision: measured before the fix, the
predictive variance changed by 21 % at a 10 km offset and by 175 % at 100 km. The model works in
coordinates relative to an origin near the data, so a rigidly translated scene gives the same
field."""

from __future__ import annotations

import numpy as np
import pytest

from pugsd.config import SvgpConfig
from pugsd.core.cubature import algorithm1
from pugsd.core.predictive import OccupancySVGP

OFFSET = np.array([12345.678, -23456.789, 3456.123])  # metres; float32 spacing here is 1-2 mm


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    x = rng.uniform(-0.05, 0.05, (600, 3))
    y = np.exp(-(x[:, 0] ** 2) / 0.0005) + 0.3 * np.exp(-((x[:, 1] - 0.02) ** 2) / 0.0002)
    q = rng.uniform(-0.04, 0.04, (40, 3))
    return x, y, q


def _paper(x: np.ndarray, y: np.ndarray) -> OccupancySVGP:
    m = OccupancySVGP(SvgpConfig(num_inducing=64, paper_num_inducing=64))
    m.fit_paper(x, y, epochs=0)
    m.set_optimal_q(x, y)
    return m


def test_a_translated_scene_gives_the_same_field_and_sigma2_occ() -> None:
    """Paper mode with q(u) at its optimum: the same predictions (Eq. 7-8), through a frozen
    snapshot too, and the same Algorithm 1 output for 2 mm sigma points, 15 km from the origin."""
    x, y, q = _scene()
    ref, far = _paper(x, y), _paper(x + OFFSET, y)
    mu0, v0, p0 = ref.predict(q)
    mu1, v1, p1 = far.predict(q + OFFSET)
    np.testing.assert_allclose(mu1, mu0, rtol=0, atol=1e-4 * np.abs(mu0).max())
    np.testing.assert_allclose(v1, v0, rtol=1e-3)
    np.testing.assert_allclose(p1, p0, rtol=1e-3)
    _, v_snap, _ = far.snapshot().predict(q + OFFSET)
    np.testing.assert_allclose(v_snap, v1, rtol=1e-6)
    cov = np.tile(np.eye(3) * 0.002**2, (len(q), 1, 1))

    def run(m: OccupancySVGP, off: np.ndarray) -> np.ndarray:
        return algorithm1(q + off, cov, lambda p: (lambda r: (r[0], r[2]))(m.predict(p)))[1]

    np.testing.assert_allclose(run(far, OFFSET), run(ref, np.zeros(3)), rtol=1e-3)
    # the full-data ELBO is the same number as well
    assert far.elbo_per_point(x + OFFSET, y) == pytest.approx(ref.elbo_per_point(x, y), rel=1e-4)


def test_streaming_a_translated_scene_learns_the_same_field() -> None:
    """Streaming updates (NGD + Adam, inducing points grown and moved) on the translated scene."""
    x, y, q = _scene()
    cfg = SvgpConfig(num_inducing=48, batch_size=256, seed=3)
    out = []
    for off in (np.zeros(3), OFFSET):
        m = OccupancySVGP(cfg)
        m.update(x[:300] + off, y[:300], np.arange(300), steps=10)
        m.update(x + off, y, np.arange(300, 600), steps=10)
        out.append(m.predict(q + off))
    np.testing.assert_allclose(out[1][0], out[0][0], rtol=0, atol=1e-3 * np.abs(out[0][0]).max())
    np.testing.assert_allclose(out[1][1], out[0][1], rtol=1e-2)


def test_observed_variance_is_the_latent_one_plus_the_scaled_noise() -> None:
    """svgp.variance = observed: sigma_z^2 = Var[f] + sigma_n^2, both in the output units (times
    s^2), the same mean, and Eq. 8 on that variance. Catches the noise added after the mapping
    to density units (unscaled), or the option ignored."""
    x, y, q = _scene()
    out = {}
    for variance in ("latent", "observed"):
        m = OccupancySVGP(SvgpConfig(num_inducing=32, paper_num_inducing=32, variance=variance))
        m.fit_paper(x, y, epochs=0)
        m.set_optimal_q(x, y)
        assert m.likelihood is not None
        noise = float(m.likelihood.noise.detach().reshape(-1)[0])
        out[variance] = m.predict(q, scale=3.0)
    s2 = 9.0
    np.testing.assert_allclose(out["observed"][0], out["latent"][0], rtol=1e-6)
    np.testing.assert_allclose(out["observed"][1], out["latent"][1] + noise * s2, rtol=1e-5)
    mu, var, pred = out["observed"]
    np.testing.assert_allclose(pred, var / (1.0 + np.abs(mu)), rtol=1e-12)
    assert noise * s2 > 1e-2 * out["latent"][1].max()  # far above the rtol: the check sees it


def test_the_streaming_origin_follows_a_map_that_moves() -> None:
    """A long transect: the point store forgets the oldest voxels, so the streaming model's data
    can end up kilometres from where its origin was set (float32 at 2-4 km changed variances by
    5-6 %). Once the data's centre is RECENTRE_M away, the origin follows and the inducing points
    are shifted with it: in float64 the model is then the same function of world coordinates to
    rounding (a sign error in the shift would move the whole field), and after the map has moved
    3 km the origin is where the data are."""
    x, y, q = _scene()
    m = OccupancySVGP(SvgpConfig(num_inducing=48, batch_size=256, seed=3, dtype="float64"))
    m.update(x, y, np.arange(len(x)), steps=10)
    np.testing.assert_array_equal(m.origin, np.zeros(3))
    before = m.predict(q)
    m._recentre(np.array([30.0, 0.0, 0.0]))  # under RECENTRE_M: nothing moves
    np.testing.assert_array_equal(m.origin, np.zeros(3))
    m._recentre(np.array([60.0, -70.0, 5.0]))
    np.testing.assert_array_equal(m.origin, [60.0, -70.0, 5.0])
    after = m.predict(q)
    for a, b in zip(after, before, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=0)
    assert m._good_state is not None  # a failure now restores inducing points in these coordinates
    np.testing.assert_allclose(
        m._good_state[0]["variational_strategy.inducing_points"].numpy(),
        m.model.variational_strategy.inducing_points.detach().numpy(),  # type: ignore[union-attr]
    )

    far = np.array([3000.0, 1000.0, 0.0])
    m32 = OccupancySVGP(SvgpConfig(num_inducing=48, batch_size=256, seed=3))
    m32.update(x, y, np.arange(len(x)), steps=5)
    st = m32.update(x + far, y, np.arange(len(x)), steps=5)  # the map has moved on
    np.testing.assert_allclose(m32.origin, far)  # the new data sit near zero in its coordinates
    # the inducing points left 3 km behind describe no data any more: they are re-placed on the
    # new data, and the steps succeed (kept there, float32 kernel distances over a 3 km inducing
    # set made the update fail with NotPSDError, and the model restored its last good state)
    Z = m32.model.variational_strategy.inducing_points.detach().numpy()  # type: ignore[union-attr]
    assert np.abs(Z).max() < 0.1
    assert np.isfinite(st.elbo) and m32.consecutive_failures == 0
