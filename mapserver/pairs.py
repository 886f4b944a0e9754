"""The ``KEY=VALUE[,KEY=VALUE…]`` syntax of the command line's ``--topics``, ``--param`` and ``--set``."""

from __future__ import annotations

from collections.abc import Iterable

from mapserver.errors import InputError


def parse_pairs(
    texts: str | Iterable[str], *, flag: str, form: str, example: str, error: type[Exception] = InputError
) -> dict[str, str]:
    """Return ``{key: value}`` from comma-separated ``KEY=VALUE`` pairs (one text, or the texts of a repeated flag).

    Keys and values are stripped; empty entries are skipped; a value may be empty. Values are not
    interpreted here (each flag's caller does that).

    Raises:
        error: an entry without ``=`` or without a key (``bad FLAG entry 'x': expected FORM, e.g. EXAMPLE``),
            or a key given twice (``bad FLAG: 'k' given twice``).
    """
    result: dict[str, str] = {}
    for text in [texts] if isinstance(texts, str) else texts:
        for raw in text.split(","):
            part = raw.strip()
            if not part:
                continue
            key, sep, value = part.partition("=")
            key = key.strip()
            if not sep or not key:
                msg = f"bad {flag} entry {part!r}: expected {form}, e.g. {example}"
                raise error(msg)
            if key in result:
                msg = f"bad {flag}: {key!r} given twice"
                raise error(msg)
            result[key] = value.strip()
    return result
