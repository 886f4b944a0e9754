"""What a merge needs (``Match``) and what it did (``MergeRecord``: an event row and an undo need it all)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.arrays import FloatArray, IntArray
from core.se3 import to_matrix
from core.snapshot import ExperienceMapSnapshot


@dataclass(frozen=True)
class Match:
    """A confirmed correspondence between a partial map and a loaded (stored) map.

    A view of the partial map (the camera view at one frame online, a partial template
    offline) matched the loaded template ``stored_template``, whose place is the loaded
    experience ``stored_experience`` (Menezes et al.: V^pm_{n_vp} = V^lm_u, e_z ↔ e_u).
    The partial side of the anchor is where the partial map was when it saw that view: a
    pose in the partial map frame and a packet in the partial lattice (the robot at that
    frame online; a partial experience offline, see :meth:`at_experience`).

    Attributes:
        stored_template: u, the loaded map's matched template.
        stored_experience: e_u, the loaded experience of that place (anchor of T and of the lattice offset).
        partial_template: z, the partial template of the same view, identified with u (Eq. 9).
        partial_pose: (x, y, z, yaw) in the partial map frame where the view was seen.
        partial_packet: (D,) the partial lattice packet (cells) where the view was seen.
        relative_rad: heading of the view relative to u (panoramic matching; 0 otherwise).
        confirmations: consecutive matching frames (online) or templates (offline) that confirmed it.
        pairs: further (partial template, loaded template) pairs seen while confirming. They are
            identified too: the partial's copies of loaded views are not duplicated, and partial
            experiences of identified templates are identified with the nearest loaded experience of
            that template (not inserted, links redirected: Eqs. 15–17).
        ties: (partial experience, stored experience, (dx, dy, dz, dyaw)) for the views that put the robot at
            a stored place while the merge's hypothesis gathered its evidence (its hits, history included):
            the stored experience's pose relative to the partial one when the view was seen there (a RatSLAM
            loop closure: the robot stood at the stored place, turned by the view's heading offset). Each whose
            partial experience the identification leaves apart (its drift puts it farther than the
            identification radius) becomes a merge link, at the height difference T gives the two (dz is not
            used): they hold the partial map's own copy of the stored ground along its length, not at the
            anchor only (online LVC merges; offline merges have their closures instead, sdr-htm merges none).
    """

    stored_template: int
    stored_experience: int
    partial_template: int
    partial_pose: tuple[float, ...]  # x, y, z, yaw
    partial_packet: tuple[float, ...]
    relative_rad: float = 0.0
    confirmations: int = 1
    pairs: tuple[tuple[int, int], ...] = ()
    ties: tuple[tuple[int, int, tuple[float, ...]], ...] = ()  # (partial, stored, x y z yaw)

    @classmethod
    def at_experience(
        cls,
        partial: Mapping[str, np.ndarray],
        partial_experience: int,
        stored_template: int,
        stored_experience: int,
        *,
        relative_rad: float = 0.0,
        confirmations: int = 1,
        pairs: tuple[tuple[int, int], ...] = (),
    ) -> Match:
        """Return the match anchored at a partial experience (the paper's e_z ↔ e_u, Eqs. 13–14).

        The partial side is the experience's pose and lattice coordinates; its template is z.
        """
        em = ExperienceMapSnapshot
        pose = np.asarray(partial[em.key("pose")], dtype=np.float64).reshape(-1, 4)[partial_experience]
        packet = np.asarray(partial[em.key("pc")], dtype=np.float64)[partial_experience]
        template = int(np.asarray(partial[em.key("template")])[partial_experience])
        return cls(
            stored_template=stored_template,
            stored_experience=stored_experience,
            partial_template=template,
            partial_pose=(float(pose[0]), float(pose[1]), float(pose[2]), float(pose[3])),
            partial_packet=tuple(float(v) for v in packet),
            relative_rad=relative_rad,
            confirmations=confirmations,
            pairs=pairs,
        )


@dataclass(frozen=True, eq=False)
class MergeRecord:
    """Everything a merge did, in the ids of its inputs and of the merged map.

    Partial template i becomes merged template ``template_map[i]`` (a loaded id when it
    was identified with a loaded template, else ``template_offset`` + its rank among the
    kept ones); likewise ``experience_map`` for experiences. Loaded ids are unchanged, so
    the loaded map is the merged map's first ``template_offset`` templates,
    ``experience_offset`` experiences and ``link_offset`` links: undoing a merge is taking
    that prefix (the partial map is kept by its session).

    Attributes:
        stored_template, stored_experience, partial_template, partial_pose, relative_rad,
        confirmations: as in :class:`Match`.
        lattice_source: the matched packet in the partial lattice (D,), cells, heading corrected.
        lattice_target: the same place's packet in the loaded lattice (D,).
        lattice_offset: ``target − source`` (D,), wrapped; the last axis is the heading offset Δθ.
        heading_offset_rad: Δθ as an angle; the (x, y) offsets are rotated by it about the matched cell.
        lattice_shifted: False when operation (iii) was disabled (debug).
        transform: T = T_loaded ⊕ T_partial⁻¹ as (x, y, z, yaw); :attr:`matrix` gives it as 4×4.
        template_offset, experience_offset, link_offset: counts of the loaded map.
        template_map: (P,) merged id of every partial template.
        experience_map: (E_p,) merged id of every partial experience.
        merge_links: merged link ids of kind ``merge`` (Eq. 17).
        templates, experiences, links: counts of the merged map.
    """

    stored_template: int
    stored_experience: int
    partial_template: int
    partial_pose: tuple[float, float, float, float]
    relative_rad: float
    confirmations: int
    lattice_source: tuple[float, ...]
    lattice_target: tuple[float, ...]
    lattice_offset: tuple[float, ...]
    heading_offset_rad: float
    lattice_shifted: bool
    transform: tuple[float, float, float, float]
    template_offset: int
    experience_offset: int
    link_offset: int
    template_map: IntArray = field(repr=False)
    experience_map: IntArray = field(repr=False)
    merge_links: IntArray = field(repr=False)
    templates: int = 0
    experiences: int = 0
    links: int = 0

    @property
    def matrix(self) -> FloatArray:
        """Return the SE(3) transform T as a homogeneous 4×4 matrix."""
        return to_matrix(np.asarray(self.transform))

    def to_dict(self) -> dict[str, Any]:
        """Return the record as JSON-able values (arrays as lists, the 4×4 matrix included)."""
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if isinstance(value, np.ndarray):
                out[name] = value.tolist()
            elif isinstance(value, tuple):
                out[name] = [float(v) for v in value]
            else:
                out[name] = value
        out["matrix"] = self.matrix.tolist()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MergeRecord:
        """Rebuild a record from :meth:`to_dict` output."""
        values = {name: data[name] for name in cls.__dataclass_fields__}
        for name in ("template_map", "experience_map", "merge_links"):
            values[name] = np.asarray(values[name], dtype=np.int64)
        for name in ("partial_pose", "lattice_source", "lattice_target", "lattice_offset"):
            values[name] = tuple(float(v) for v in values[name])
        values["transform"] = tuple(float(v) for v in values["transform"])
        return cls(**values)
