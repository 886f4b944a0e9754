"""Stable identities of a map's rows through merges: (origin session, index within that session).

The store keys templates and experiences by stable identity (docs/architecture.md, "Store"); the
engine keys them by row. :class:`RowIdentities` follows a running engine: rows it appends get the
next index of the engine's origin tag, in creation order; a merge (``MergeRecord.template_map`` /
``experience_map``) puts the loaded map's identities first and the kept partial rows after them, in
order. A partial row that a merge identifies with a loaded one leaves the map, and its index is not
given again (``next_index`` only grows), so an archived partial map and the live map never hold two
different rows under one identity.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from core.arrays import IntArray
from mapserver.errors import MergeError
from mapserver.merge.record import MergeRecord


def _as_int64(values: npt.ArrayLike) -> IntArray:
    return np.asarray(values, dtype=np.int64).reshape(-1)


@dataclass(eq=False)
class RowIdentities:
    """Identities (session tag, index) of every template and experience row of one engine state.

    Tags are the engine's origin tags (the store's session ids; a session not stored yet has its
    own tag until it has an id, see :meth:`retagged`).

    Attributes:
        next_index: session tag → (next template index, next experience index).
    """

    _t_session: list[int] = field(default_factory=list)
    _t_index: list[int] = field(default_factory=list)
    _e_session: list[int] = field(default_factory=list)
    _e_index: list[int] = field(default_factory=list)
    next_index: dict[int, tuple[int, int]] = field(default_factory=dict)

    @classmethod
    def from_arrays(
        cls,
        template_session: npt.ArrayLike,
        template_index: npt.ArrayLike,
        experience_session: npt.ArrayLike,
        experience_index: npt.ArrayLike,
        next_index: Mapping[int, tuple[int, int]] | None = None,
    ) -> RowIdentities:
        """Build identities from per-row arrays; ``next_index`` is raised past every index present.

        Raises:
            MergeError: session and index arrays of different lengths.
        """
        ts, ti = _as_int64(template_session), _as_int64(template_index)
        es, ei = _as_int64(experience_session), _as_int64(experience_index)
        if ts.size != ti.size or es.size != ei.size:
            msg = f"identity arrays differ in length: templates {ts.size}/{ti.size}, experiences {es.size}/{ei.size}"
            raise MergeError(msg)
        out = cls(ts.tolist(), ti.tolist(), es.tolist(), ei.tolist(), dict(next_index or {}))
        for tags, indices, axis in ((ts, ti, 0), (es, ei, 1)):
            for tag in np.unique(tags).tolist():
                out._raise(int(tag), axis, int(indices[tags == tag].max()) + 1)
        return out

    def _raise(self, tag: int, axis: int, value: int) -> None:
        current = list(self.next_index.get(tag, (0, 0)))
        current[axis] = max(current[axis], value)
        self.next_index[tag] = (current[0], current[1])

    def raise_next(self, tag: int, templates: int, experiences: int) -> None:
        """Make the next indices of ``tag`` at least these (indices used elsewhere, e.g. by stored rows)."""
        self._raise(tag, 0, templates)
        self._raise(tag, 1, experiences)

    # ---------------------------------------------------------------- counts
    @property
    def templates(self) -> int:
        """Return the number of template rows covered."""
        return len(self._t_index)

    @property
    def experiences(self) -> int:
        """Return the number of experience rows covered."""
        return len(self._e_index)

    def template_arrays(self) -> tuple[IntArray, IntArray]:
        """Return (session tags, indices) of the template rows, int64."""
        return np.asarray(self._t_session, dtype=np.int64), np.asarray(self._t_index, dtype=np.int64)

    def template_identity(self, row: int) -> tuple[int, int]:
        """Return (session tag, index) of template row ``row`` (constant time; (−1, −1) outside the rows)."""
        if 0 <= row < len(self._t_index):
            return self._t_session[row], self._t_index[row]
        return -1, -1

    def experience_identity(self, row: int) -> tuple[int, int]:
        """Return (session tag, index) of experience row ``row`` (constant time; (−1, −1) outside the rows)."""
        if 0 <= row < len(self._e_index):
            return self._e_session[row], self._e_index[row]
        return -1, -1

    def experience_arrays(self) -> tuple[IntArray, IntArray]:
        """Return (session tags, indices) of the experience rows, int64."""
        return np.asarray(self._e_session, dtype=np.int64), np.asarray(self._e_index, dtype=np.int64)

    def copy(self) -> RowIdentities:
        """Return an independent copy."""
        return RowIdentities(
            list(self._t_session), list(self._t_index), list(self._e_session), list(self._e_index),
            dict(self.next_index),
        )  # fmt: skip

    # ---------------------------------------------------------------- growth
    def extend(self, templates: int, experiences: int, tag: int) -> None:
        """Cover rows appended by the engine since: up to ``templates`` and ``experiences`` rows, tagged ``tag``.

        Raises:
            MergeError: the engine has fewer rows than covered (rows are only ever appended).
        """
        if templates < self.templates or experiences < self.experiences:
            msg = (
                f"the engine has {templates} templates and {experiences} experiences, fewer than the "
                f"{self.templates} and {self.experiences} identified"
            )
            raise MergeError(msg)
        nt, ne = self.next_index.get(tag, (0, 0))
        for _ in range(templates - self.templates):
            self._t_session.append(tag)
            self._t_index.append(nt)
            nt += 1
        for _ in range(experiences - self.experiences):
            self._e_session.append(tag)
            self._e_index.append(ne)
            ne += 1
        self.next_index[tag] = (nt, ne)

    @classmethod
    def merged(cls, loaded: RowIdentities, partial: RowIdentities, record: MergeRecord) -> RowIdentities:
        """Return the identities of a merged state (``merge_states``): loaded rows first, kept partial rows after.

        Raises:
            MergeError: the identities do not fit the record (row counts, or kept rows not appended in order).
        """
        if (loaded.templates, loaded.experiences) != (record.template_offset, record.experience_offset):
            msg = (
                f"loaded identities cover {loaded.templates} templates and {loaded.experiences} experiences, "
                f"the merge loaded {record.template_offset} and {record.experience_offset}"
            )
            raise MergeError(msg)
        tmap, emap = np.asarray(record.template_map), np.asarray(record.experience_map)
        if (partial.templates, partial.experiences) != (tmap.size, emap.size):
            msg = (
                f"partial identities cover {partial.templates} templates and {partial.experiences} experiences, "
                f"the merge had {tmap.size} and {emap.size}"
            )
            raise MergeError(msg)
        out = loaded.copy()
        for key, (nt, ne) in partial.next_index.items():
            out.raise_next(key, nt, ne)
        for mapping, offset, sessions, indices, dst_s, dst_i in (
            (tmap, record.template_offset, partial._t_session, partial._t_index, out._t_session, out._t_index),
            (emap, record.experience_offset, partial._e_session, partial._e_index, out._e_session, out._e_index),
        ):
            kept = np.flatnonzero(mapping >= offset)
            if not np.array_equal(mapping[kept], offset + np.arange(kept.size)):
                msg = "a merge must append the partial rows it keeps in their order"
                raise MergeError(msg)
            dst_s.extend(np.asarray(sessions, dtype=np.int64)[kept].tolist())
            dst_i.extend(np.asarray(indices, dtype=np.int64)[kept].tolist())
        return out

    def retagged(self, tags: Mapping[int, int]) -> RowIdentities:
        """Return a copy with session tags renamed (e.g. a new session's tag → its id); others unchanged."""

        def rename(values: list[int]) -> list[int]:
            return [tags.get(v, v) for v in values]

        next_index: dict[int, tuple[int, int]] = {}
        for key, (nt, ne) in self.next_index.items():
            old = next_index.get(tags.get(key, key), (0, 0))
            next_index[tags.get(key, key)] = (max(old[0], nt), max(old[1], ne))
        return RowIdentities(
            rename(self._t_session), list(self._t_index), rename(self._e_session), list(self._e_index), next_index
        )

    # ---------------------------------------------------------------- persistence
    def next_table(self) -> IntArray:
        """Return ``next_index`` as an (S, 3) int64 table: session, next template index, next experience index."""
        rows = [[k, v[0], v[1]] for k, v in sorted(self.next_index.items())]
        return np.asarray(rows, dtype=np.int64).reshape(-1, 3)


def next_index_from_table(table: npt.ArrayLike | None) -> dict[int, tuple[int, int]]:
    """Return the ``next_index`` mapping of :meth:`RowIdentities.next_table` output (empty for None)."""
    if table is None:
        return {}
    rows = np.asarray(table, dtype=np.int64).reshape(-1, 3)
    return {int(r[0]): (int(r[1]), int(r[2])) for r in rows}
