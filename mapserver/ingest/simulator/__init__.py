"""Mission simulator: synthetic missions with ground truth, written as ROS bags (``mapserver simulate``).

A scenario (:data:`SCENARIOS`) is a 3-D world of textured vertical surfaces (:mod:`.world`,
:mod:`.textures`), routes (:mod:`.routes`) and sessions driven along them (:mod:`.drive`: true trajectory
with per-visit variation, drifting odometry, ground truth). A panoramic camera (:mod:`.render`) images
the world at the vehicle's pose. :func:`simulate` writes every session as a ``.bag``, ``.db3`` or
``.mcap`` log plus a TUM ground-truth file and ``scenario.json``; everything is deterministic per seed.
"""

from mapserver.ingest.simulator.drive import Drive, DriveSpec, Noise, Rates, VehicleErrors, simulate_drive
from mapserver.ingest.simulator.output import SCENARIO_FILE, plan_scenario, render_frames, simulate, simulate_session
from mapserver.ingest.simulator.render import Camera, expose, render
from mapserver.ingest.simulator.scenarios import SCENARIOS, Plan, ScenarioDef, SessionPlan
from mapserver.ingest.simulator.world import World, WorldBuilder

__all__ = [
    "SCENARIOS",
    "SCENARIO_FILE",
    "Camera",
    "Drive",
    "DriveSpec",
    "Noise",
    "Plan",
    "Rates",
    "ScenarioDef",
    "SessionPlan",
    "VehicleErrors",
    "World",
    "WorldBuilder",
    "expose",
    "plan_scenario",
    "render",
    "render_frames",
    "simulate",
    "simulate_drive",
    "simulate_session",
]
