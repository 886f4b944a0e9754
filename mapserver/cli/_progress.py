"""A progress bar on stderr for long commands."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

SHOW_AFTER_S = 0.5
"""A command that ends sooner shows no bar (and does not load tqdm)."""


def progress_bar(description: str) -> tuple[Callable[[int, int], None], Callable[[], None]]:
    """Return ``(update(done, total), close())`` driving a tqdm bar on stderr, shown once SHOW_AFTER_S have passed."""
    bar: Any = None
    started = time.monotonic()

    def update(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            if time.monotonic() - started < SHOW_AFTER_S:
                return
            from tqdm import tqdm

            bar = tqdm(total=total, desc=description, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=False)
        bar.n = done
        if done == total or done % 10 == 0:
            bar.refresh()

    def close() -> None:
        if bar is not None:
            bar.close()

    return update, close
