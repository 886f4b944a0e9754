"""core: the RatSLAM-family SLAM engine (pure computation, no I/O).

Public surface::

    from core import Engine, Params, preset, load_config, Motion
    engine = Engine(preset("irat"))
    result = engine.step(image, motion, stamp_s)
    state = engine.snapshot(); Engine.restore(params, state)

The names load on first use (PEP 562), so importing ``core.config`` alone (the CLI's parsers) does not load
the engine and its libraries.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from core.config import ConfigError, Params, load_config, params_from_dict, preset
    from core.engine import Action, Engine, StepResult
    from core.links import LinkKind
    from core.localview import ImageError
    from core.motion import Motion
    from core.paths import ExperienceGraph, NoPath, PathResult

_WHERE = {
    "Action": "core.engine",
    "ConfigError": "core.config",
    "Engine": "core.engine",
    "ExperienceGraph": "core.paths",
    "ImageError": "core.localview",
    "LinkKind": "core.links",
    "Motion": "core.motion",
    "NoPath": "core.paths",
    "Params": "core.config",
    "PathResult": "core.paths",
    "StepResult": "core.engine",
    "load_config": "core.config",
    "params_from_dict": "core.config",
    "preset": "core.config",
}

__all__ = [
    "Action",
    "ConfigError",
    "Engine",
    "ExperienceGraph",
    "ImageError",
    "LinkKind",
    "Motion",
    "NoPath",
    "Params",
    "PathResult",
    "StepResult",
    "load_config",
    "params_from_dict",
    "preset",
]


def __getattr__(name: str) -> Any:
    """Import the module that defines ``name`` on first use and return it."""
    module = _WHERE.get(name)
    if module is None:
        msg = f"module 'core' has no attribute {name!r}"
        raise AttributeError(msg)
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
