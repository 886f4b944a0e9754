"""The engine's typed parameter set, with OpenRatSLAM's key names."""

from __future__ import annotations

import dataclasses
import difflib
import typing
from dataclasses import dataclass
from typing import Any


class ConfigError(ValueError):
    """A parameter, preset or configuration file is invalid (one-line message)."""


@dataclass(frozen=True)
class Params:
    """Every engine parameter, typed, with OpenRatSLAM's code defaults (anchors §1.1)."""

    # local view
    image_crop_x_min: int = 0
    image_crop_x_max: int = -1
    image_crop_y_min: int = 0
    image_crop_y_max: int = -1
    template_x_size: int = 1
    template_y_size: int = 1
    vt_match_threshold: float = 0.03
    vt_shift_match: int = 25
    vt_step_match: int = 5
    vt_normalisation: float = 0.0
    vt_patch_normalise: int = 0
    vt_min_patch_normalisation_std: float = 0.0
    vt_panoramic: bool = False
    vt_active_decay: float = 1.0
    vt_mean_prefilter_epsilon: float = 0.005
    vt_min_inject_age: int = 10
    # pose cells
    pc_dim_xy: int = 21
    pc_dim_th: int = 36
    pc_dim_z: int = 1
    pc_w_e_dim: int = 7
    pc_w_i_dim: int = 5
    pc_w_e_var: float = 1.0
    pc_w_i_var: float = 2.0
    pc_global_inhib: float = 0.00002
    pc_vt_inject_energy: float = 0.15
    pc_cell_x_size: float = 1.0
    pc_cell_z_size: float = 1.0
    pc_vt_restore: float = 0.05
    pc_cells_to_avg: int = 3
    # experience map
    exp_delta_pc_threshold: float = 2.0
    exp_correction: float = 0.5
    exp_loops: int = 10
    exp_initial_em_deg: float = 90.0
    exp_relax_tolerance: float = 1e-4
    exp_relax_batch: int = 64
    max_correction_norm: float = 0.0
    max_correction_step: float = 0.0
    # visual odometry
    vtrans_image_x_min: int = 0
    vtrans_image_x_max: int = -1
    vtrans_image_y_min: int = 0
    vtrans_image_y_max: int = -1
    vrot_image_x_min: int = 0
    vrot_image_x_max: int = -1
    vrot_image_y_min: int = 0
    vrot_image_y_max: int = -1
    camera_fov_deg: float = 50.0
    camera_hz: float = 10.0
    vtrans_scaling: float = 100.0
    vtrans_max: float = 20.0
    # PoseidonSLAM back-end
    vpr_guard: bool = False
    vpr_window: int = 26
    vpr_min_rep: int = 3
    vpr_leak_rate: int = 20
    motion_gate: bool = False
    min_event_trans_xy: float = 0.12
    min_event_dz: float = 0.05
    sync_stale_sec: float = 0.75
    # multisession merge
    merge_confirm: int = 3

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def lattice_rank(self) -> int:
        """Return 3 for an (x, y, th) lattice, 4 for (x, y, z, th)."""
        return 3 if self.pc_dim_z <= 1 else 4

    @property
    def lattice_shape(self) -> tuple[int, ...]:
        """Return the pose-cell array shape, axes (x, y, [z,] th)."""
        if self.lattice_rank == 3:
            return (self.pc_dim_xy, self.pc_dim_xy, self.pc_dim_th)
        return (self.pc_dim_xy, self.pc_dim_xy, self.pc_dim_z, self.pc_dim_th)

    def to_dict(self) -> dict[str, Any]:
        """Return the parameters as a JSON-able dict with OpenRatSLAM key names."""
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> Params:
        """Return a copy with ``changes`` applied and validated.

        Raises:
            ConfigError: an unknown key (the closest valid key is named) or an invalid value.
        """
        for key in changes:
            if key not in FIELD_NAMES:
                raise ConfigError(unknown_key_message(key))
        coerced = {key: coerce(key, value) for key, value in changes.items()}
        return dataclasses.replace(self, **coerced)


FIELD_TYPES: dict[str, type] = dict(typing.get_type_hints(Params))
FIELD_NAMES = frozenset(FIELD_TYPES)


def unknown_key_message(key: str, where: str = "") -> str:
    """Return "unknown parameter 'k' (did you mean 'x'?)" with the closest valid key."""
    close = difflib.get_close_matches(key, sorted(FIELD_NAMES), n=1, cutoff=0.5)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    place = f" in {where}" if where else ""
    return f"unknown parameter {key!r}{place}{hint}"


def coerce(key: str, value: Any) -> Any:
    """Convert ``value`` to the type of field ``key`` (strings from INI files included)."""
    kind = FIELD_TYPES[key]
    try:
        if kind is bool:
            if isinstance(value, str):
                text = value.strip().lower()
                if text in ("1", "true", "yes", "on"):
                    return True
                if text in ("0", "false", "no", "off"):
                    return False
                raise ValueError(text)
            return bool(value)
        if kind is int:
            if isinstance(value, str):
                value = float(value.strip())
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return int(value)
        if kind is float:
            return float(value.strip() if isinstance(value, str) else value)
    except (TypeError, ValueError) as err:
        msg = f"parameter {key!r}: {value!r} is not a valid {kind.__name__}"
        raise ConfigError(msg) from err
    return value


def _validate(p: Params) -> None:
    def fail(key: str, why: str) -> None:
        msg = f"parameter {key!r} = {getattr(p, key)!r}: {why}"
        raise ConfigError(msg)

    for key in ("template_x_size", "template_y_size", "vt_step_match", "pc_dim_z", "exp_loops", "exp_relax_batch"):
        if getattr(p, key) < (0 if key == "exp_loops" else 1):
            fail(key, "must be at least 1" if key != "exp_loops" else "must be ≥ 0")
    if p.pc_dim_xy < 3:
        fail("pc_dim_xy", "must be at least 3")
    if p.pc_dim_th < 2:
        fail("pc_dim_th", "must be at least 2")
    for key in ("pc_w_e_dim", "pc_w_i_dim"):
        if getattr(p, key) < 1 or getattr(p, key) % 2 == 0:
            fail(key, "must be an odd number of cells ≥ 1")
    for key in ("pc_w_e_var", "pc_w_i_var", "pc_cell_x_size", "pc_cell_z_size", "camera_hz"):
        if not getattr(p, key) > 0:
            fail(key, "must be > 0")
    for key in ("vt_match_threshold", "vt_shift_match", "vt_normalisation", "vt_patch_normalise",
                "pc_global_inhib", "pc_vt_inject_energy", "pc_vt_restore", "exp_delta_pc_threshold",
                "exp_relax_tolerance", "max_correction_norm", "max_correction_step", "vt_min_inject_age",
                "vt_active_decay", "pc_cells_to_avg", "min_event_trans_xy", "min_event_dz", "sync_stale_sec"):
        if getattr(p, key) < 0:
            fail(key, "must be ≥ 0")
    if not 0 < p.exp_correction <= 1:
        fail("exp_correction", "must be in (0, 1]")
    if not 1 <= p.vpr_min_rep <= p.vpr_window:
        fail("vpr_min_rep", f"must be in 1..vpr_window ({p.vpr_window})")
    if p.vpr_leak_rate < 1:
        fail("vpr_leak_rate", "must be ≥ 1")
    if p.merge_confirm < 1:
        fail("merge_confirm", "must be ≥ 1")
    for axis in ("x", "y"):
        lo, hi = getattr(p, f"image_crop_{axis}_min"), getattr(p, f"image_crop_{axis}_max")
        if lo < 0 or (hi != -1 and hi <= lo):
            fail(f"image_crop_{axis}_max", f"must be -1 or greater than image_crop_{axis}_min ({lo})")
