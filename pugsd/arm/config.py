# SPDX-License-Identifier: Apache-2.0
"""Config section of the Bravo 7 arm interface."""

from __future__ import annotations

from dataclasses import dataclass

from pugsd.configbase import opt


@dataclass(frozen=True, slots=True)
class ArmConfig:
    """Reach Bravo 7 arm: disabled unless enabled here."""

    enabled: bool = opt(False, "allow arm commands at all")
    transport: str = opt("serial", "link to the arm", choices=("serial", "udp", "can"))
