"""Path queries from a per-map cache of :class:`core.paths.ExperienceGraph`, keyed by the map's version.

Every write of a map's state increments ``maps.version`` (``store.claim_map``), so a cache entry
``(map id, version)`` is exactly the stored graph of that version. A query first asks the database
for the map's ``(id, version)`` (:meth:`GraphCache.current`: one indexed lookup of two integers,
``store.queries.map_version``); only when that is not the cached version is the graph loaded again
(:meth:`GraphCache.get`) — links and poses only (``store.queries.load_graph``), never templates or engine
state — in one read transaction with the map's row, so graph and version always agree. Least recently
used maps are evicted beyond ``capacity``. The version check is not cached in memory: a write by
another process (``mapserver process`` on the same database) is seen by the very next query.

Graphs are built once, under a lock, and shared: a query takes no lock. The table of cached graphs is
never changed in place (a build or an eviction installs a new one), a built graph is read-only
(:class:`core.paths.ExperienceGraph`), and recency is one counter value per map.

The API calls :meth:`current` and :meth:`path` on the event loop (both are short: an indexed lookup,
and one Dijkstra over the contracted graph that stops at the target) and :meth:`get` in a worker thread
(a load and a build).
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from core.paths import ExperienceGraph, NoPath, PathResult, Weight
from mapserver.errors import ConflictError, NotFoundError
from mapserver.store import Database, MapRecord, get_map
from mapserver.store.queries import load_graph, map_version


@dataclass(frozen=True, slots=True)
class CachedGraph:
    """A map's graph as of one version."""

    map_id: int
    name: str
    version: int
    graph: ExperienceGraph

    def path(self, source: int, target: int, weight: Weight) -> PathResult:
        """Return the shortest path between two experiences of this map.

        Raises:
            NotFoundError: an experience id the map does not have (404).
            ConflictError: the two experiences are not connected (409).
        """
        size = self.graph.size
        for node in (source, target):
            if not 0 <= node < size:
                msg = f"map {self.name!r} has no experience {node} (ids are 0..{size - 1})"
                if size == 0:
                    msg = f"map {self.name!r} has no experience {node} (it has none)"
                raise NotFoundError(msg)
        result = self.graph.shortest_path(source, target, weight)
        if isinstance(result, NoPath):
            msg = f"no path from experience {source} to {target} in map {self.name!r}: they are not connected"
            raise ConflictError(msg)
        return result


class GraphCache:
    """Thread-safe LRU of experience graphs, read without a lock (see the module docstring).

    Args:
        db: the map store.
        capacity: maps kept in memory.
    """

    def __init__(self, db: Database, capacity: int = 8) -> None:
        self.db = db
        self.capacity = capacity
        self._entries: Mapping[int, CachedGraph] = MappingProxyType({})
        self._used: dict[int, int] = {}  # map id → tick of its latest query (the LRU order)
        self._ticks = itertools.count()
        self._build_lock = threading.Lock()
        self.builds = 0

    def _lookup(self, map_id: int, version: int) -> CachedGraph | None:
        """Return the cached graph of ``map_id`` if it is of ``version`` (no lock: one read of the table)."""
        entry = self._entries.get(map_id)
        if entry is None or entry.version != version:
            return None
        self._used[map_id] = next(self._ticks)
        return entry

    def _install(self, entry: CachedGraph) -> None:
        """Install a new table with ``entry``, evicting the least recently queried maps beyond ``capacity``."""
        entries = dict(self._entries)
        entries[entry.map_id] = entry
        self._used[entry.map_id] = next(self._ticks)
        while len(entries) > self.capacity:
            del entries[min(entries, key=lambda key: self._used.get(key, -1))]
        self._entries = MappingProxyType(entries)
        for key in [key for key in list(self._used) if key not in entries]:
            self._used.pop(key, None)

    def current(self, name: str) -> CachedGraph | None:
        """Return the cached graph of map ``name`` if it is the stored version, else None (no such map included).

        One indexed lookup of the map's id and version; nothing is loaded.
        """
        with self.db.read() as conn:
            found = map_version(conn=conn, name=name)
        return None if found is None else self._lookup(*found)

    def get(self, name: str) -> CachedGraph:
        """Return the current graph of map ``name``, loading and building it when the map changed.

        Raises:
            UnknownMapError: no such map.
        """
        entry = self.current(name)
        if entry is not None:
            return entry
        with self._build_lock:  # one build at a time: concurrent first queries wait for it
            with self.db.read() as conn:
                record: MapRecord = get_map(conn=conn, name=name)
                entry = self._lookup(record.id, record.version)
                if entry is not None:
                    return entry
                loaded = load_graph(conn=conn, map_id=record.id)
            graph = ExperienceGraph(
                loaded.poses, loaded.link_from, loaded.link_to, loaded.link_dt, loaded.link_distance
            )
            entry = CachedGraph(record.id, record.name, record.version, graph)
            self.builds += 1
            self._install(entry)
        return entry

    def shortest_path(self, name: str, source: int, target: int, weight: Weight) -> PathResult:
        """Return the shortest path between two experiences of map ``name`` (:meth:`get`, then the search).

        Raises:
            UnknownMapError: no such map (404).
            NotFoundError: an experience id the map does not have (404).
            ConflictError: the two experiences are not connected (409).
        """
        return self.get(name).path(source, target, weight)
