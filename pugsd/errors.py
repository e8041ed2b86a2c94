# SPDX-License-Identifier: Apache-2.0
"""Exception hierarchy: every error pugsd raises on purpose is a :class:`PugsdError`."""

from __future__ import annotations


class PugsdError(Exception):
    """Root of all pugsd errors; the CLI maps these to exit codes and clear messages."""


class ConfigError(PugsdError):
    """Unknown key, wrong type or out-of-range value in a configuration (message has the dotted path)."""


class InputError(PugsdError):
    """Bad input data handed to the pipeline."""


class ImageSizeError(InputError):
    """An image has the wrong shape or does not match its camera / its stereo partner."""


class PoseError(InputError):
    """A pose is non-finite or not a rigid transform."""


class CovarianceError(InputError):
    """A covariance is non-finite, non-symmetric or not positive semi-definite."""


class EmptyCloudError(InputError):
    """A stage received no valid points."""


class ModelNotReadyError(PugsdError):
    """The SVGP has not been trained enough to give uncertainty."""


class Preempted(PugsdError):
    """A computation gave way part-way because its caller's ``should_stop`` said so (not a
    failure: its result would have been superseded)."""


class DecodeError(PugsdError):
    """A wire message (CDR, packet, file) could not be decoded. ``reason``, when set, is the
    countable class of the failure, fixed by the code (the message may quote text from the wire)."""

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason


class ArmError(PugsdError):
    """The arm refused or failed a command."""


class PortInUseError(ArmError):
    """The arm's serial port is held by another process (a running daemon)."""


class SafetyError(ArmError):
    """A motion was refused by a safety check (workspace, limits, reachability, distance)."""
