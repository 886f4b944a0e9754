"""Output helpers shared by the commands: JSON result line and stderr progress."""

from __future__ import annotations

import json
import sys
from typing import Any


def emit_json(result: dict[str, Any]) -> None:
    """Print ``result`` as exactly one JSON object on the last line of stdout."""
    sys.stdout.write(json.dumps(result, sort_keys=False, default=_default) + "\n")
    sys.stdout.flush()


def info(message: str) -> None:
    """Print a human-readable progress line on stderr."""
    sys.stderr.write(message + "\n")
    sys.stderr.flush()


def _default(value: Any) -> Any:
    """Convert numpy scalars and arrays for JSON."""
    if hasattr(value, "tolist"):
        return value.tolist()
    msg = f"not JSON serialisable: {type(value).__name__}"
    raise TypeError(msg)
