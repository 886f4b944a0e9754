"""Map names: the one rule a new map's name must follow, and the name a log gives a map by default.

A map name is 1 to 64 characters from ``A-Z a-z 0-9 . _ -``, starting with a letter or a digit
(``MAP_NAME_PATTERN``). The name appears as one segment of REST paths (``/v1/maps/{name}``) and as a
file name of exports, so it holds no ``/``, no ``%``, no space and is never ``.`` or ``..``. Maps stored
under other names before the rule existed stay readable; only new names are checked.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from mapserver.errors import InputError

MAP_NAME_MAX = 64
MAP_NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}"
DERIVED_NAME_MAX = 56
"""A name derived from a log keeps room for a ``-N`` suffix (:func:`unique_map_name` makes it unique)."""

_VALID = re.compile(MAP_NAME_PATTERN)
_INVALID_RUN = re.compile(r"[^A-Za-z0-9._-]+")


def check_map_name(name: str) -> str:
    """Return ``name`` when it is a valid map name (see the module docstring).

    Raises:
        InputError: the name breaks the rule; the message says which characters are allowed.
    """
    if not isinstance(name, str) or _VALID.fullmatch(name) is None:
        shown = name if isinstance(name, str) and len(name) <= 80 else f"{str(name)[:77]}..."
        msg = (
            f"invalid map name {shown!r}: use 1 to {MAP_NAME_MAX} characters from A-Z a-z 0-9 . _ -, "
            "starting with a letter or a digit"
        )
        raise InputError(msg)
    return name


def is_map_name(name: str) -> bool:
    """True when ``name`` follows the map name rule."""
    return isinstance(name, str) and _VALID.fullmatch(name) is not None


def default_map_name(log_path: str | Path) -> str:
    """Return the map name a log gives a new map: its file name up to the first dot, made valid.

    Characters outside the rule become ``_``, leading characters that are not a letter or a digit are
    dropped, the result is cut to ``DERIVED_NAME_MAX`` characters; ``map`` when nothing is left.
    """
    stem = Path(log_path).name.split(".")[0]
    cleaned = _INVALID_RUN.sub("_", stem)
    cleaned = re.sub(r"^[^A-Za-z0-9]+", "", cleaned)[:DERIVED_NAME_MAX]
    return cleaned or "map"


def unique_map_name(base: str, taken: Callable[[str], bool]) -> str:
    """Return ``base``, or the first of ``base-2``, ``base-3``, ... that is not ``taken``.

    ``base`` is cut to ``DERIVED_NAME_MAX`` characters before the suffix, so a valid base gives a valid
    name. ``taken(name)`` says whether a map (or a pending request) holds the name; the caller decides
    which maps count (live only, or archived ones too).
    """
    name, k = base, 2
    while taken(name):
        name, k = f"{base[:DERIVED_NAME_MAX]}-{k}", k + 1
    return name


def log_stem(log_path: str | Path) -> str:
    """Return the name a log gives its session (and the map of ``process`` without a database).

    That is its file name up to the first dot, ``map`` when that is empty; unlike :func:`default_map_name`
    nothing in it is replaced.
    """
    return Path(log_path).name.split(".")[0] or "map"
