# SPDX-License-Identifier: Apache-2.0
"""The SVGP's training and prediction run with denormals flushed to zero, and only they do."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pugsd.core.config import SvgpConfig
from pugsd.core.predictive import OccupancySVGP, denormals_flushed

TINY = 1e-39  # a float32 denormal


def _denormal_survives() -> bool:
    return bool((torch.tensor([TINY], dtype=torch.float32) * 1.0).item() != 0.0)


@pytest.fixture(autouse=True)
def _needs_ftz() -> None:
    supported = torch.set_flush_denormal(True)
    torch.set_flush_denormal(False)
    if not supported:
        pytest.skip("this CPU has no flush-to-zero mode")


def test_denormals_are_flushed_inside_the_block_and_restored_after() -> None:
    assert _denormal_survives()
    with denormals_flushed():
        assert not _denormal_survives()
        with denormals_flushed():
            assert not _denormal_survives()
        assert not _denormal_survives()  # the inner block's end keeps the outer block's mode
    assert _denormal_survives()


def test_mode_is_restored_when_the_block_raises() -> None:
    with pytest.raises(RuntimeError), denormals_flushed():
        raise RuntimeError("boom")
    assert _denormal_survives()


def test_training_steps_and_predictions_flush_and_leave_the_thread_as_it_was(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    svgp = OccupancySVGP(SvgpConfig(num_inducing=8, batch_size=16))
    seen: list[bool] = []
    step = OccupancySVGP._step

    def spy(self: OccupancySVGP, xb: torch.Tensor, yb: torch.Tensor) -> float:
        seen.append(_denormal_survives())
        return step(self, xb, yb)

    monkeypatch.setattr(OccupancySVGP, "_step", spy)
    x = np.random.default_rng(0).uniform(-0.05, 0.05, (64, 3))
    svgp.update(x, np.ones(len(x)), np.arange(len(x)), steps=3)
    assert seen == [False, False, False]
    assert _denormal_survives()
    mu, var, _ = svgp.predict(x[:4])
    assert np.isfinite(mu).all() and np.isfinite(var).all()
    assert _denormal_survives()
