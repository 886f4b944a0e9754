"""Loading OpenRatSLAM INI (``config_*.txt``) and OpenRatSLAM2 ROS 2 YAML parameter files."""

from __future__ import annotations

import configparser
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from core.config._params import FIELD_NAMES, ConfigError, Params, coerce, unknown_key_message

#: Spellings seen in real files, mapped to the canonical key.
ALIASES: Mapping[str, str] = {
    "vt_normalization": "vt_normalisation",
    "vt_patch_normalisation": "vt_patch_normalise",
    "vt_patch_normalization": "vt_patch_normalise",
    "pc_dim_x": "pc_dim_xy",
    "require_vpr_for_event": "vpr_guard",
    "motion_gate_enable": "motion_gate",
}

#: Keys real OpenRatSLAM / OpenRatSLAM2 files carry that the engine does not use: accepted and ignored.
IGNORED_KEYS = frozenset(
    {
        "topic_root", "media_path", "image_file", "enable", "vt_window_width", "vt_window_height",
        "exp_map_size", "posecells_size", "vt_threshold_condition", "use_sim_time", "image_topic",
        "odom_topic", "camera_topic", "pc_vt_inject_energy_scale", "draw", "log_file", "log_level",
        "vt_enable_draw", "pc_enable_draw", "em_enable_draw", "max_goals",
    }
)


def params_from_dict(values: Mapping[str, Any], base: Params | None = None, *, where: str = "") -> Params:
    """Return ``base`` (default ``Params()``) updated with ``values``.

    Raises:
        ConfigError: an unknown key, naming the closest valid one, or an invalid value.
    """
    changes: dict[str, Any] = {}
    unknown: list[str] = []
    for raw_key, value in values.items():
        key = ALIASES.get(str(raw_key).strip(), str(raw_key).strip())
        if key in IGNORED_KEYS:
            continue
        if key not in FIELD_NAMES:
            unknown.append(str(raw_key))
            continue
        changes[key] = coerce(key, value)
    if len(unknown) == 1:
        raise ConfigError(unknown_key_message(unknown[0], where))
    if unknown:
        place = f" in {where}" if where else ""
        msg = f"{len(unknown)} unknown parameters{place}: {', '.join(map(repr, unknown))} (not keys of this engine)"
        raise ConfigError(msg)
    return (base or Params()).replace(**changes)


def load_config(path: str | Path, base: Params | None = None) -> Params:
    """Load an OpenRatSLAM INI ``config_*.txt`` or an OpenRatSLAM2 YAML parameter file as it is.

    Raises:
        ConfigError: missing/unreadable/malformed file, unknown key or invalid value.
    """
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as err:
        msg = f"cannot read config {str(file)!r}: {err.strerror or err}"
        raise ConfigError(msg) from err
    values = _parse_yaml(text, file) if _looks_like_yaml(file, text) else _parse_ini(text, file)
    return params_from_dict(values, base, where=str(file))


def _looks_like_yaml(file: Path, text: str) -> bool:
    if file.suffix.lower() in (".yaml", ".yml"):
        return True
    return "[" not in text.split("\n", 1)[0] and "ros__parameters" in text


def _parse_ini(text: str, file: Path) -> dict[str, Any]:
    parser = configparser.ConfigParser(inline_comment_prefixes=("#", ";"), interpolation=None, strict=False)
    try:
        parser.read_string(text, source=str(file))
    except configparser.Error as err:
        msg = f"malformed config {str(file)!r}: {str(err).splitlines()[0]}"
        raise ConfigError(msg) from err
    values: dict[str, Any] = {}
    for section in parser.sections():
        for key, value in parser.items(section):
            values[key] = value
    return values


def _parse_yaml(text: str, file: Path) -> dict[str, Any]:
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        msg = f"malformed YAML config {str(file)!r}: {str(err).splitlines()[0]}"
        raise ConfigError(msg) from err
    if not isinstance(doc, dict):
        msg = f"config {str(file)!r} is not a mapping of parameters"
        raise ConfigError(msg)
    return _flatten(doc)


def _flatten(doc: Mapping[str, Any]) -> dict[str, Any]:
    """Return the leaf keys of nested YAML sections (node → ros__parameters → group → key), later ones winning."""
    values: dict[str, Any] = {}
    for key, value in doc.items():
        if isinstance(value, dict):
            values.update(_flatten(value))
        else:
            values[key] = value
    return values
