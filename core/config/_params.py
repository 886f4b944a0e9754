"""The engine's typed parameter set, with OpenRatSLAM's key names."""

from __future__ import annotations

import dataclasses
import difflib
import enum
import functools
import math
import re
import typing
from dataclasses import dataclass
from typing import Any


class ConfigError(ValueError):
    """A parameter, preset or configuration file is invalid (one-line message)."""


class Departure(enum.StrEnum):
    """A part of the engine whose code departs from OpenRatSLAM's (``openratslam_parts``: those run as OpenRatSLAM's).

    Each module docstring says what its departure does and why: ``odometry``, ``link_dt`` and ``relaxation``
    in :mod:`core.experience_map` (``relaxation``: anchored, bounded per frame, settled to the fixed point at the
    end of a log, with the robust check and links that keep the measured odometry; OpenRatSLAM's: ``exp_loops``
    sweeps after every action), ``translation``, ``injection`` and ``decode`` in :mod:`core.posecells`,
    ``patch`` in :mod:`core.localview`, ``vo_interval`` in :mod:`core.visual_odometry`.
    """

    ODOMETRY = "odometry"
    LINK_DT = "link_dt"
    RELAXATION = "relaxation"
    TRANSLATION = "translation"
    INJECTION = "injection"
    DECODE = "decode"
    PATCH = "patch"
    VO_INTERVAL = "vo_interval"


def parse_departures(text: str) -> frozenset[Departure]:
    """Return the departures named in a list separated by commas or ``+`` (``all``: every one; ``none`` or "": none).

    Raises:
        ConfigError: a name that is not a :class:`Departure` (the valid ones are listed).
    """
    names = [name.strip().lower() for name in re.split(r"[,+]", text) if name.strip()]
    if names == ["all"]:
        return frozenset(Departure)
    if names in ([], ["none"]):
        return frozenset()
    unknown = [name for name in names if name not in Departure.__members__.values()]
    if unknown:
        valid = ", ".join(d.value for d in Departure)
        msg = f"parameter 'openratslam_parts': unknown part {unknown[0]!r} (valid: all, none, {valid})"
        raise ConfigError(msg)
    return frozenset(Departure(name) for name in names)


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
    vt_shift_heading: bool = False  # a forward view's best column shift gives its heading offset (not OpenRatSLAM)
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
    pc_model: str = "can"  # can: rate-coded attractor lattice; mlif: PC-MLIF spiking networks (core.mlif)
    # experience map
    exp_delta_pc_threshold: float = 2.0
    exp_correction: float = 0.5
    exp_loops: int = 10
    exp_initial_em_deg: float = 90.0
    exp_relax_tolerance: float = 1e-4
    exp_relax_batch: int = 64
    max_correction_norm: float = 0.0
    max_correction_step: float = 0.0
    # robust relaxation (core.robust): switch off loop/merge links inconsistent with the graph
    exp_robust: bool = True
    exp_relax_joint: bool = False  # settle and the robust check on the joint least squares (not OpenRatSLAM)
    exp_loop_weight: float = 0.3  # the joint least squares weighs a loop or merge link by this (odometry link: 1)
    exp_settle_joint: bool = True  # settle ends on the joint least squares; the robust check stays on RatSLAM's
    exp_robust_view: bool = True  # a view link's z counts the view match's own uncertainty (core.robust.Drift.of)
    exp_robust_drift: float = 0.1  # expected odometry drift, metres per metre travelled
    exp_robust_yaw_drift: float = 0.1  # radians per metre travelled
    exp_robust_threshold: float = 4.0  # outlier when the normalised residual exceeds this
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
    merge_evidence_m: float = -1.0  # net agreeing metres before a merge; −1: the map's scale; 0: K matches only
    merge_probation_m: float = -1.0  # metres a merge keeps verifying itself; −1: auto (map scale); 0: no verification
    merge_probation_max_m: float = -1.0  # metres a probation whose matches never stop lasts; −1: by front-end
    merge_miss_weight: float = -1.0  # a miss on mapped ground counts this many hits; −1: by front-end (Params docs)
    merge_sv_min_intersection: int = 8  # sdr-htm merge evidence: I_min of a stored map's cortex reading the session
    merge_sv_enable_f1_gate: bool = False  # sdr-htm merge evidence: the F1 gate of that reading
    merge_sdr_min_overlap: float = 0.68  # sdr-htm merge evidence: a frame's SDR shares this share of a view cell's code
    merge_sdr_null_quantile: float = 0.0  # sdr-htm: raise it to this quantile of the map's look-alikes (0: off)
    merge_lattice_slack: float = 0.2  # cells of closure gate per cell between a merged experience and its merge anchor
    merge_view_heading: bool = True  # closures and ties joining two sessions, closures of a merged map: view's heading
    merge_relax_joint: bool = True  # a merged map (a merge link, or two sessions' experiences): joint least squares
    # OpenRatSLAM's code behaviour wherever the engine departs from it (differential tests; README)
    openratslam_compat: bool = False
    openratslam_parts: str = "translation,injection,decode"  # departures run as OpenRatSLAM's code (Departure names)
    # neocortical front-end (PoseidonSLAM §4.2.2 / NeoSLAM): "lvc" intensity templates or "sdr-htm"
    frontend: str = "lvc"
    frontend_backbone: str = "none"  # none (weight-free: LVC template through LSBH) | shufflenetv2 | alexnet
    frontend_weights: str = ""  # torchvision state-dict file for the backbone (never downloaded)
    frontend_device: str = "auto"  # auto (CUDA when present) | cpu | cuda
    lsbh_bits: int = 2048  # L: SDR length per modality (two halves of L/2)
    lsbh_s: float = 0.25  # k = floor(s·L/2) top and bottom projections (Eq. 4.2)
    lsbh_seed: int = 42
    sp_columns: int = 2048
    sp_num_active_columns: int = 20
    sp_potential_radius: int = 600
    sp_potential_pct: float = 0.5
    sp_syn_perm_connected: float = 0.2
    sp_syn_perm_active_inc: float = 0.006
    sp_syn_perm_inactive_dec: float = 0.008
    sp_boost_strength: float = 0.0
    sp_duty_cycle_period: int = 1000
    sp_learn: bool = True
    tm_cells_per_column: int = 40
    tm_activation_threshold: int = 5
    tm_min_threshold: int = 3
    tm_initial_permanence: float = 0.55
    tm_connected_permanence: float = 0.5
    tm_max_new_synapse_count: int = 20
    tm_max_synapses_per_segment: int = 32
    tm_permanence_increment: float = 0.008
    tm_permanence_decrement: float = 0.012
    tm_predicted_segment_decrement: float = 0.0
    sv_descriptor_source: str = "tm"  # tm: TM winner cells (sequence memory); sp: SP columns (ablation)
    sv_tm_window: int = 7
    sv_tm_topk: int = 15
    interval_mode: bool = True
    theta_alpha: float = 0.65
    theta_rho: int = 3
    sv_tm_match_threshold: float = 0.30
    sv_min_intersection: int = 12
    sv_enable_f1_gate: bool = True
    min_f1: float = 0.55
    sv_use_iou_tiebreak: bool = True
    # engine: "ratslam" (pose cells on an (x, y, [z,] θ) lattice) or "neuroslam" (Yu et al. 2019: grid cells and
    # multilayer head-direction cells, core.neuroslam); the gc_/hdc_ keys are NeuroSLAM's Tables 5–6 (SynPerData)
    engine: str = "ratslam"
    gc_dim_xy: int = 36
    gc_dim_z: int = 36
    gc_excite_size: int = 7
    gc_excite_var: float = 1.5
    gc_inhibit_size: int = 5
    gc_inhibit_var: float = 2.0
    gc_global_inhib: float = 0.0002
    gc_vt_inject_energy: float = 0.1
    gc_packet_size: int = 4
    gc_cell_size: float = 1.0  # metres per grid cell in the plane
    gc_cell_size_z: float = 1.0  # metres per grid cell in height
    hdc_dim_yaw: int = 36
    hdc_dim_height: int = 36
    hdc_excite_size: int = 8
    hdc_excite_var: float = 1.9
    hdc_inhibit_size: int = 5
    hdc_inhibit_var: float = 3.0
    hdc_global_inhib: float = 0.0002
    hdc_vt_inject_energy: float = 0.001
    hdc_packet_size: int = 5
    hdc_cell_size_height: float = 1.0  # metres per head-direction cell in height
    vt_global_decay: float = 0.1  # NeuroSLAM: every template's novelty decay recovers this much a frame

    def __post_init__(self) -> None:
        _validate(self)

    @functools.cached_property
    def _openratslam_parts(self) -> frozenset[Departure]:
        return frozenset(Departure) if self.openratslam_compat else parse_departures(self.openratslam_parts)

    def follows_openratslam(self, part: Departure) -> bool:
        """Return whether ``part`` runs as OpenRatSLAM's code (``openratslam_compat``, or in ``openratslam_parts``)."""
        return part in self._openratslam_parts

    @property
    def miss_weight(self) -> float:
        """Return the merge test's miss weight: ``merge_miss_weight``, or for −1 the front-end's own.

        Wald's log-likelihood ratios of a frame on mapped ground, log((1 − p₀)/(1 − p₁)) / log(p₁/p₀), with
        p₁ the chance that a true alignment's predicted place is recognised and p₀ that a look-alike is:
        ``lvc`` p₁ = 0.9, p₀ = 0.25 → 2.0 (the ratio is 1.57; 2 was chosen and every figure measured with it);
        ``sdr-htm`` matching the view cells' codes (``merge_sdr_min_overlap``: p₁ 0.88–1.0 measured on
        ``cave3d``, ``symmetric``, ``twin-overlap``) as ``lvc``; a stored ``sdr-htm`` map without codes (made
        before ``lv_sdr``), read by its cortex at the merge gates ``merge_sv_*``: p₁ = 0.4 (measured on
        ``cave3d``, 0.31–0.55 over 4 seeds), p₀ = 0.02 (no false match in 121 on ``aliased``, bounded) → 0.16.
        """
        return self.miss_weight_reading(codes=self.frontend != "sdr-htm")

    def miss_weight_reading(self, *, codes: bool) -> float:
        """Return :attr:`miss_weight` for a stored map's observations: by code, or by its cortex's descriptors.

        ``codes``: ``lvc`` templates or ``sdr-htm`` view cells' codes; False: a stored ``sdr-htm`` map without
        codes, read by its cortex.
        """
        if self.merge_miss_weight > 0:
            return self.merge_miss_weight
        return 2.0 if codes else 0.16

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
        if kind is str:
            return "" if value is None else str(value).strip()  # a YAML key with no value: the empty string
    except (TypeError, ValueError) as err:
        msg = f"parameter {key!r}: {value!r} is not a valid {kind.__name__}"
        raise ConfigError(msg) from err
    return value


def _validate(p: Params) -> None:
    def fail(key: str, why: str) -> None:
        msg = f"parameter {key!r} = {getattr(p, key)!r}: {why}"
        raise ConfigError(msg)

    _validate_finite(p, fail)
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
    for key in ("exp_robust_drift", "exp_robust_yaw_drift", "exp_robust_threshold", "exp_loop_weight"):
        if not getattr(p, key) > 0:
            fail(key, "must be > 0")
    if not 0 < p.exp_correction <= 1:
        fail("exp_correction", "must be in (0, 1]")
    if not 1 <= p.vpr_min_rep <= p.vpr_window:
        fail("vpr_min_rep", f"must be in 1..vpr_window ({p.vpr_window})")
    if p.vpr_leak_rate < 1:
        fail("vpr_leak_rate", "must be ≥ 1")
    if p.merge_confirm < 1:
        fail("merge_confirm", "must be ≥ 1")
    if not (p.merge_miss_weight > 0 or p.merge_miss_weight == -1.0):
        fail("merge_miss_weight", "must be > 0, or -1 for the front-end's own")
    if p.merge_sv_min_intersection < 1:
        fail("merge_sv_min_intersection", "must be ≥ 1")
    if not 0.0 < p.merge_sdr_min_overlap <= 1.0:
        fail("merge_sdr_min_overlap", "must be in (0, 1]")
    if p.merge_lattice_slack < 0:
        fail("merge_lattice_slack", "must be ≥ 0")
    if not 0.0 <= p.merge_sdr_null_quantile <= 1.0:
        fail("merge_sdr_null_quantile", "must be in [0, 1]")
    for key in ("merge_evidence_m", "merge_probation_m", "merge_probation_max_m"):
        if getattr(p, key) < 0 and getattr(p, key) != -1.0:
            fail(key, "must be ≥ 0 metres, or -1 for the map's scale")
    _validate_frontend(p, fail)
    _validate_neuroslam(p, fail)
    _validate_pc_model(p, fail)
    parse_departures(p.openratslam_parts)
    for axis in ("x", "y"):
        lo, hi = getattr(p, f"image_crop_{axis}_min"), getattr(p, f"image_crop_{axis}_max")
        if lo < 0 or (hi != -1 and hi <= lo):
            fail(f"image_crop_{axis}_max", f"must be -1 or greater than image_crop_{axis}_min ({lo})")


ENGINES = ("ratslam", "neuroslam")


def _validate_neuroslam(p: Params, fail: typing.Callable[[str, str], None]) -> None:
    """NeuroSLAM's networks: sizes, kernels, widths and rates (only read when ``engine = neuroslam``)."""
    if p.engine not in ENGINES:
        fail("engine", f"must be one of {', '.join(ENGINES)}")
    for key in ("gc_dim_xy", "gc_dim_z", "hdc_dim_yaw", "hdc_dim_height", "gc_excite_size", "gc_inhibit_size",
                "hdc_excite_size", "hdc_inhibit_size"):
        if getattr(p, key) < 1:
            fail(key, "must be at least 1")
    for key in ("gc_excite_var", "gc_inhibit_var", "hdc_excite_var", "hdc_inhibit_var", "gc_cell_size",
                "gc_cell_size_z", "hdc_cell_size_height"):
        if not getattr(p, key) > 0:
            fail(key, "must be > 0")
    for key in ("gc_global_inhib", "gc_vt_inject_energy", "gc_packet_size", "hdc_global_inhib",
                "hdc_vt_inject_energy", "hdc_packet_size", "vt_global_decay"):
        if getattr(p, key) < 0:
            fail(key, "must be ≥ 0")
    if p.engine == "neuroslam" and p.frontend != "lvc":
        fail("frontend", "the neuroslam engine takes intensity templates (lvc)")


PC_MODELS = ("can", "mlif")


def _validate_pc_model(p: Params, fail: typing.Callable[[str, str], None]) -> None:
    """The pose-cell model: the CAN lattice or PC-MLIF spiking networks (the latter only for the ratslam engine)."""
    if p.pc_model not in PC_MODELS:
        fail("pc_model", f"must be one of {', '.join(PC_MODELS)}")
    if p.pc_model == "mlif" and p.engine != "ratslam":
        fail("pc_model", "mlif pose cells belong to the ratslam engine")


FRONTENDS = ("lvc", "sdr-htm")
BACKBONES = ("none", "shufflenetv2", "alexnet")


def _validate_finite(p: Params, fail: typing.Callable[[str, str], None]) -> None:
    """Refuse a float key that is NaN (it passes every range check) or ±inf (no setting either)."""
    for field in dataclasses.fields(p):
        value = getattr(p, field.name)
        if isinstance(value, float) and not math.isfinite(value):
            fail(field.name, "must be a finite number")


def _validate_frontend(p: Params, fail: typing.Callable[[str, str], None]) -> None:
    """Check the neocortical front-end's keys (only their ranges; the module checks the weights file)."""
    for key, allowed in (("frontend", FRONTENDS), ("frontend_backbone", BACKBONES),
                         ("frontend_device", ("auto", "cpu", "cuda")), ("sv_descriptor_source", ("tm", "sp"))):
        if getattr(p, key) not in allowed:
            fail(key, f"must be one of {', '.join(allowed)}")
    if p.lsbh_bits < 2 or p.lsbh_bits % 2:
        fail("lsbh_bits", "must be an even number ≥ 2")
    if not 0 < p.lsbh_s <= 0.5 or int(p.lsbh_s * (p.lsbh_bits // 2)) < 1:
        fail("lsbh_s", "must be in (0, 0.5] and give k = floor(s·L/2) ≥ 1")
    for key in ("sp_columns", "sp_num_active_columns", "sp_duty_cycle_period", "tm_cells_per_column",
                "tm_activation_threshold", "tm_max_new_synapse_count", "sv_tm_window", "sv_tm_topk", "theta_rho"):
        if getattr(p, key) < 1:
            fail(key, "must be at least 1")
    if p.sp_num_active_columns > p.sp_columns:
        fail("sp_num_active_columns", f"must be ≤ sp_columns ({p.sp_columns})")
    if not 0 <= p.tm_min_threshold <= p.tm_activation_threshold:
        fail("tm_min_threshold", f"must be in 0..tm_activation_threshold ({p.tm_activation_threshold})")
    if p.tm_max_synapses_per_segment < p.tm_max_new_synapse_count:
        fail("tm_max_synapses_per_segment", f"must be ≥ tm_max_new_synapse_count ({p.tm_max_new_synapse_count})")
    for key in ("sp_potential_pct", "sp_syn_perm_connected", "tm_initial_permanence", "tm_connected_permanence",
                "theta_alpha", "sv_tm_match_threshold", "min_f1"):
        if not 0 <= getattr(p, key) <= 1:
            fail(key, "must be in [0, 1]")
    for key in ("sp_potential_radius", "sp_syn_perm_active_inc", "sp_syn_perm_inactive_dec", "sp_boost_strength",
                "tm_permanence_increment", "tm_permanence_decrement", "tm_predicted_segment_decrement",
                "sv_min_intersection"):
        if getattr(p, key) < 0:
            fail(key, "must be ≥ 0")
