# SPDX-License-Identifier: Apache-2.0
"""pugsd.errors: the exception hierarchy the command line and the daemon catch, and DecodeError's
reason."""

from __future__ import annotations

from pugsd import errors


def test_the_exception_hierarchy() -> None:
    parents = {
        "ConfigError": "PugsdError",
        "InputError": "PugsdError",
        "ImageSizeError": "InputError",
        "PoseError": "InputError",
        "CovarianceError": "InputError",
        "EmptyCloudError": "InputError",
        "ModelNotReadyError": "PugsdError",
        "DecodeError": "PugsdError",
        "ArmError": "PugsdError",
        "PortInUseError": "ArmError",
        "SafetyError": "ArmError",
        "PugsdError": "Exception",
    }
    for name, parent in parents.items():
        cls = getattr(errors, name)
        assert [b.__name__ for b in cls.__bases__] == [parent], name


def test_a_decode_error_carries_its_reason() -> None:
    e = errors.DecodeError("bad cdr: 'x'", "malformed cdr")
    assert (str(e), e.reason, e.args) == ("bad cdr: 'x'", "malformed cdr", ("bad cdr: 'x'",))
    assert errors.DecodeError("short").reason is None
