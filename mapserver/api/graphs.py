"""Path queries from a per-map cache of :class:`core.paths.ExperienceGraph`, keyed by the map's version.

Every write of a map's state increments ``maps.version`` (``store.claim_map``), so a cache entry
``(map id, version)`` is exactly the stored graph of that version: a query reads the map's row (one
indexed lookup), and only when the version changed is the graph loaded again — links and poses only
(``store.queries.load_graph``), never templates or engine state — in the same read transaction, so
graph and version always agree. Least recently used maps are evicted beyond ``capacity``.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

from core.paths import ExperienceGraph, NoPath, PathResult, Weight
from mapserver.errors import ConflictError, NotFoundError
from mapserver.store import Database, MapRecord, get_map
from mapserver.store.queries import load_graph


@dataclass(frozen=True, slots=True)
class CachedGraph:
    """A map's graph as of one version."""

    map_id: int
    name: str
    version: int
    graph: ExperienceGraph


class GraphCache:
    """Thread-safe LRU of experience graphs (see the module docstring).

    Args:
        db: the map store.
        capacity: maps kept in memory.
    """

    def __init__(self, db: Database, capacity: int = 8) -> None:
        self.db = db
        self.capacity = capacity
        self._entries: OrderedDict[int, CachedGraph] = OrderedDict()
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()
        self.builds = 0

    def _lookup(self, record: MapRecord) -> CachedGraph | None:
        with self._lock:
            entry = self._entries.get(record.id)
            if entry is not None and entry.version == record.version:
                self._entries.move_to_end(record.id)
                return entry
            return None

    def get(self, name: str) -> CachedGraph:
        """Return the current graph of map ``name``, loading it when the map changed.

        Raises:
            UnknownMapError: no such map.
        """
        with self.db.read() as conn:
            record = get_map(conn=conn, name=name)
        entry = self._lookup(record)
        if entry is not None:
            return entry
        with self._build_lock:  # one build at a time: concurrent first queries wait for it
            with self.db.read() as conn:
                record = get_map(conn=conn, name=name)
                entry = self._lookup(record)
                if entry is not None:
                    return entry
                loaded = load_graph(conn=conn, map_id=record.id)
            graph = ExperienceGraph(
                loaded.poses, loaded.link_from, loaded.link_to, loaded.link_dt, loaded.link_distance
            )
            entry = CachedGraph(record.id, record.name, record.version, graph)
            self.builds += 1
            with self._lock:
                self._entries[record.id] = entry
                self._entries.move_to_end(record.id)
                while len(self._entries) > self.capacity:
                    self._entries.popitem(last=False)
        return entry

    def shortest_path(self, name: str, source: int, target: int, weight: Weight) -> PathResult:
        """Return the shortest path between two experiences of map ``name``.

        Raises:
            UnknownMapError: no such map (404).
            NotFoundError: an experience id the map does not have (404).
            ConflictError: the two experiences are not connected (409).
        """
        entry = self.get(name)
        for node in (source, target):
            if not 0 <= node < entry.graph.size:
                msg = f"map {name!r} has no experience {node} (ids are 0..{entry.graph.size - 1})"
                if entry.graph.size == 0:
                    msg = f"map {name!r} has no experience {node} (it has none)"
                raise NotFoundError(msg)
        result = entry.graph.shortest_path(source, target, weight)
        if isinstance(result, NoPath):
            msg = f"no path from experience {source} to {target} in map {name!r}: they are not connected"
            raise ConflictError(msg)
        return result
