"""The engine snapshot as typed parts: one dataclass per concept, the owner of the snapshot's key names.

``Engine.snapshot()`` returns plain arrays keyed by name (docs/architecture.md, "Engine state snapshot"), the
form the store writes. This module owns those names: a part's key is its ``PREFIX`` followed by the field's
name (``ExperienceMapSnapshot.link_from`` is ``em_link_from``), and :meth:`EngineSnapshot.from_arrays` /
:meth:`EngineSnapshot.to_arrays` convert at the store's boundary without touching an array (the same objects
go in and come out, so the round trip is bit for bit; the keys come back in the order they went in).

A part's optional fields (``None`` by default) are keys that older snapshots, or merged snapshots before the
engine restored them, may lack: ``None`` means the key is absent. Keys no part names (other front-ends' and
pose-cell models' arrays: ``nc_*``, ``ns_*``, ``ml_*``, …) travel untouched in
:attr:`EngineSnapshot.extra`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np

Arrays = Mapping[str, np.ndarray]


class MissingKeysError(KeyError):
    """A snapshot lacks keys a part requires; ``keys`` lists them (in schema order)."""

    def __init__(self, keys: list[str]) -> None:
        super().__init__(", ".join(keys))
        self.keys = keys


@dataclass(eq=False)
class _Part:
    """A group of snapshot arrays whose keys are ``PREFIX`` + field name."""

    PREFIX: ClassVar[str] = ""

    @classmethod
    def key(cls, name: str) -> str:
        """Return the snapshot key of field ``name`` (raises KeyError for a name the part lacks)."""
        if name not in cls.field_names():
            raise KeyError(name)
        return cls.PREFIX + name

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Return the part's field names in schema order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def all_keys(cls) -> tuple[str, ...]:
        """Return every key of the part, in schema order."""
        return tuple(cls.PREFIX + name for name in cls.field_names())

    @classmethod
    def required_keys(cls) -> tuple[str, ...]:
        """Return the keys a snapshot must hold for this part (fields without a default)."""
        return tuple(
            cls.PREFIX + f.name
            for f in dataclasses.fields(cls)
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        )

    @classmethod
    def optional_keys(cls) -> tuple[str, ...]:
        """Return the keys older snapshots may lack (fields defaulting to None)."""
        required = set(cls.required_keys())
        return tuple(key for key in cls.all_keys() if key not in required)

    @classmethod
    def missing(cls, arrays: Arrays) -> list[str]:
        """Return the required keys ``arrays`` lacks."""
        return [key for key in cls.required_keys() if key not in arrays]

    @classmethod
    def from_arrays(cls, arrays: Arrays) -> Self:
        """Return the part read from ``arrays`` (the arrays themselves, uncopied); MissingKeysError if incomplete."""
        missing = cls.missing(arrays)
        if missing:
            raise MissingKeysError(missing)
        return cls(**{name: arrays[cls.PREFIX + name] for name in cls.field_names() if cls.PREFIX + name in arrays})

    def items(self) -> Iterator[tuple[str, np.ndarray]]:
        """Yield (key, array) of every field that is present (not None), in schema order."""
        for name in self.field_names():
            value = getattr(self, name)
            if value is not None:
                yield self.PREFIX + name, value

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the present fields as snapshot arrays (the same objects, uncopied)."""
        return dict(self.items())

    def replace(self, **changes: Any) -> Self:
        """Return a copy with ``changes`` (field name → array) applied."""
        return dataclasses.replace(self, **changes)


@dataclass(eq=False)
class ViewSnapshot(_Part):
    """The view cells and the engine's per-template records (keys ``lv_*``; ``sdr``: the ``sdr-htm`` codes)."""

    PREFIX: ClassVar[str] = "lv_"
    templates: np.ndarray
    means: np.ndarray
    current: np.ndarray
    previous: np.ndarray
    relative_rad: np.ndarray
    origin: np.ndarray
    place: np.ndarray | None = None
    place_offset: np.ndarray | None = None
    place_yaw: np.ndarray | None = None
    sdr: np.ndarray | None = None


@dataclass(eq=False)
class OdometrySnapshot(_Part):
    """The visual odometry's previous profiles (keys ``vo_*``)."""

    PREFIX: ClassVar[str] = "vo_"
    prev_vtrans: np.ndarray
    prev_vrot: np.ndarray


@dataclass(eq=False)
class PoseCellSnapshot(_Part):
    """The continuous-attractor pose cells and their view links (keys ``pc_*``)."""

    PREFIX: ClassVar[str] = "pc_"
    activity: np.ndarray
    best: np.ndarray
    link_template: np.ndarray
    link_coords: np.ndarray
    link_strength: np.ndarray
    link_decay: np.ndarray
    current_vt: np.ndarray
    prev_vt: np.ndarray
    vt_delta_th: np.ndarray


@dataclass(eq=False)
class ExperienceMapSnapshot(_Part):
    """The experience map: experiences, links, the robot's place and the relaxation's state (keys ``em_*``)."""

    PREFIX: ClassVar[str] = "em_"
    pose: np.ndarray
    pc: np.ndarray
    template: np.ndarray
    stamp: np.ndarray
    origin: np.ndarray
    link_from: np.ndarray
    link_to: np.ndarray
    link_transform: np.ndarray
    link_dt: np.ndarray
    link_distance: np.ndarray
    link_kind: np.ndarray
    current: np.ndarray
    previous: np.ndarray
    accum: np.ndarray
    relax_pending: np.ndarray
    pc_lever: np.ndarray | None = None
    link_active: np.ndarray | None = None
    robust_checked: np.ndarray | None = None
    stored_links: np.ndarray | None = None
    relax_queue: np.ndarray | None = None
    reckon_from: np.ndarray | None = None
    reckon_to: np.ndarray | None = None
    reckon_link: np.ndarray | None = None
    reckon: np.ndarray | None = None
    last_created: np.ndarray | None = None

    def link_status(self) -> np.ndarray:
        """Return (n_links,) bool: each link's status (``link_active``; links it lists none for are on)."""
        count = np.asarray(self.link_from).reshape(-1).shape[0]
        active = np.ones(count, dtype=bool)
        given = np.asarray(self.link_active if self.link_active is not None else np.zeros(0, dtype=bool), dtype=bool)
        given = given.reshape(-1)
        active[: min(given.size, count)] = given[:count]
        return active

    def levers(self, n: int) -> np.ndarray:
        """Return (n,) float64 ``pc_lever`` fitted to n experiences (0 past its end or when absent)."""
        out = np.zeros(n, dtype=np.float64)
        given = np.asarray(self.pc_lever if self.pc_lever is not None else np.zeros(0), dtype=np.float64)
        given = given.reshape(-1)[:n]
        out[: given.size] = given
        return out

    def reckoning_links(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the reckoning links (from (k,) int64, to (k,) int64, odometry (k, 6) float64); none when absent."""
        return (
            np.asarray(self.reckon_from if self.reckon_from is not None else np.zeros(0), dtype=np.int64).reshape(-1),
            np.asarray(self.reckon_to if self.reckon_to is not None else np.zeros(0), dtype=np.int64).reshape(-1),
            np.asarray(
                self.reckon_link if self.reckon_link is not None else np.zeros((0, 6)), dtype=np.float64
            ).reshape(-1, 6),
        )


@dataclass(eq=False)
class GateSnapshot(_Part):
    """The event gate's recent templates and counters (keys ``gate_*``)."""

    PREFIX: ClassVar[str] = "gate_"
    history: np.ndarray
    state: np.ndarray


@dataclass(eq=False)
class CountersSnapshot(_Part):
    """The engine's own counters (keys ``eng_*``)."""

    PREFIX: ClassVar[str] = "eng_"
    frames: np.ndarray
    last_stamp: np.ndarray
    loop_closures: np.ndarray | None = None


_PARTS: tuple[tuple[str, type[_Part]], ...] = (
    ("view", ViewSnapshot),
    ("odometry", OdometrySnapshot),
    ("pose_cells", PoseCellSnapshot),
    ("map", ExperienceMapSnapshot),
    ("gate", GateSnapshot),
    ("counters", CountersSnapshot),
)


@dataclass(eq=False)
class EngineSnapshot:
    """A whole engine snapshot as typed parts.

    ``pose_cells`` is None for pose-cell models other than the continuous attractor (their ``ns_*``/``ml_*``
    arrays are in ``extra``). ``extra`` holds every key no part names, untouched; ``order`` the keys in the
    order :meth:`from_arrays` read them, so that :meth:`to_arrays` gives them back in that order (keys added
    since follow in schema order).
    """

    view: ViewSnapshot
    odometry: OdometrySnapshot
    pose_cells: PoseCellSnapshot | None
    map: ExperienceMapSnapshot
    gate: GateSnapshot
    counters: CountersSnapshot
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    order: tuple[str, ...] = ()

    @staticmethod
    def all_keys() -> tuple[str, ...]:
        """Return every key a part names, in schema order."""
        return tuple(key for _, part in _PARTS for key in part.all_keys())

    @staticmethod
    def required_keys(pose_cells: bool = True) -> tuple[str, ...]:
        """Return the keys every snapshot holds (with the continuous-attractor pose cells unless told not)."""
        return tuple(key for name, part in _PARTS if pose_cells or name != "pose_cells" for key in part.required_keys())

    @staticmethod
    def optional_keys() -> tuple[str, ...]:
        """Return the keys older snapshots may lack."""
        return tuple(key for _, part in _PARTS for key in part.optional_keys())

    @classmethod
    def from_arrays(cls, arrays: Arrays) -> EngineSnapshot:
        """Return the typed snapshot of ``arrays`` (the arrays themselves); MissingKeysError when incomplete.

        The pose-cell part is read when any ``pc_*`` key it names is present, else it is None.
        """
        pose_cells = any(key in arrays for key in PoseCellSnapshot.all_keys())
        missing = [key for key in cls.required_keys(pose_cells) if key not in arrays]
        if missing:
            raise MissingKeysError(missing)
        named = set(cls.all_keys())
        return cls(
            view=ViewSnapshot.from_arrays(arrays),
            odometry=OdometrySnapshot.from_arrays(arrays),
            pose_cells=PoseCellSnapshot.from_arrays(arrays) if pose_cells else None,
            map=ExperienceMapSnapshot.from_arrays(arrays),
            gate=GateSnapshot.from_arrays(arrays),
            counters=CountersSnapshot.from_arrays(arrays),
            extra={key: value for key, value in arrays.items() if key not in named},
            order=tuple(arrays),
        )

    def parts(self) -> Iterator[_Part]:
        """Yield the parts that are present, in schema order."""
        for name, _ in _PARTS:
            part = getattr(self, name)
            if part is not None:
                yield part

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the snapshot as plain arrays: the keys read in their order, then new ones in schema order."""
        arrays: dict[str, np.ndarray] = {}
        for part in self.parts():
            arrays.update(part.items())
        arrays.update(self.extra)
        ordered = {key: arrays[key] for key in self.order if key in arrays}
        ordered.update((key, value) for key, value in arrays.items() if key not in ordered)
        return ordered

    def replace(self, **changes: Any) -> EngineSnapshot:
        """Return a copy with ``changes`` (part name → part, ``extra``, ``order``) applied."""
        return dataclasses.replace(self, **changes)
