"""One exception family for mapserver; the CLI and the API map it to exit codes and HTTP statuses.

A preset, configuration file or setting that is invalid raises the engine's own ``core.config.ConfigError``
(a ``ValueError``, one class for core and mapserver); the CLI and the API map it as an :class:`InputError`
(exit 2, HTTP 400).
"""

from __future__ import annotations

import re


class MapServerError(Exception):
    """Root of mapserver's errors (CLI exit 1, HTTP 500 unless a subclass says otherwise)."""

    exit_code = 1
    http_status = 500


class InputError(MapServerError):
    """The user's input is unusable: missing file, not a bag, corrupt, bad parameter (exit 2, HTTP 400)."""

    exit_code = 2
    http_status = 400


class IngestError(InputError):
    """A mission log cannot be read or has no usable topics."""


class LimitError(InputError):
    """The input exceeds one of the configured limits (exit 2, HTTP 413); ``limit`` names it.

    ``limit`` is the limit's key in ``GET /v1/limits`` (e.g. ``max_unpacked_bytes``, ``max_image_pixels``);
    the message names it too, with the value that applied.
    """

    http_status = 413

    def __init__(self, message: str, *, limit: str) -> None:
        super().__init__(message)
        self.limit = limit


class NotFoundError(MapServerError):
    """A named map, session, experience or job does not exist (exit 2, HTTP 404)."""

    exit_code = 2
    http_status = 404


class ConflictError(MapServerError):
    """The request conflicts with stored state, e.g. no path exists or a merge is refused (HTTP 409)."""

    exit_code = 1
    http_status = 409


class StoreError(MapServerError):
    """The database could not complete an operation."""


class MergeError(ConflictError):
    """Two maps cannot be merged (no confirmed match)."""


class NoConfirmedMatchError(MergeError):
    """An offline merge found no confirmed template match: the maps do not connect (exit 2, HTTP 409).

    The contract's ``mapserver merge`` exits 2 with the reason; other refused merges exit 1.
    """

    exit_code = 2


_OPAQUE = (AssertionError, KeyError, IndexError, AttributeError, TypeError, OverflowError)
_ARGS_TUPLE = re.compile(r"""\(\s*(['"])(.*?)\1,?\s*\)""")  # a library's "damaged: ('reason',)"


def describe_cause(err: BaseException, *, limit: int = 200) -> str:
    """Return a one-line reason for a library's error, or ``malformed data`` when it would say nothing useful.

    A library's own message (``Invalid string length 3951624202 at offset 20.``) is kept, shortened to
    ``limit`` characters, with an exception's argument tuple quoted inside it (``damaged: ('reason',)``) reduced
    to its text; undecodable text reads ``malformed text (not UTF-8)``; an assertion, a lookup error's bare key
    or number, an overflow of Python's integers, a message of one word or one spanning several lines (a message
    definition, a traceback) becomes ``malformed data``.
    """
    if isinstance(err, UnicodeDecodeError):
        return "malformed text (not UTF-8)"
    raw = str(err)
    text = _ARGS_TUPLE.sub(lambda m: m.group(2), " ".join(raw.split()))
    opaque = isinstance(err, _OPAQUE) or "\n" in raw.strip() or len(text.split()) < 2
    if opaque or not any(c.isalpha() for c in text):
        return "malformed data"
    return text if len(text) <= limit else text[: limit - 3] + "..."
