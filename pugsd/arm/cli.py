# SPDX-License-Identifier: Apache-2.0
"""Subcommands of this subsystem."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """No subcommands yet."""
