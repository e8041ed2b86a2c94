# SPDX-License-Identifier: Apache-2.0
"""The streaming SVGP's learning-rate scale (``OccupancySVGP.set_rate_scale``): what it scales,
that one step moves every parameter by exactly the scale, and that decaying rates let a model
with nothing new to learn settle (the daemon's idle training, ``daemon.idle_rate_decay_steps``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pugsd.config import SvgpConfig
from pugsd.core.predictive import OccupancySVGP
from tests.core.test_predictive import _field  # the known field the SVGP tests learn


def _data(n: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.1, 0.1, (n, 3))
    x[:, 2] *= 0.1
    return x, _field(x) + 0.02 * rng.standard_normal(n)


def _model(steps: int = 40, **cfg: object) -> tuple[OccupancySVGP, np.ndarray, np.ndarray]:
    x, y = _data()
    m = OccupancySVGP(SvgpConfig(num_inducing=32, seed=0, batch_size=256, **cfg))  # type: ignore[arg-type]
    m.update(x, y, np.arange(len(x)), steps=steps)
    return m, x, y


NONE = np.zeros(0, dtype=np.int64)  # no new points: no inducing-point moves, steps only


def _rates(m: OccupancySVGP) -> tuple[list[float], list[float]]:
    assert m._ngd is not None and m._adam is not None
    return [g["lr"] for g in m._ngd.param_groups], [g["lr"] for g in m._adam.param_groups]


def test_the_scale_multiplies_every_streaming_rate_and_outlives_new_optimizers() -> None:
    m, x, y = _model()
    cfg = m.cfg
    assert m.rate_scale == 1.0
    assert _rates(m) == ([cfg.ngd_lr], [cfg.adam_lr, cfg.inducing_lr])
    m.set_rate_scale(0.25)
    assert _rates(m) == ([0.25 * cfg.ngd_lr], [0.25 * cfg.adam_lr, 0.25 * cfg.inducing_lr])
    # a step failure makes fresh optimizers: they run at the scaled rates too
    m._recover(RuntimeError("test"), len(x))
    assert _rates(m) == ([0.25 * cfg.ngd_lr], [0.25 * cfg.adam_lr, 0.25 * cfg.inducing_lr])
    m.set_rate_scale(1.0)
    assert _rates(m) == ([cfg.ngd_lr], [cfg.adam_lr, cfg.inducing_lr])
    # a reset starts the next model at the configured rates
    m.set_rate_scale(0.5)
    m.reset()
    assert m.rate_scale == 1.0
    m.update(x, y, np.arange(len(x)), steps=1)
    assert _rates(m) == ([cfg.ngd_lr], [cfg.adam_lr, cfg.inducing_lr])


def test_a_model_that_grows_keeps_the_scale() -> None:
    """``_grow_inducing`` rebuilds the model and its optimizers (more inducing points than the
    first store allowed): the scale carries over."""
    x, y = _data()
    m = OccupancySVGP(SvgpConfig(num_inducing=32, seed=0, batch_size=64))
    m.update(x[:20], y[:20], np.arange(20), steps=2)  # 20 points: 20 inducing points
    m.set_rate_scale(0.125)
    m.update(x, y, np.arange(20, len(x)), steps=1)
    assert m.model is not None and len(m.model.variational_strategy.inducing_points) == 32
    ngd, adam = _rates(m)
    assert ngd == [0.125 * m.cfg.ngd_lr] and adam[0] == 0.125 * m.cfg.adam_lr


def test_the_paper_fit_runs_at_the_papers_rate_whatever_the_scale() -> None:
    m, x, y = _model()
    m.set_rate_scale(0.1)
    m.fit_paper(x, y, epochs=1)
    assert m.rate_scale == 1.0 and m._adam is not None
    assert [g["lr"] for g in m._adam.param_groups] == [m.cfg.paper_lr]


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, math.nan, math.inf])
def test_a_scale_outside_0_1_is_refused(bad: float) -> None:
    m, _, _ = _model(steps=1)
    with pytest.raises(ValueError, match="rate scale"):
        m.set_rate_scale(bad)
    assert m.rate_scale == 1.0


def test_one_step_moves_every_parameter_by_exactly_the_scale() -> None:
    """Two identical models (same data, seed and history, so the same next minibatch and the same
    optimizer state) take one step, at scale 1 and at 0.1: NGD's update is lr N grad and Adam's
    lr m / (sqrt(v) + eps), both linear in the rate, so every parameter moves a tenth as far."""
    a, x, y = _model(steps=30)
    b, _, _ = _model(steps=30)
    before = {k: v.detach().clone() for k, v in a.model.state_dict().items()}  # type: ignore[union-attr]
    for k, v in b.model.state_dict().items():  # type: ignore[union-attr]
        assert torch.equal(v, before[k])
    a.update(x, y, NONE, steps=1)
    b.set_rate_scale(0.1)
    b.update(x, y, NONE, steps=1)
    moved = 0
    for k, v0 in before.items():
        if not v0.is_floating_point():
            continue
        da = a.model.state_dict()[k].double() - v0.double()  # type: ignore[union-attr]
        db = b.model.state_dict()[k].double() - v0.double()  # type: ignore[union-attr]
        if da.abs().max() == 0:
            continue
        moved += 1
        big = da.abs() > 1e-3 * da.abs().max()  # float32 rounding swamps the smallest moves
        np.testing.assert_allclose(db[big].numpy(), 0.1 * da[big].numpy(), rtol=2e-3, err_msg=k)
    # q(u)'s natural parameters, the inducing points and the kernel/likelihood hyperparameters
    assert moved >= 5


def _jitter(m: OccupancySVGP, x: np.ndarray, y: np.ndarray, q: np.ndarray, tau: float) -> float:
    """Median over the query points of |log(var_r / var_{r-1})| between rounds of 4 steps, over
    the last 10 of 30 rounds; the rates decay as 1 / (1 + k / tau) with k the steps taken
    (``tau`` = 0: constant rates)."""
    prev = None
    jumps = []
    k = 0
    for r in range(30):
        for _ in range(4):
            m.set_rate_scale(1.0 / (1.0 + k / tau) if tau > 0 else 1.0)
            m.update(x, y, NONE, steps=1)
            k += 1
        var = m.predict(q)[1]
        if prev is not None and r >= 20:
            jumps.append(np.median(np.abs(np.log(var / prev))))
        prev = var
    return float(np.median(jumps))


def test_decaying_rates_let_a_model_with_nothing_new_to_learn_settle() -> None:
    """The daemon's idle training: from the same trained model, rounds at constant rates keep the
    predictive variance jittering with the minibatches; with the rates decaying (tau = 10 steps,
    scale 0.1 at the end) it moves far less from one round to the next."""
    q = _data(300, seed=5)[0]
    m_const, x, y = _model(steps=150)
    m_decay, _, _ = _model(steps=150)
    const = _jitter(m_const, x, y, q, 0.0)
    decay = _jitter(m_decay, x, y, q, 10.0)
    assert decay < 0.5 * const, (decay, const)
