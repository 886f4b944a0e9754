"""Engine parameters as the store keeps them: a JSON-normalised dict, and the view front-end they name."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from mapserver.errors import StoreError


def plain_params(params: Any) -> dict[str, Any]:
    """Return parameters (a ``core.Params`` or a mapping) as a JSON-normalised dict.

    Raises:
        StoreError: a value is not JSON-serialisable.
    """
    values = params.to_dict() if hasattr(params, "to_dict") else dict(params)
    try:
        result: dict[str, Any] = json.loads(json.dumps(values, allow_nan=True))
    except (TypeError, ValueError) as err:
        msg = f"parameters cannot be stored as JSON: {err}"
        raise StoreError(msg) from err
    return result


def frontend_of(params: Any) -> str:
    """Return the view front-end named by engine parameters (``core.Params`` or its dict)."""
    value = params.get("frontend", "lvc") if isinstance(params, Mapping) else getattr(params, "frontend", "lvc")
    return str(value)
