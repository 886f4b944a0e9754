"""A sonar image topic as the sdr-htm front-end's second modality (issue 17 part 1, Eq. 4.3): read, fused, stored."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import preset
from core.engine import Engine
from core.neocortex import NeocortexViewCells
from mapserver.errors import IngestError, InputError
from mapserver.ingest import open_log
from mapserver.ingest.topics import TopicInfo, choose_topics, map_topics
from mapserver.processing.run import run_engine
from tests.mapserver.ingest.conftest import T0_NS, LogFactory, arc_odometry, frame_images, test_image

SONAR = "/robot/sonar/image"
SDR = preset("irat").replace(frontend="sdr-htm", template_x_size=16, template_y_size=8)  # the logs' 32 × 24 images


def _sonar_images(n: int, rate_hz: float, offset_ns: int) -> list[tuple[int, np.ndarray]]:
    return [(T0_NS + offset_ns + round(i * 1e9 / rate_hz), test_image(100 + 7 * i, False, (40, 60))) for i in range(n)]


def _log(make_log: LogFactory, name: str = "sonar.bag") -> tuple[Path, list[tuple[int, np.ndarray]]]:
    sonar = _sonar_images(6, 4.0, offset_ns=150_000_000)  # 4 Hz from 0.15 s; the camera: 10 Hz from 0
    path = make_log(name, "bag", frame_images(20, 10.0, False), arc_odometry(40, 20.0), sonar=sonar, sonar_topic=SONAR)
    return path, sonar


def test_the_sonar_topic_is_named_not_guessed_and_must_be_another_image_topic() -> None:
    topics = [TopicInfo("/cam", "sensor_msgs/msg/Image", 10, 10.0), TopicInfo(SONAR, "sensor_msgs/msg/Image", 4, 4.0),
              TopicInfo("/odom", "nav_msgs/msg/Odometry", 20, 20.0)]  # fmt: skip
    assert "sonar" not in choose_topics(topics)  # never automatic: a log without it reads as before
    assert map_topics(topics).as_dict() == {"image": "/cam", "odometry": "/odom", "ground_truth": None}
    mapping = map_topics(topics, {"sonar": SONAR})
    assert mapping.sonar == SONAR and mapping.as_dict()["sonar"] == SONAR
    assert map_topics(topics, {"sonar": "none"}).sonar is None
    with pytest.raises(IngestError, match="has type 'nav_msgs/msg/Odometry'"):
        map_topics(topics, {"sonar": "/odom"})
    with pytest.raises(IngestError, match="is the camera topic"):
        map_topics(topics, {"sonar": "/cam"})


def test_each_frame_carries_the_newest_sonar_image_at_or_before_its_stamp(make_log: LogFactory) -> None:
    path, sonar = _log(make_log)
    stamps = np.array([s for s, _ in sonar])
    with open_log(path, {"sonar": SONAR}) as log:
        frames = list(log.frames())
        tail = list(log.frames(start=7))
    assert frames[0].sonar is None and frames[1].sonar is None  # 0 s, 0.1 s: before the first sonar (0.15 s)
    for frame in frames[2:]:
        newest = int(np.searchsorted(stamps, frame.stamp_ns, side="right")) - 1
        np.testing.assert_array_equal(frame.sonar, sonar[newest][1])
    for a, b in zip(frames[7:], tail, strict=True):  # a later start reads the same
        np.testing.assert_array_equal(a.sonar, b.sonar)
    with open_log(path) as log:
        assert all(f.sonar is None for f in log.frames())  # not named: not read


def test_the_sonar_sdr_is_fused_by_or_with_its_own_projection() -> None:
    cells = NeocortexViewCells(SDR)
    camera, sonar = test_image(1, False, (48, 64)), test_image(50, False, (40, 60))
    alone = cells.sdr(camera)
    fused = cells.sdr(camera, sonar)
    sonar_bits = fused & ~alone
    assert int(alone.sum()) == 2 * cells.k and bool(torch.all(fused >= alone))  # OR keeps the camera's bits
    assert int(fused.sum()) > int(alone.sum()) and int(sonar_bits.sum()) <= 2 * cells.k
    assert cells.sonar_projection is not None and not torch.equal(cells.sonar_projection, cells.projection)


def test_a_run_with_sonar_differs_from_camera_only_and_resumes_bit_for_bit(make_log: LogFactory) -> None:
    path, _ = _log(make_log, "resume.bag")
    whole, camera_only = Engine(SDR), Engine(SDR)
    with open_log(path, {"sonar": SONAR}) as log:
        frames = list(log.frames())
    for f in frames:
        whole.step(f.image, f.motion, f.stamp_ns * 1e-9, f.sonar)
        camera_only.step(f.image, f.motion, f.stamp_ns * 1e-9)
    a, b = whole.snapshot(), camera_only.snapshot()
    assert "nc_sonar_projection_digest" in a and "nc_sonar_projection_digest" not in b
    assert not np.array_equal(a["nc_sp_permanence"], b["nc_sp_permanence"])  # the sonar bits reached the pooler
    first = Engine(SDR)
    for f in frames[:9]:
        first.step(f.image, f.motion, f.stamp_ns * 1e-9, f.sonar)
    second = Engine.restore(SDR, first.snapshot())
    for f in frames[9:]:
        second.step(f.image, f.motion, f.stamp_ns * 1e-9, f.sonar)
    split = second.snapshot()
    assert a.keys() == split.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], split[key], err_msg=key)


def test_lvc_refuses_a_sonar_topic_with_the_reason(make_log: LogFactory) -> None:
    path, _ = _log(make_log, "lvc.bag")
    with pytest.raises(InputError, match="modality of the sdr-htm front-end"):
        run_engine(Engine(preset("irat")), open_log(path, {"sonar": SONAR}))
    with pytest.raises(ValueError, match="needs the sdr-htm front-end"):
        Engine(preset("irat")).step(test_image(0, False), None, 0.0, test_image(1, False))
