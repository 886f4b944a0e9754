"""Engine parameters: the typed set, presets and OpenRatSLAM / OpenRatSLAM2 config loading."""

from core.config._loaders import load_config, params_from_dict
from core.config._params import ConfigError, Departure, Params
from core.config._presets import PRESETS, preset

__all__ = ["PRESETS", "ConfigError", "Departure", "Params", "load_config", "params_from_dict", "preset"]
