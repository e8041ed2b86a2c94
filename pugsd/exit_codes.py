# SPDX-License-Identifier: Apache-2.0
"""The exit codes of the ``pugsd`` commands (listed in ``pugsd --help`` and the README)."""

OK = 0
FAILURE = 1  # an error: a bad config or file, a refused request, a daemon's error reply
USAGE = 2  # argparse: unknown command or option, a bad value
UNHEALTHY = 3  # `pugsd status`: the daemon answered, unhealthy
NO_PEER = 4  # nobody at the other end: no reply (status, grasps, reset), nothing received (record)
# or delivered to a subscriber (play)
NOT_READY = 5  # `pugsd grasps`: the daemon answered that it has no grasps yet (model not ready, reset)
INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
BROKEN_PIPE = 141  # the reader of stdout went away (128 + SIGPIPE)
