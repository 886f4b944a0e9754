"""Choosing the engine parameters for a run: preset, config file, or the log's scenario.json."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from core import Params, load_config, preset
from core.config import ConfigError, params_from_dict
from mapserver.pairs import parse_pairs

logger = logging.getLogger(__name__)

DEFAULT_PRESET = "circle"


def resolve_params(
    preset_name: str | None = None, config: str | Path | None = None, log: str | Path | None = None
) -> Params:
    """Return the parameters named by ``preset_name`` or loaded from ``config``.

    With neither, a ``scenario.json`` written by ``mapserver simulate`` beside the log
    names the preset that suits it; otherwise :data:`DEFAULT_PRESET` is used.

    Raises:
        ConfigError: both given, unknown preset, unreadable or invalid config file.
    """
    if preset_name and config:
        msg = "give either --preset or --config, not both"
        raise ConfigError(msg)
    if config:
        return load_config(config)
    if preset_name:
        return preset(preset_name)
    suggested = _scenario_preset(log)
    return preset(suggested or DEFAULT_PRESET)


def _scenario_preset(log: str | Path | None) -> str | None:
    if log is None:
        return None
    path = Path(log)
    scenario = (path if path.is_dir() else path.parent) / "scenario.json"
    if not scenario.is_file():
        scenario = path.parent / "scenario.json"
    try:
        name = json.loads(scenario.read_text(encoding="utf-8")).get("preset")
    except (OSError, ValueError, AttributeError):
        return None
    if isinstance(name, str):
        logger.info("using preset %r from %s", name, scenario)
        return name
    return None


def with_frontend(params: Params, backbone: str | None = None, weights: str | Path | None = None) -> Params:
    """Return ``params`` with the CLI's ``--backbone`` / ``--weights`` applied to the neocortical front-end.

    Raises:
        ConfigError: a weights file that does not exist, weights without a backbone, or an invalid name.
    """
    changes: dict[str, str] = {}
    if backbone:
        changes["frontend_backbone"] = backbone
    if weights:
        if not Path(weights).is_file():
            msg = f"weights file not found: {str(weights)!r}"
            raise ConfigError(msg)
        changes["frontend_weights"] = str(weights)
    if not changes:
        return params
    updated = params.replace(**changes)
    if updated.frontend != "sdr-htm":
        msg = "--backbone/--weights apply to the sdr-htm front-end: use --preset poseidon or neoslam"
        raise ConfigError(msg)
    if updated.frontend_weights and updated.frontend_backbone == "none":
        msg = "--weights needs a CNN backbone: --backbone shufflenetv2 or alexnet (or frontend_backbone in the config)"
        raise ConfigError(msg)
    return updated


def with_settings(params: Params, settings: str | None) -> Params:
    """Return ``params`` with ``--set KEY=VALUE[,KEY=VALUE…]`` applied (on top of the preset or config file).

    Values take the key's type as in a config file (``1``/``true`` for a flag).

    Raises:
        ConfigError: an item without ``=``, a key given twice, an unknown key (the closest valid one is named) or an
            invalid value.
    """
    if not settings:
        return params
    values = parse_pairs(settings, flag="--set", form="KEY=VALUE", example="vt_shift_heading=1", error=ConfigError)
    return params_from_dict(values, params, where="--set")


def require_storable(params: Params) -> Params:
    """Return ``params`` if the store can keep the maps they make; not the neuroslam engine's, nor PC-MLIF's.

    Raises:
        ConfigError: ``engine = neuroslam`` (its grid and head-direction cells have no tables in the store), or
            ``pc_model = mlif`` (the store's ``map_states.pc_activity`` holds one CAN lattice; the two spiking
            networks' activities, potentials and memristor states have no columns).
    """
    if params.engine != "ratslam":
        msg = f"maps of the {params.engine} engine cannot be stored in a database yet: process with --out MAP.json"
        raise ConfigError(msg)
    if params.pc_model != "can":
        msg = "maps of the mlif pose cells cannot be stored in a database yet: process with --out MAP.json"
        raise ConfigError(msg)
    return params
