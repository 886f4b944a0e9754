"""Merging a partial map's engine state into a loaded map's: Menezes et al. (2023) Algorithm 1, corrected.

``merge_states`` works on snapshot arrays (docs/architecture.md) and returns the merged
snapshot, built from the documented keys only, that ``core.Engine.restore`` continues from.
Loaded ids are kept; partial templates, links and experiences are appended after them.
Every step is vectorised over templates, links and experiences.

Operations (Algorithm 1):

* (i) templates, Eq. 9: the partial templates are appended except those identified with a
  loaded template (the matched one, and the pairs seen while confirming the match), whose
  ids are remapped to the loaded id everywhere (pose-cell links, experiences, the gate window).
* (ii) pose-cell activation: the partial packet centre is carried through the lattice
  transform f (below) and the activity restarts there as a unit packet. When the robot is
  where its matched template was learnt this is the loaded template's cell, heading
  corrected by the view's relative_rad (the paper's P_u^lm).
* (iii) LVC→pose-cell links, Eqs. 10–12: every partial link (and experience lattice
  coordinate) is carried through f: the offset is loaded − partial (the printed Eq. 10 adds
  them), and the (x, y) displacement from the matched cell is rotated by the heading offset
  before wrapping (the paper only translates, wrong when the sessions' lattice headings differ).
  ``shift_lattice=False`` skips this operation (debug: Fig. 12 of the paper).
* (iv) experience maps, Eqs. 13–17: every partial experience pose is mapped by the 4-DoF
  rigid transform T = T_loaded ⊕ T_partial⁻¹ of the matched pair; ids are renumbered, links
  (relative transforms) are kept; the matched partial experience is not inserted (its links
  are redirected to the loaded one, kind ``merge`` for those that join the two graphs: Eq. 17).
  The merge links come last in the link arrays. Relaxation is scheduled (``em_relax_pending``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core import LinkKind
from core.angles import wrap_angle
from core.arrays import BoolArray, Float32Array, FloatArray, IntArray
from core.se3 import alignment, compose, relative, turn_step
from core.snapshot import (
    CountersSnapshot,
    EngineSnapshot,
    ExperienceMapSnapshot,
    GateSnapshot,
    OdometrySnapshot,
    PoseCellSnapshot,
    ViewSnapshot,
)
from mapserver.errors import MergeError
from mapserver.merge.lattice import LatticeTransform, signed_delta, splat
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.snapshot import (
    State,
    experiences_by_template,
    incompatibility,
    lattice_shape,
    pose_cells_of,
    typed_state,
)


def _heading(rad: float) -> FloatArray:
    return np.array([0.0, 0.0, 0.0, rad])


def _check_id(value: int, count: int, what: str, allow_none: bool = False) -> None:
    low = -1 if allow_none else 0
    if not low <= value < count:
        msg = f"{what} {value!r} is out of range (the map has {count})"
        raise MergeError(msg)


def _template_map(match: Match, n_loaded: int, n_partial: int) -> IntArray:
    """Return (P,) merged template ids: identified ones → loaded ids, the rest appended in order.

    A match whose ``partial_template`` is −1 (a manual link, :mod:`mapserver.atlas.manual_links`) identifies none.
    """
    identified: dict[int, int] = {} if match.partial_template < 0 else {match.partial_template: match.stored_template}
    for z, u in match.pairs:
        _check_id(z, n_partial, "partial template")
        _check_id(u, n_loaded, "stored template")
        identified.setdefault(int(z), int(u))
    tmap = np.full(n_partial, -1, dtype=np.int64)
    keys = np.fromiter(identified.keys(), dtype=np.int64, count=len(identified))
    tmap[keys] = np.fromiter(identified.values(), dtype=np.int64, count=len(identified))
    kept = tmap < 0
    tmap[kept] = n_loaded + np.arange(int(kept.sum()), dtype=np.int64)
    return tmap


def _remap(ids: IntArray, mapping: IntArray) -> IntArray:
    """Map ids ≥ 0 through ``mapping``; −1 (none) stays −1."""
    ids = np.asarray(ids, dtype=np.int64)
    out = np.full(ids.shape, -1, dtype=np.int64)
    valid = ids >= 0
    out[valid] = mapping[ids[valid]]
    return out


def _link_active(state: EngineSnapshot) -> BoolArray:
    """Return the state's per-link status (every link on when it lists none)."""
    return state.map.link_status()


def default_identify_within(loaded: EngineSnapshot) -> float:
    """Return half the median odometry-link length of the loaded map, metres (∞ when it has no link).

    How close, after T, a partial experience must lie to a loaded experience of the same view
    to be identified with it.
    """
    kind = np.asarray(loaded.map.link_kind)
    distance = np.asarray(loaded.map.link_distance, dtype=np.float64)[kind == int(LinkKind.ODOMETRY)]
    distance = distance[distance > 0]
    return 0.5 * float(np.median(distance)) if distance.size else math.inf


def _identify_experiences(
    loaded: EngineSnapshot,
    partial: EngineSnapshot,
    tmap: IntArray,
    n_loaded_templates: int,
    emap: IntArray,
    T: FloatArray,
    within: float,
) -> None:
    """Identify partial experiences of identified templates with the nearest loaded experience of that template.

    Only when that experience lies within ``within`` metres after T: a view matches its template
    over a stretch of road, so a pair of matched views does not make two experiences one place.
    Only experiences of identified templates are visited (the confirmation window), so the
    Python loop is bounded by the window, not by the map size.
    """
    p_templates = np.asarray(partial.map.template, dtype=np.int64)
    identified_t = tmap < n_loaded_templates
    candidates = np.flatnonzero(identified_t[p_templates] & (emap < 0))
    if candidates.size == 0:
        return
    order, starts = experiences_by_template(np.asarray(loaded.map.template), n_loaded_templates)
    poses = compose(T, np.asarray(partial.map.pose)[candidates])
    loaded_pose = np.asarray(loaded.map.pose)
    for k, exp in enumerate(candidates.tolist()):
        u = int(tmap[p_templates[exp]])
        mine = order[starts[u] : starts[u + 1]]
        if mine.size:
            gap = np.linalg.norm(loaded_pose[mine, :3] - poses[k, :3], axis=1)
            nearest = int(np.argmin(gap))
            if gap[nearest] <= within:
                emap[exp] = int(mine[nearest])


def _links(
    loaded: EngineSnapshot, partial: EngineSnapshot, emap: IntArray, kept_e: BoolArray, n_total: int
) -> tuple[np.ndarray, ...]:
    """Return the partial links remapped: (keep mask, from, to, kind, joins), self-loops and duplicates dropped.

    ``joins`` marks the links that now join a kept partial experience to a loaded one (kind ``merge``).
    """
    pf = np.asarray(partial.map.link_from, dtype=np.int64)
    pt = np.asarray(partial.map.link_to, dtype=np.int64)
    nf, nt = emap[pf], emap[pt]
    keep = nf != nt
    code = nf * n_total + nt
    # only a link between two identified (now loaded) experiences can repeat a loaded link
    both = np.flatnonzero(~kept_e[pf] & ~kept_e[pt])
    if both.size:
        lf = np.asarray(loaded.map.link_from, dtype=np.int64)
        lt = np.asarray(loaded.map.link_to, dtype=np.int64)
        ends = np.unique(np.concatenate([nf[both], nt[both]]))
        near = np.isin(lf, ends) & np.isin(lt, ends)  # loaded links among those experiences only
        keep[both] &= ~np.isin(code[both], lf[near] * n_total + lt[near])
    _, first = np.unique(code, return_index=True)
    unique = np.zeros(code.shape, dtype=bool)
    unique[first] = True
    keep &= unique
    kind = np.asarray(partial.map.link_kind, dtype=np.int8).copy()
    joins = kept_e[pf] != kept_e[pt]  # one end kept in the partial, the other now a loaded experience
    kind[joins] = int(LinkKind.MERGE)
    return keep, nf, nt, kind, joins


def merge_states(
    loaded: State,
    partial: State,
    match: Match,
    *,
    shift_lattice: bool = True,
    identify_within: float | None = None,
) -> tuple[dict[str, np.ndarray], MergeRecord]:
    """Merge the partial map's state into the loaded map's (Menezes et al. Algorithm 1, corrected).

    The steps follow the algorithm: (i) templates (:func:`_merge_templates`, Eq. 9), (ii)/(iii) the
    lattice transform between the matched packets and the pose-cell links moved by it
    (:func:`_lattice_transform`, :func:`_merge_pose_cell_links`, corrected Eq. 10), (iv) experiences and
    their links under T (:func:`_merge_experiences`, :func:`_merge_links`, Eqs. 13–14 and 17), then the
    robot's own state continues in the merged map (:func:`_robot_state`); :func:`_merge_record` records
    the merge.

    Args:
        loaded: snapshot of the loaded (stored) map; its ids are kept.
        partial: snapshot of the partial map (the session being mapped, or the map merged offline);
            its robot state (current experience, odometry since, packet) continues in the merged map.
        match: the confirmed correspondence (:class:`Match`).
        shift_lattice: False skips operation (iii): the partial links and experience lattice
            coordinates keep the partial lattice's frame (debug; the paper's Fig. 12).
        identify_within: metres; a partial experience of an identified template is identified with
            (not inserted, links redirected to) the nearest loaded experience of that template when
            they lie this close after T. None → :func:`default_identify_within`.

    Returns:
        The merged snapshot (documented keys only; ``Engine.restore`` continues from it) and
        the :class:`MergeRecord`.

    Raises:
        MergeError: the snapshots cannot be merged (different lattice or template shapes, a
            documented key missing, an id out of range).
    """
    l_state, _ = typed_state(loaded, "loaded")
    merged, record = _merge_typed(l_state, partial, match, shift_lattice, identify_within)
    view = merged.view.replace(templates=merged_templates(loaded, merged.view.templates))
    return merged.replace(view=view).to_arrays(), record


def merge_states_apart(
    loaded: State,
    partial: State,
    match: Match,
    *,
    shift_lattice: bool = True,
    identify_within: float | None = None,
) -> tuple[dict[str, np.ndarray], MergeRecord, Float32Array]:
    """Return :func:`merge_states`' snapshot less ``lv_templates``, its record, and the partial's kept templates.

    The merged map's templates are the loaded map's ``lv_templates`` followed by the kept ones (float32, in the
    loaded map's template shape; :func:`merged_templates` joins them): a caller that can hold them apart, as
    :func:`mapserver.merge.engines.merge_engine` does, never builds a copy of the loaded map's templates.
    """
    l_state, _ = typed_state(loaded, "loaded")
    merged, record = _merge_typed(l_state, partial, match, shift_lattice, identify_within)
    state = merged.to_arrays()
    del state[ViewSnapshot.key("templates")]
    return state, record, merged.view.templates


def _merge_typed(
    loaded: EngineSnapshot, partial_state: State, match: Match, shift_lattice: bool, identify_within: float | None
) -> tuple[EngineSnapshot, MergeRecord]:
    """Return the merged snapshot, whose ``view.templates`` are only the partial's kept ones, and its record."""
    partial, _ = typed_state(partial_state, "partial")
    dims = _check_inputs(loaded, partial, match)
    tmap, kept_t, appended = _merge_templates(loaded, partial, match)
    f, delta_u = _lattice_transform(loaded, match, dims)
    pc_links = _merge_pose_cell_links(loaded, partial, tmap, kept_t, f if shift_lattice else None, len(dims))
    experiences = _merge_experiences(loaded, partial, match, tmap, f if shift_lattice else None, identify_within)
    links = _merge_links(loaded, partial, match, experiences)
    robot = _robot_state(partial, match, experiences)
    state = _merged_state(loaded, partial, match, dims, tmap, kept_t, f, delta_u, pc_links,
                          experiences, links, robot, appended)  # fmt: skip
    return state, _merge_record(loaded, match, shift_lattice, tmap, f, experiences, links, state)


def _merge_record(
    loaded: EngineSnapshot,
    match: Match,
    shift_lattice: bool,
    tmap: IntArray,
    f: LatticeTransform,
    exp: _Experiences,
    links: _Links,
    state: EngineSnapshot,
) -> MergeRecord:
    """Return the merge's record: the match, f and T (operations (ii)-(iv)), the id offsets and maps, the sizes."""
    return MergeRecord(
        stored_template=match.stored_template,
        stored_experience=match.stored_experience,
        partial_template=match.partial_template,
        partial_pose=_four(np.asarray(match.partial_pose, dtype=np.float64)),
        relative_rad=float(match.relative_rad),
        confirmations=int(match.confirmations),
        lattice_source=f.source,
        lattice_target=f.target,
        lattice_offset=tuple(f.offset.tolist()),
        heading_offset_rad=f.heading_rad,
        lattice_shifted=shift_lattice,
        transform=_four(exp.T),
        template_offset=int(np.shape(loaded.view.means)[0]),
        experience_offset=exp.n_loaded,
        link_offset=links.n_loaded,
        template_map=tmap,
        experience_map=exp.emap,
        merge_links=links.merge_links.astype(np.int64),
        templates=int(state.view.means.shape[0]),
        experiences=int(state.map.pose.shape[0]),
        links=int(state.map.link_from.shape[0]),
    )


def _check_inputs(loaded: EngineSnapshot, partial: EngineSnapshot, match: Match) -> tuple[int, ...]:
    """Check both snapshots and the match's ids; return the lattice shape."""
    reason = incompatibility(loaded, partial)
    if reason:
        raise MergeError(reason)
    dims = lattice_shape(loaded)
    _check_id(match.stored_template, int(np.shape(loaded.view.means)[0]), "stored template")
    _check_id(match.stored_experience, int(np.shape(loaded.map.pose)[0]), "stored experience")
    _check_id(match.partial_template, int(np.shape(partial.view.means)[0]), "partial template", allow_none=True)
    if len(match.partial_packet) != len(dims) or len(match.partial_pose) != 4:
        msg = f"partial anchor must be a pose (4,) and a packet ({len(dims)},), got {match.partial_pose!r}, " \
              f"{match.partial_packet!r}"
        raise MergeError(msg)
    return dims


def _merge_templates(
    loaded: EngineSnapshot, partial: EngineSnapshot, match: Match
) -> tuple[IntArray, BoolArray, Float32Array]:
    """Operation (i), Eq. 9: the template id map, which partial templates are kept, and the kept templates.

    The kept templates (float32, in the loaded map's template shape) follow the loaded map's in the merged map.
    """
    n_lt, n_pt = int(np.shape(loaded.view.means)[0]), int(np.shape(partial.view.means)[0])
    tmap = _template_map(match, n_lt, n_pt)
    kept_t = tmap >= n_lt
    shape = np.shape(loaded.view.templates)[1:] if n_lt else np.shape(partial.view.templates)[1:]
    appended = np.asarray(partial.view.templates, dtype=np.float32).reshape(-1, *shape)[kept_t]
    return tmap, kept_t, appended


def merged_templates(loaded: State, appended: Float32Array) -> Float32Array:
    """Return the merged map's templates: the loaded map's (float32) followed by ``appended`` (one new array)."""
    own = np.asarray(loaded[ViewSnapshot.key("templates")], dtype=np.float32).reshape(-1, *appended.shape[1:])
    return np.concatenate([own, appended])


def _lattice_transform(
    loaded: EngineSnapshot, match: Match, dims: tuple[int, ...]
) -> tuple[LatticeTransform, float]:
    """Operations (ii)/(iii): the lattice transform f between the matched packets, and the view's heading cells.

    Offset loaded − partial (corrected Eq. 10), (x, y) rotated by the heading offset. The loaded packet is
    the matched experience's lattice coordinates (the packet after its frame's path integration; a link
    holds the packet of the frame before, and a session's first template the initial one), heading
    corrected by the view's offset.
    """
    l_pc = np.asarray(loaded.map.pc, dtype=np.float64).reshape(-1, len(dims))
    delta_u = match.relative_rad / (2.0 * math.pi) * dims[-1]
    target = l_pc[match.stored_experience].copy()
    target[-1] += delta_u
    return LatticeTransform.between(dims, np.asarray(match.partial_packet, dtype=np.float64), target), delta_u


def _merge_pose_cell_links(
    loaded: EngineSnapshot,
    partial: EngineSnapshot,
    tmap: IntArray,
    kept_t: BoolArray,
    f: LatticeTransform | None,
    rank: int,
) -> _PoseCellLinks:
    """Operation (iii) on the LVC→pose-cell links: the partial links of kept templates, moved by f."""
    lpc, ppc = pose_cells_of(loaded), pose_cells_of(partial)
    p_links = np.asarray(ppc.link_template, dtype=np.int64)
    keep_link = kept_t[p_links]  # links of identified templates: the loaded template's links stand
    p_coords = np.asarray(ppc.link_coords, dtype=np.float64).reshape(-1, rank)
    l_coords = np.asarray(lpc.link_coords, dtype=np.float64).reshape(-1, rank)
    return _PoseCellLinks(
        template=np.concatenate([np.asarray(lpc.link_template, dtype=np.int64), tmap[p_links[keep_link]]]),
        coords=np.concatenate([l_coords, _moved(f, p_coords[keep_link], rank)]),
        strength=_cat(lpc.link_strength, ppc.link_strength, np.float64, keep_link),
        decay=_cat(lpc.link_decay, ppc.link_decay, np.float64, keep_link),
    )


@dataclass(frozen=True, slots=True)
class _PoseCellLinks:
    """Operation (iii)'s outcome: the merged LVC→pose-cell links."""

    template: IntArray
    coords: FloatArray
    strength: FloatArray
    decay: FloatArray


@dataclass(frozen=True, slots=True)
class _Experiences:
    """Operation (iv)'s outcome for the experiences: T, the id map, and the merged arrays."""

    T: FloatArray  # (4,) the rigid transform partial → loaded frame
    anchor_loaded: FloatArray  # (4,) the matched loaded experience's pose turned by the view's offset
    emap: IntArray  # (n_partial,) merged id of each partial experience
    kept: BoolArray  # (n_partial,) partial experiences inserted (not identified)
    n_loaded: int
    n_total: int
    pose: FloatArray
    pc: FloatArray
    template: IntArray
    stamp: FloatArray
    origin: IntArray
    pc_lever: FloatArray


def _merge_experiences(
    loaded: EngineSnapshot,
    partial: EngineSnapshot,
    match: Match,
    tmap: IntArray,
    f: LatticeTransform | None,
    identify_within: float | None,
) -> _Experiences:
    """Operation (iv), Eqs. 13–14 generalised to (x, y, z, yaw): T = T_loaded ⊕ T_partial⁻¹, experiences under T."""
    lm, pm = loaded.map, partial.map
    l_pose = np.asarray(lm.pose, dtype=np.float64).reshape(-1, 4)
    p_pose = np.asarray(pm.pose, dtype=np.float64).reshape(-1, 4)
    n_le, n_pe = l_pose.shape[0], p_pose.shape[0]
    n_lt = int(np.shape(loaded.view.means)[0])
    anchor_loaded = compose(l_pose[match.stored_experience], _heading(match.relative_rad))
    T = alignment(anchor_loaded, np.asarray(match.partial_pose, dtype=np.float64))
    emap = np.full(n_pe, -1, dtype=np.int64)
    within = default_identify_within(loaded) if identify_within is None else identify_within
    _identify_experiences(loaded, partial, tmap, n_lt, emap, T, within)
    kept = emap < 0
    emap[kept] = n_le + np.arange(int(kept.sum()), dtype=np.int64)
    rank = len(lattice_shape(loaded))
    l_pc = np.asarray(lm.pc, dtype=np.float64).reshape(-1, rank)
    p_pc = np.asarray(pm.pc, dtype=np.float64).reshape(-1, rank)
    return _Experiences(
        T, anchor_loaded, emap, kept, n_le, n_le + int(kept.sum()),
        pose=np.concatenate([l_pose, compose(T, p_pose[kept])]),
        pc=np.concatenate([l_pc, _moved(f, p_pc[kept], rank)]),
        template=np.concatenate([np.asarray(lm.template, dtype=np.int64), tmap[np.asarray(pm.template)[kept]]]),
        stamp=_cat(lm.stamp, pm.stamp, np.float64, kept),
        origin=_cat(lm.origin, pm.origin, np.int64, kept),
        pc_lever=np.concatenate([lm.levers(n_le), pm.levers(n_pe)[kept] + _lever_arm(f, p_pc[kept])]),
    )  # fmt: skip


@dataclass(frozen=True, slots=True)
class _LinkRows:
    """Link arrays in the experience map's columns (one row per link)."""

    link_from: IntArray
    link_to: IntArray
    link_transform: FloatArray
    link_dt: FloatArray
    link_distance: FloatArray
    link_kind: np.ndarray
    link_active: BoolArray

    @staticmethod
    def join(parts: list[_LinkRows]) -> _LinkRows:
        """Return the rows of ``parts`` one after the other."""
        return _LinkRows(
            link_from=np.concatenate([p.link_from for p in parts]),
            link_to=np.concatenate([p.link_to for p in parts]),
            link_transform=np.concatenate([p.link_transform for p in parts]),
            link_dt=np.concatenate([p.link_dt for p in parts]),
            link_distance=np.concatenate([p.link_distance for p in parts]),
            link_kind=np.concatenate([p.link_kind for p in parts]).astype(np.int8),
            link_active=np.concatenate([p.link_active for p in parts]),
        )


@dataclass(frozen=True, slots=True)
class _Links:
    """Operation (iv)'s outcome for the links: the merged link arrays and which of them are merge links."""

    n_loaded: int
    merge_links: IntArray  # ids (in the merged map) of the links that join the two graphs
    rows: _LinkRows


def _merge_links(loaded: EngineSnapshot, partial: EngineSnapshot, match: Match, exp: _Experiences) -> _Links:
    """Operation (iv) on the links: the partial's kept links, merge links last.

    Where nothing identified joins the graphs, Eq. 17 adds a link from the partial's current experience to
    the matched one.
    """
    lm, pm = loaded.map, partial.map
    keep_l, nf, nt, kind, joins = _links(loaded, partial, exp.emap, exp.kept, exp.n_total)
    kept_links = np.flatnonzero(keep_l)
    keep_l = np.concatenate([kept_links[~joins[kept_links]], kept_links[joins[kept_links]]])
    p_transform = np.asarray(pm.link_transform, dtype=np.float64).reshape(-1, 4)
    n_ll = int(np.shape(lm.link_from)[0])
    rows = [
        _LinkRows(
            np.asarray(lm.link_from, dtype=np.int64), np.asarray(lm.link_to, dtype=np.int64),
            np.asarray(lm.link_transform, dtype=np.float64).reshape(-1, 4),
            np.asarray(lm.link_dt, dtype=np.float64), np.asarray(lm.link_distance, dtype=np.float64),
            np.asarray(lm.link_kind, dtype=np.int8), _link_active(loaded),
        ),
        _LinkRows(
            nf[keep_l], nt[keep_l], p_transform[keep_l],
            np.asarray(pm.link_dt, dtype=np.float64)[keep_l], np.asarray(pm.link_distance, dtype=np.float64)[keep_l],
            kind[keep_l], _joined_status(_link_active(partial)[keep_l], joins[keep_l]),
        ),
    ]  # fmt: skip
    new_joins = [joins[keep_l]]
    current = int(pm.current)
    if current >= 0 and exp.n_loaded and exp.kept.any() and not new_joins[0].any():
        # nothing identified joins the graphs (e.g. no partial experience of an identified template):
        # Eq. 17 as a link from the partial's current experience to e_u, at their relative pose under T
        e_u = match.stored_experience
        p_pose = np.asarray(pm.pose, dtype=np.float64).reshape(-1, 4)
        l_pose = np.asarray(lm.pose, dtype=np.float64).reshape(-1, 4)
        link = relative(compose(exp.T, p_pose[current]), l_pose[e_u])
        rows.append(_LinkRows(
            np.array([int(exp.emap[current])], dtype=np.int64), np.array([e_u], dtype=np.int64), link[None, :],
            np.array([float(np.asarray(pm.accum, dtype=np.float64)[4])]),
            np.array([float(np.linalg.norm(link[:3]))]),
            np.array([int(LinkKind.MERGE)], dtype=np.int8), np.array([True]),
        ))  # fmt: skip
        new_joins.append(np.array([True]))
    ties = _tie_links(match, exp)
    rows.append(ties)
    new_joins.append(np.ones(ties.link_from.size, dtype=bool))
    return _Links(n_ll, n_ll + np.flatnonzero(np.concatenate(new_joins)), _LinkRows.join(rows))


def _tie_links(match: Match, exp: _Experiences) -> _LinkRows:
    """Return the match's ties (:attr:`Match.ties`) as merge links, in merged ids, one per experience pair.

    A tie whose partial experience the identification made a loaded one is left out (the two are one node),
    as are repeats of a pair (the first, in support order, is kept). Its height difference is the one T gives
    the two experiences: a view places the robot along the stored track only to within the experiences'
    spacing, and on a slope that is a depth error the vehicle's own depth odometry does not make (a 4-DoF loop
    that goes up and down: merged depths 0.041 m RMSE with the tie's height, 0.018 m for the session alone).
    """
    seen: set[tuple[int, int]] = set()
    rows: list[tuple[int, int, tuple[float, ...]]] = []
    for e_p, e_l, tie in match.ties:
        _check_id(e_p, exp.emap.size, "tied partial experience")
        _check_id(e_l, exp.n_loaded, "tied stored experience")
        if not exp.kept[e_p] or (e_p, e_l) in seen:
            continue
        seen.add((e_p, e_l))
        rows.append((int(exp.emap[e_p]), e_l, tie))
    transform = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
    ends = np.array([r[:2] for r in rows], dtype=np.int64).reshape(-1, 2)
    poses = exp.pose
    transform[:, 2] = poses[ends[:, 1], 2] - poses[ends[:, 0], 2]  # the depth T gives them (see Match.ties)
    return _LinkRows(
        link_from=np.array([r[0] for r in rows], dtype=np.int64),
        link_to=np.array([r[1] for r in rows], dtype=np.int64),
        link_transform=transform,
        link_dt=np.zeros(len(rows)),
        link_distance=np.linalg.norm(transform[:, :3], axis=1),
        link_kind=np.full(len(rows), int(LinkKind.MERGE), dtype=np.int8),
        link_active=np.ones(len(rows), dtype=bool),
    )


def _robot_state(partial: EngineSnapshot, match: Match, exp: _Experiences) -> tuple[int, int, FloatArray]:
    """The robot continues in the merged map: (current, previous experience, odometry since it rotated by T)."""
    accum = np.asarray(partial.map.accum, dtype=np.float64).copy()
    current = int(partial.map.current)
    if current < 0:  # no partial experience yet: the robot is at T ⊕ its odometry so far (accum), measured from e_u
        here = compose(exp.T, accum[:4])
        accum[:3] = here[:3] - exp.anchor_loaded[:3]
        accum[3] = float(here[3])
        return match.stored_experience, -1, accum
    previous = int(partial.map.previous)
    accum[:4] = turn_step(accum[:4].tolist(), float(exp.T[3]))
    accum[3] = float(wrap_angle(accum[3]))
    return int(exp.emap[current]), int(exp.emap[previous]) if previous >= 0 else -1, accum


def _merged_reckoning(
    loaded: EngineSnapshot, partial: EngineSnapshot, emap: IntArray, kept: BoolArray
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, IntArray]:
    """Return both maps' reckoning links (from, to, odometry), the running dead reckoning, the last created experience.

    Ids are merged ids.

    Reckoning links hold odometry in their source's frame, which no rigid transform changes. One whose
    start is identified with a loaded experience starts there: dropped, as until 2026-11-28, it left the
    relocalisation's odometry link it stood in for (into a kept experience, switched off in the partial
    map) with no partner, so the merged map's robust check could not switch it off; it came back on and
    folded session 2's map again (offline merge of ``symmetric`` seed 7, merged APE 17.5 m against 3.0 m
    now). One whose end is identified is dropped: the link it stood in for, into that experience, is a
    merge link now or gone, and the first odometry link into a loaded experience is the loaded map's
    own (:meth:`core.experience_map.ExperienceMap._standby` would pair them). Likewise the running
    session's last created experience, when identified, starts no reckoning link (``last_created``
    −1): one from the loaded experience would join the sessions in the dead reckoning that the robust
    check tests links against (:func:`core.robust.contradicts_odometry`). States without them (older,
    imported) have none.
    """
    l_from, l_to, l_link = loaded.map.reckoning_links()
    p_from, p_to, p_link = partial.map.reckoning_links()
    keep = kept[p_to]  # a reckoning link into an identified experience stood in for a link that is no longer odometry
    p_from, p_to = emap[p_from], emap[p_to]
    keep &= p_from != p_to
    pm = partial.map
    last = int(np.asarray(pm.last_created if pm.last_created is not None else np.asarray(-1)))
    return (
        np.concatenate([l_from, p_from[keep]]),
        np.concatenate([l_to, p_to[keep]]),
        np.concatenate([l_link, p_link[keep]]),
        np.asarray(pm.reckon if pm.reckon is not None else np.zeros(6), dtype=np.float64).copy(),
        np.asarray(int(emap[last]) if last >= 0 and kept[last] else -1, dtype=np.int64),
    )


def _cat(loaded: np.ndarray, partial: np.ndarray, dtype: type, mask: BoolArray) -> np.ndarray:
    """Return the loaded map's array followed by the partial's rows under ``mask``."""
    return np.concatenate([np.asarray(loaded, dtype=dtype), np.asarray(partial, dtype=dtype)[mask]])


def _merged_state(
    loaded: EngineSnapshot,
    partial: EngineSnapshot,
    match: Match,
    dims: tuple[int, ...],
    tmap: IntArray,
    kept_t: BoolArray,
    f: LatticeTransform,
    delta_u: float,
    pc_links: _PoseCellLinks,
    exp: _Experiences,
    links: _Links,
    robot: tuple[int, int, FloatArray],
    appended: Float32Array,
) -> EngineSnapshot:
    """Assemble the merged snapshot (templates: ``appended`` only): the merged parts and the partial's running state."""
    lv, ppc = partial.view, pose_cells_of(partial)
    best = f.apply(np.asarray(ppc.best, dtype=np.float64))
    lv_current = int(lv.current)
    pc_current = int(ppc.current_vt)

    def scalar(value: int) -> IntArray:
        return np.asarray(_remap(np.asarray(value), tmap), dtype=np.int64)

    em_current, em_previous, accum = robot
    view = ViewSnapshot(
        templates=appended,
        means=_cat(loaded.view.means, lv.means, np.float64, kept_t),
        current=scalar(lv_current),
        previous=scalar(int(lv.previous)),
        relative_rad=np.asarray(
            match.relative_rad if lv_current == match.partial_template else float(lv.relative_rad), dtype=np.float64
        ),
        origin=_cat(loaded.view.origin, lv.origin, np.int64, kept_t),
    )
    odometry = OdometrySnapshot(
        prev_vtrans=np.asarray(partial.odometry.prev_vtrans, dtype=np.float64).copy(),
        prev_vrot=np.asarray(partial.odometry.prev_vrot, dtype=np.float64).copy(),
    )
    pose_cells = PoseCellSnapshot(
        activity=splat(dims, best),
        best=best,
        link_template=pc_links.template,
        link_coords=pc_links.coords,
        link_strength=pc_links.strength,
        link_decay=pc_links.decay,
        current_vt=scalar(pc_current),
        prev_vt=scalar(int(ppc.prev_vt)),
        vt_delta_th=np.asarray(delta_u if pc_current == match.partial_template else float(ppc.vt_delta_th)),
    )
    rows = links.rows
    reckon_from, reckon_to, reckon_link, reckon, last_created = _merged_reckoning(loaded, partial, exp.emap, exp.kept)
    experience_map = ExperienceMapSnapshot(
        pose=exp.pose, pc=exp.pc, template=exp.template, stamp=exp.stamp, origin=exp.origin, pc_lever=exp.pc_lever,
        link_from=rows.link_from, link_to=rows.link_to, link_transform=rows.link_transform, link_dt=rows.link_dt,
        link_distance=rows.link_distance, link_kind=rows.link_kind, link_active=rows.link_active,
        current=np.asarray(em_current, dtype=np.int64),
        previous=np.asarray(em_previous, dtype=np.int64),
        accum=accum,
        relax_pending=np.asarray(True),
        reckon_from=reckon_from, reckon_to=reckon_to, reckon_link=reckon_link, reckon=reckon,
        last_created=last_created,
    )  # fmt: skip
    gate = GateSnapshot(
        history=_remap(np.asarray(partial.gate.history), tmap),
        state=np.asarray(partial.gate.state, dtype=np.float64).copy(),
    )
    counters = CountersSnapshot(
        frames=np.asarray(int(partial.counters.frames), dtype=np.int64),
        last_stamp=np.asarray(float(partial.counters.last_stamp), dtype=np.float64),
    )
    return EngineSnapshot(view, odometry, pose_cells, experience_map, gate, counters)


def _four(values: FloatArray) -> tuple[float, float, float, float]:
    """Return a pose (4,) as a tuple of floats."""
    return (float(values[0]), float(values[1]), float(values[2]), float(values[3]))


def _moved(f: LatticeTransform | None, coords: FloatArray, rank: int) -> FloatArray:
    """Return partial lattice coordinates in the loaded lattice (unchanged when f is None: (iii) skipped)."""
    moved = f.apply(coords) if f is not None else np.asarray(coords, dtype=np.float64).copy()
    return moved.reshape(-1, rank)


def _joined_status(active: BoolArray, joins: BoolArray) -> BoolArray:
    """Return the kept partial links' status in the merged map: each keeps its own.

    A link the partial map's robust check switched off stays off when it becomes a merge link (an end
    identified with a stored experience): a false relocalisation's odometry link turned on again won the
    merged map's check on a tie and turned session 2's first lap by 3.6 rad (offline merge of ``symmetric``
    seed 4, merged APE 16 m). Only when every link that joins the graphs was off do they all start on (the
    merged map's robust check decides them afresh).
    """
    out = active.copy()
    if joins.any() and not out[joins].any():
        out[joins] = True
    return out


def _lever_arm(f: LatticeTransform | None, coords: FloatArray) -> FloatArray:
    """Return each partial coordinate's (x, y) distance in cells from the anchor f rotates about (0: not moved).

    Operation (iii) rotates the partial lattice about the matched cell by the heading offset of one view, and
    that offset is off by the view's heading error ε (1–17° on true merges; docs/journal.md, "the merge's heading
    fitted over its support"): a coordinate r cells from the anchor lands about ε·r cells from where the loaded
    lattice holds its place. The engine widens its closure gate by ``merge_lattice_slack`` (ε) times this lever
    (``Engine._get_action``); levers of successive merges add.
    """
    if f is None:
        return np.zeros(coords.shape[0], dtype=np.float64)
    delta = signed_delta(coords, np.asarray(f.source), np.asarray(f.dims))
    return np.hypot(delta[:, 0], delta[:, 1])
