"""core: the RatSLAM-family SLAM engine (pure computation, no I/O).

Public surface::

    from core import Engine, Params, preset, load_config, Motion
    engine = Engine(preset("irat"))
    result = engine.step(image, motion, stamp_s)
    state = engine.snapshot(); Engine.restore(params, state)
"""

from core.config import ConfigError, Params, load_config, params_from_dict, preset
from core.engine import Action, Engine, StepResult
from core.experience_map import LinkKind
from core.localview import ImageError
from core.motion import Motion
from core.paths import ExperienceGraph, NoPath, PathResult

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
