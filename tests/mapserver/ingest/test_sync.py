"""Synchronisation: the map depends on the messages and their header stamps, never on how the log was recorded.

Logs are simulated (a short 4-DoF cave run, processed with the ``poseidon`` preset, torch front-end included) and
then re-recorded with rosbags' own writers under other receive times: played back at half rate a day later, or
with random per-message network delays that put messages out of stamp order within and across topics. Every variant,
and every container (.bag, .db3, .mcap) of the same scenario, must give the same map.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from core import preset
from mapserver.ingest import open_log
from mapserver.ingest.ordering import reorder_window
from mapserver.ingest.simulator import simulate
from mapserver.processing.pipeline import process_log

pytestmark = pytest.mark.slow

SHORT_CAVE = {"single_laps": 0.35}
DAY_NS = 86_400 * 1_000_000_000


def _simulated(tmp_path: Path, fmt: str, seed: int = 3) -> Path:
    out = tmp_path / f"sim_{fmt}"
    doc = simulate("cave3d", out, seed=seed, fmt=fmt, params=SHORT_CAVE, only=["single"])  # type: ignore[arg-type]
    return out / doc["single"]["log"]


def _rerecord(src: Path, dst: Path, receive: Any) -> list[int]:
    """Copy every message of ``src`` into ``dst`` with receive time ``receive(topic, index, t)``.

    Returns the image topic's header-stamp sequence in the new receive order (raw bytes are copied as they
    are, so header stamps and contents do not change).
    """
    with AnyReader([src]) as reader:
        rows = []
        for k, (conn, t, raw) in enumerate(reader.messages()):
            rows.append((int(receive(conn.topic, k, t)), k, conn.topic, conn.msgtype, bytes(raw)))
        image_stamps = {
            k: reader.deserialize(raw, msgtype).header.stamp
            for _, k, topic, msgtype, raw in rows
            if topic == "/robot/camera/image"
        }
    rows.sort()
    if src.suffix == ".bag":
        store = get_typestore(Stores.ROS1_NOETIC)
        with Writer1(dst) as writer:
            conns: dict[str, Any] = {}
            for t, _, topic, msgtype, raw in rows:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(conns[topic], t, raw)
    else:
        store = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if src.suffix == ".mcap" else StoragePlugin.SQLITE3
        with Writer2(dst, version=9, storage_plugin=plugin) as writer2:
            conns = {}
            for t, _, topic, msgtype, raw in rows:
                if topic not in conns:
                    conns[topic] = writer2.add_connection(topic, msgtype, typestore=store)
                writer2.write(conns[topic], t, raw)
    return [image_stamps[k].sec * 1_000_000_000 + image_stamps[k].nanosec for _, k, *_ in rows if k in image_stamps]


def _without_log_identity(doc: dict[str, Any]) -> dict[str, Any]:
    out = dict(doc)
    out["sessions"] = [{k: v for k, v in s.items() if k not in ("log_sha256", "name")} for s in doc["sessions"]]
    out["experiences"] = [{k: v for k, v in e.items() if k != "session"} for e in doc["experiences"]]
    return out


def _map(path: Path) -> dict[str, Any]:
    result = process_log(path, preset("poseidon"))
    assert result.document is not None
    return _without_log_identity(result.document)


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_other_playback_rate_and_network_delays_give_the_same_map(tmp_path: Path, fmt: str) -> None:
    src = _simulated(tmp_path, fmt)
    reference = _map(src)
    assert reference["experiences"] and len(reference["frames"]) > 50

    slow = tmp_path / f"half_rate.{fmt}"
    t0 = None

    def half_rate(_topic: str, _k: int, t: int) -> int:
        nonlocal t0
        t0 = t if t0 is None else t0
        return t0 + DAY_NS + 2 * (t - t0)

    _rerecord(src, slow if fmt == "bag" else slow.with_suffix(""), half_rate)
    if fmt != "bag":
        (slow.with_suffix("") / f"{slow.stem}.{fmt}").rename(slow)

    rng = np.random.default_rng(0)
    delays = rng.uniform(0.0, 1.2e9, size=100_000).astype(np.int64)  # up to 1.2 s: over two camera periods
    jittered = tmp_path / f"jitter.{fmt}"
    order = _rerecord(src, jittered if fmt == "bag" else jittered.with_suffix(""), lambda _t, k, t: t + delays[k])
    if fmt != "bag":
        (jittered.with_suffix("") / f"{jittered.stem}.{fmt}").rename(jittered)
    assert reorder_window(order) >= 1, "the jittered log must really hold images out of stamp order"

    assert _map(slow) == reference
    assert _map(jittered) == reference


def test_bag_db3_and_mcap_of_one_scenario_give_identical_maps(tmp_path: Path) -> None:
    maps = {fmt: _map(_simulated(tmp_path, fmt)) for fmt in ("bag", "db3", "mcap")}
    assert maps["bag"] == maps["db3"] == maps["mcap"]
    z = [e["z"] for e in maps["bag"]["experiences"]]
    assert max(z) - min(z) > 0.05  # a real 4-DoF map, not a trivially planar one


def test_frames_come_in_stamp_order_from_a_jittered_log(tmp_path: Path) -> None:
    src = _simulated(tmp_path, "bag")
    rng = np.random.default_rng(1)
    delays = rng.uniform(0.0, 1.5e9, size=100_000).astype(np.int64)
    jittered = tmp_path / "jitter.bag"
    order = _rerecord(src, jittered, lambda _t, k, t: t + delays[k])
    with open_log(jittered) as log, open_log(src) as original:
        got = [(f.stamp_ns, f.image.tobytes(), f.motion) for f in log.frames()]
        want = [(f.stamp_ns, f.image.tobytes(), f.motion) for f in original.frames()]
    assert order != sorted(order)
    assert [g[0] for g in got] == sorted(order)
    assert got == want
