# SPDX-License-Identifier: Apache-2.0
"""Progress bars with an ETA for the long commands (``evaluate``, ``bench``, ``replay``,
``play``): tqdm on stderr, shown only when stderr is a terminal, so logs, pipes and tests stay
clean."""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


def progress_bar(total: float | None, desc: str, unit: str = "it", quiet: bool = False) -> Any:
    """A tqdm bar on stderr; off when ``quiet`` or when stderr is not a terminal. ``total`` None:
    a count and a rate, without an ETA."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        file=sys.stderr,
        disable=True if quiet else None,  # None: off unless the file is a terminal
        dynamic_ncols=True,
    )


@contextmanager
def ticking(bar: Any, every_s: float = 1.0) -> Iterator[Any]:
    """``bar`` redrawn every ``every_s`` while the block runs, so that its elapsed time counts on
    through a long step that updates nothing."""
    stop = threading.Event()

    def tick() -> None:
        while not stop.wait(every_s):
            bar.refresh()

    th = None if bar.disable else threading.Thread(target=tick, name="progress", daemon=True)
    if th is not None:
        th.start()
    try:
        yield bar
    finally:
        stop.set()
        if th is not None:
            th.join()
        bar.close()
