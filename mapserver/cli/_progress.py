"""A progress bar on stderr for long commands."""

from __future__ import annotations

import sys
from collections.abc import Callable

from tqdm import tqdm


def progress_bar(description: str) -> tuple[Callable[[int, int], None], Callable[[], None]]:
    """Return ``(update(done, total), close())`` driving a tqdm bar on stderr."""
    bar: tqdm | None = None

    def update(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc=description, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=False)
        bar.n = done
        if done == total or done % 10 == 0:
            bar.refresh()

    def close() -> None:
        if bar is not None:
            bar.close()

    return update, close
