# SPDX-License-Identifier: Apache-2.0
"""Fixtures shared by the arm tests."""

from __future__ import annotations

import pytest

from pugsd.arm.config import ArmConfig
from pugsd.arm.controller import model_from_config
from pugsd.arm.kinematics import Bravo7Model


@pytest.fixture(scope="module")
def model() -> Bravo7Model:
    """The Bravo 7 kinematic model of the default arm config."""
    return model_from_config(ArmConfig())
