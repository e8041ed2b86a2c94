# SPDX-License-Identifier: Apache-2.0
"""The stream engine shared by the daemon, ``pugsd replay`` and the bench: frame assembly, time
sync and the streaming training schedule, pure and synchronous with an injected clock."""
