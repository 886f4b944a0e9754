"""The simulator's AUV navigation sensors (cave3d ``nav=1``, the ``seabed`` scenario), end to end."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from mapserver.errors import InputError
from mapserver.evaluation.maps import evaluate_map
from mapserver.formats import read_tum
from mapserver.ingest import open_log
from mapserver.ingest.simulator import plan_scenario
from mapserver.params import resolve_params
from mapserver.processing.run import process_log
from tests.simulations import simulate_once

NAV_TOPICS = {"/robot/dvl/twist", "/robot/imu", "/robot/pressure", "/tf_static"}


def _topic_digests(path: Path) -> dict[str, str]:
    """Each topic's messages (stamps and raw bytes) hashed."""
    digests: dict[str, hashlib._Hash] = {}
    with AnyReader([path]) as reader:
        for conn, stamp, raw in reader.messages():
            h = digests.setdefault(conn.topic, hashlib.sha256())
            h.update(str(stamp).encode())
            h.update(raw)
    return {topic: h.hexdigest() for topic, h in digests.items()}


def test_cave3d_nav_adds_topics_and_changes_none_of_the_others(tmp_path: Path) -> None:
    base = {"session1_laps": 0.2}
    simulate_once("cave3d", tmp_path / "plain", seed=2, fmt="mcap", params=base, only=["session1"])
    simulate_once("cave3d", tmp_path / "nav", seed=2, fmt="mcap", params={**base, "nav": 1}, only=["session1"])
    plain = _topic_digests(tmp_path / "plain" / "session1.mcap")
    nav = _topic_digests(tmp_path / "nav" / "session1.mcap")
    assert set(plain) == {"/robot/camera/image", "/robot/odom", "/robot/ground_truth"}  # no new topic by default
    assert set(nav) == set(plain) | NAV_TOPICS
    assert {t: nav[t] for t in plain} == plain  # odometry, images and ground truth byte for byte the same
    with pytest.raises(InputError, match="nav must be 0 or 1"):
        plan_scenario("cave3d", params={"nav": 2})


def test_cave3d_without_odometry_is_mapped_on_the_fused_sensors(tmp_path: Path) -> None:
    doc = simulate_once("cave3d", tmp_path, seed=0, params={"single_laps": 0.5, "nav": 1, "odometry": 0},
                        only=["single"])  # fmt: skip
    log = tmp_path / doc["single"]["log"]
    with open_log(log) as opened:
        assert opened.mapping.odometry is None and opened.motion_source == "navigation"
        opened.verify()
        report = opened.navigation_report
    assert report is not None and report.dvl_gaps > 0 and report.mounts["dvl"].startswith("/tf_static")
    result = process_log(log, resolve_params("poseidon-lvc"))
    assert result.document is not None and result.experiences > 3
    ev = evaluate_map(result.document, read_tum(tmp_path / doc["single"]["ground_truth"]))
    # the fused dead reckoning (DVL scale error 1 %, lost bottom, IMU yaw drift) stays within 0.1 m over 7.7 m
    assert ev["odometry_ape_rmse"] < 0.1 and ev["odometry_ape_z_rmse"] < 0.02
    assert ev["ape_rmse"] < 0.3


def test_seabed_revisits_its_first_leg_at_the_same_depth() -> None:
    plan = plan_scenario("seabed", seed=1)
    assert plan.navigation is not None and not plan.odometry and plan.preset == "poseidon-lvc"
    spec = plan.single.spec if plan.single else None
    assert spec is not None and spec.depth is not None
    revisit = plan.info["revisit_start_m"]
    route = spec.route
    leg = 6.0
    first = np.linspace(0.5, leg - 0.5, 12)  # arc length along the first leg: x = s, y = 0
    last = route.length - leg + first  # the revisit's leg, flown last
    np.testing.assert_allclose(route.position(first), np.column_stack([first, np.zeros(12)]), atol=1e-6)
    np.testing.assert_allclose(route.position(last), route.position(first), atol=1e-3)
    np.testing.assert_allclose(spec.depth(last), spec.depth(first), atol=1e-3)
    assert np.ptp(spec.depth(np.linspace(0.0, revisit, 200))) > 0.5  # the survey changes depth
    assert [s.name for s in plan.sessions] == ["session1", "session2"]
    with pytest.raises(InputError, match="even number of legs"):
        plan_scenario("seabed", params={"legs": 3})
