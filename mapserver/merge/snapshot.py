"""Reading engine snapshots (docs/architecture.md schema) and checking that two can be merged."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from core.arrays import IntArray
from core.snapshot import EngineSnapshot, ExperienceMapSnapshot, PoseCellSnapshot
from mapserver.errors import MergeError

if TYPE_CHECKING:
    from core import Params

State = Mapping[str, np.ndarray]

#: The documented keys a merge reads and writes (owned by :mod:`core.snapshot`; docs/architecture.md).
SNAPSHOT_KEYS: tuple[str, ...] = EngineSnapshot.required_keys()

#: Keys a merge writes that older states may lack (``pc_lever``: 0, no merge moved them; ``link_active``:
#: every link on when missing; the reckoning keys: none kept, no experience created since).
OPTIONAL_SNAPSHOT_KEYS: tuple[str, ...] = tuple(
    ExperienceMapSnapshot.key(name)
    for name in ("pc_lever", "link_active", "reckon_from", "reckon_to", "reckon_link", "reckon", "last_created")
)


def check_state(state: State, name: str) -> None:
    """Raise MergeError when a documented snapshot key is missing."""
    missing = [key for key in SNAPSHOT_KEYS if key not in state]
    if missing:
        msg = f"{name} map snapshot lacks {', '.join(missing)}"
        raise MergeError(msg)


def typed_state(state: State, name: str) -> tuple[EngineSnapshot, PoseCellSnapshot]:
    """Return a checked snapshot (:func:`check_state`) as typed parts, and its pose cells."""
    check_state(state, name)
    snapshot = EngineSnapshot.from_arrays(state)
    return snapshot, pose_cells_of(snapshot)


def pose_cells_of(snapshot: EngineSnapshot) -> PoseCellSnapshot:
    """Return a snapshot's continuous-attractor pose cells; MergeError for other pose-cell models."""
    if snapshot.pose_cells is None:
        msg = "only maps of the continuous-attractor pose cells merge"
        raise MergeError(msg)
    return snapshot.pose_cells


def lattice_shape(state: EngineSnapshot) -> tuple[int, ...]:
    """Return the pose-cell lattice shape of a snapshot."""
    return tuple(int(d) for d in np.shape(pose_cells_of(state).activity))


def template_shape(state: EngineSnapshot) -> tuple[int, ...] | None:
    """Return the (ty, tx) template shape of a snapshot, None when it holds no template."""
    templates = np.asarray(state.view.templates)
    if templates.ndim != 3 or templates.shape[0] == 0:
        return None
    return (int(templates.shape[1]), int(templates.shape[2]))


def incompatibility(loaded: EngineSnapshot, partial: EngineSnapshot) -> str | None:
    """Return why two snapshots cannot be merged (lattice or template shapes differ), None if they can."""
    a, b = lattice_shape(loaded), lattice_shape(partial)
    if a != b:
        return f"pose-cell lattices differ: {a!r} and {b!r}"
    ta, tb = template_shape(loaded), template_shape(partial)
    if ta is not None and tb is not None and ta != tb:
        return f"template sizes differ: {ta!r} and {tb!r}"
    return None


def params_incompatibility(loaded: Params, partial: Params, *, reads_frames: bool = False) -> str | None:
    """Return why maps built with these parameters cannot be merged, None if they can.

    The lattice shape, the template size and the matcher's geometry (panoramic or not)
    must agree; the rest (thresholds, energies) may differ between sessions. Maps of the
    ``sdr-htm`` front-end merge only where something compares their views (``reads_frames``: online the
    stored map's cortex reads the session's frames, :mod:`mapserver.merge.cortex`; offline both maps'
    view-cell codes, :func:`mapserver.merge.offline_views.offline_incompatibility`), with the same cortex
    structure.
    """
    if loaded.lattice_shape != partial.lattice_shape:
        return f"pose-cell lattices differ: {loaded.lattice_shape!r} and {partial.lattice_shape!r}"
    if loaded.frontend != partial.frontend:
        return f"view front-ends differ: {loaded.frontend!r} and {partial.frontend!r}"
    if loaded.frontend == "sdr-htm":
        if not reads_frames:
            return ("maps of the sdr-htm front-end merge only where their views are compared (each map's view "
                    "cells are its own HTM's cells): online, or offline by their view cells' codes")
        from mapserver.merge.cortex import structural_difference

        return structural_difference(loaded, partial)
    a = (loaded.template_y_size, loaded.template_x_size)
    b = (partial.template_y_size, partial.template_x_size)
    if a != b:
        return f"template sizes differ: {a!r} and {b!r}"
    if loaded.vt_panoramic != partial.vt_panoramic:
        return "one map uses panoramic template matching and the other does not"
    return None


def experiences_by_template(templates: IntArray, n_templates: int) -> tuple[IntArray, IntArray]:
    """Return (order, starts): experiences of template t are ``order[starts[t]:starts[t + 1]]``, ascending ids."""
    t = np.asarray(templates, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    starts = np.searchsorted(t[order], np.arange(n_templates + 1))
    return order, starts
