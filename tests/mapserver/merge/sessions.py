"""Engine-level helpers for merge tests: map a stretch of a LoopWorld, run a session through the online driver."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from core import Action, Engine, Params
from core.se3 import compose, inverse
from mapserver.merge import MergeEvent, OnlineMerger, Rollback, StoredMap
from tests.mapserver.merge.world import LoopWorld

# A small lattice (41 cells of 1 m: the 40 m loop never wraps it) with the Virtual Tour's weak
# injection (δ = 0.06, decay 1.5) so that the packet moves by path integration and operation (iii)
# decides whether the partial experiences are found again.
PARAMS = Params().replace(
    template_x_size=32, template_y_size=12, vt_shift_match=2, vt_step_match=1, vt_match_threshold=0.03,
    pc_dim_xy=41, pc_dim_th=36, pc_cell_x_size=1.0, exp_delta_pc_threshold=3.0, exp_loops=20,
    vt_min_inject_age=5, exp_initial_em_deg=0.0, pc_vt_inject_energy=0.06, vt_active_decay=1.5,
)


def map_stretch(
    world: LoopWorld, start: float, length: float, key: object, params: Params = PARAMS, step: float = 0.5
) -> StoredMap:
    """Run one session over [start, start + length] and return it as a stored map (origin = key)."""
    engine = Engine(params, origin=int(key))  # type: ignore[call-overload]
    for image, motion, stamp in world.drive(start, length, step=step):
        engine.step(image, motion, stamp)
    return StoredMap(key, params, engine.snapshot())


@dataclass
class Run:
    """What a session did under the online driver."""

    engine: Engine
    events: list[MergeEvent]
    arcs: np.ndarray
    created: np.ndarray  # per frame: the frame created an experience
    merged_frames: list[int] = field(default_factory=list)
    rolled_back_frames: list[int] = field(default_factory=list)
    rollbacks: list[Rollback] = field(default_factory=list)
    driver: OnlineMerger | None = None  # the online driver, as the log's end left it (a probation may run)

    def new_on_mapped_ground(self, mapped: list[tuple[float, float]], after: int | None = None) -> tuple[int, int]:
        """Return (frames, frames creating an experience) after the first merge where the route was mapped.

        ``mapped``: arc intervals mapped before the merge (the stored sessions' stretches); the
        session's own stretch before the merge is added.
        """
        first = self.merged_frames[0] if after is None else after
        covered = np.zeros(self.arcs.size, dtype=bool)
        for lo, hi in mapped:
            covered |= _within(self.arcs, lo, hi)
        own = self.arcs[: first + 1]
        covered |= np.isin(np.round(self.arcs * 2), np.round(own * 2))
        frames = np.arange(self.arcs.size) > first
        sel = frames & covered
        return int(sel.sum()), int(self.created[sel].sum())


def _within(arcs: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (arcs >= lo - 1e-9) & (arcs <= hi + 1e-9)


def run_session(
    world: LoopWorld,
    start: float,
    length: float,
    stored: list[StoredMap],
    *,
    params: Params = PARAMS,
    origin: int = 9,
    step: float = 0.5,
    **merger: object,
) -> Run:
    """Run a session from ``start`` over ``length`` metres, feeding the online driver after every frame."""
    engine = Engine(params, origin=origin)
    driver = OnlineMerger(stored, **merger)  # type: ignore[arg-type]
    arcs = world.arc(start, length, step=step)
    created = np.zeros(arcs.size, dtype=bool)
    merged_frames: list[int] = []
    rolled_back: list[int] = []
    for i, (image, motion, stamp) in enumerate(world.drive(start, length, step=step, t0=1000.0)):
        frame = SimpleNamespace(image=image, motion=motion, stamp_ns=round(stamp * 1e9))
        result = engine.step(image, motion, frame.stamp_ns * 1e-9)
        created[i] = result.action == Action.CREATE_NODE
        event = driver.observe(engine, result, frame)
        if isinstance(event, MergeEvent):
            engine = event.engine
            merged_frames.append(i)
        elif isinstance(event, Rollback):
            engine = event.engine
            rolled_back.append(i)
    return Run(engine, driver.events, arcs, created, merged_frames, rolled_back, driver.rollbacks, driver)


def true_alignment(world: LoopWorld, loaded_start: float, partial_start: float) -> np.ndarray:
    """Return the true T taking the partial session's map frame onto the loaded session's (x, y, z, yaw)."""
    return compose(inverse(world.pose(loaded_start)), world.pose(partial_start))
