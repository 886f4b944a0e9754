"""Multisession merging of engine states (Menezes et al. 2023, Algorithm 1, corrected and generalised).

Public surface::

    from mapserver.merge import OnlineMerger, StoredMap, merge_maps, merge_states
    merger = OnlineMerger([StoredMap(key, params, state), ...])   # online, fed after every engine.step
    event = merger.observe(engine, result)                          # MergeEvent | None
    engine, record = merge_maps(StoredMap(a, ...), StoredMap(b, ...))  # offline: A into B
    state, record = merge_states(loaded_state, partial_state, match)   # the pure algorithm on snapshots

Modules: ``se3`` (4-DoF pose algebra), ``lattice`` (pose-cell lattice transform),
``record`` (Match, MergeRecord), ``snapshot`` (schema checks), ``states`` (merge_states),
``engines`` (engine-level merge), ``confirm`` (match observations, the offline confirmation rule),
``hypotheses`` (the online merge decision), ``verify`` (probation and rollback), ``online`` (driver),
``resume`` (the driver's state between runs),
``offline`` (search and merge of two stored maps).
"""

from mapserver.merge.confirm import Observation, Streak
from mapserver.merge.engines import StoredMap, merge_engine, merge_snapshots, restore_merged
from mapserver.merge.lattice import LatticeTransform
from mapserver.merge.offline import find_match, merge_maps
from mapserver.merge.online import MergeEvent, OnlineMerger, Rollback, default_position_tolerance
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.states import merge_states

__all__ = [
    "LatticeTransform",
    "Match",
    "MergeEvent",
    "MergeRecord",
    "Observation",
    "OnlineMerger",
    "Rollback",
    "StoredMap",
    "Streak",
    "default_position_tolerance",
    "find_match",
    "merge_engine",
    "merge_maps",
    "merge_snapshots",
    "merge_states",
    "restore_merged",
]
