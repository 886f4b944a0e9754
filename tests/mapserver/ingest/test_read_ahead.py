"""Reading ahead (``MissionLog.frames_ahead``): the frames of ``frames()``, in order, with its errors, and a clean stop.

Each test runs with the worker in a forked process and in a thread; the reference is the log's own
``frames()`` read in the caller.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from mapserver.errors import IngestError
from mapserver.ingest import Frame, open_log
from mapserver.ingest import reader as reader_module
from mapserver.ingest.reader import ReadAhead
from tests.mapserver.ingest.conftest import (
    T0_NS,
    LogFactory,
    frame_images,
    image_msg,
    odometry_msg,
    varying_odometry,
    write_raw,
)

WORKERS = ["process", "thread"]
IMG, ODOM = "sensor_msgs/msg/Image", "nav_msgs/msg/Odometry"


def _same(a: list[Frame], b: list[Frame]) -> bool:
    if len(a) != len(b):
        return False
    pairs = zip(a, b, strict=True)
    return all(x.stamp_ns == y.stamp_ns and np.array_equal(x.image, y.image) and x.motion == y.motion for x, y in pairs)


@pytest.fixture
def log_path(make_log: LogFactory) -> Path:
    """A 60-frame JPEG log with changing odometry (more frames than one batch of the worker, fewer than its depth)."""
    return make_log("ahead", "bag", frame_images(60, 10.0, False), varying_odometry(240, 40.0), image_encoding="jpeg")


@pytest.mark.parametrize("worker", WORKERS)
@pytest.mark.parametrize(("start", "stop"), [(0, None), (7, 41), (59, None), (30, 30)])
def test_read_ahead_gives_the_frames_in_order(log_path: Path, worker: str, start: int, stop: int | None) -> None:
    with open_log(log_path) as log:
        expected = list(log.frames(start, stop))
        with log.frames_ahead(start, stop, worker=worker, depth=8) as frames:  # type: ignore[arg-type]
            got = list(frames)
    assert _same(got, expected)
    assert len(got) == (stop if stop is not None else 60) - start


@pytest.mark.parametrize("worker", WORKERS)
def test_leaving_early_stops_the_worker(log_path: Path, worker: str) -> None:
    with open_log(log_path) as log:
        ahead = log.frames_ahead(worker=worker, depth=4)  # type: ignore[arg-type]
        with ahead as frames:
            for index, _frame in enumerate(frames):
                if index == 3:
                    break
        assert not ahead._runner.is_alive()
        with pytest.raises(KeyboardInterrupt), log.frames_ahead(worker=worker, depth=4) as frames:  # type: ignore[arg-type]
            for _frame in frames:
                raise KeyboardInterrupt
        assert list(log.frames(0, 2))  # the log is still usable


def _bad_from(index: int) -> object:
    def build(ts: object, stamp: int) -> object:
        return image_msg(ts, stamp, "yuv422" if stamp >= T0_NS + index * 100_000_000 else "mono8")

    return build


@pytest.mark.parametrize("worker", WORKERS)
def test_an_error_in_the_reader_surfaces_where_frames_raises_it(tmp_path: Path, worker: str) -> None:
    """Frame 5 cannot be decoded: both raise the same IngestError after the same 5 frames."""
    path = write_raw(
        tmp_path / "bad.bag", "bag", [("/cam/image", IMG, _bad_from(5), 9), ("/odom", ODOM, odometry_msg, 30)]
    )
    with open_log(path) as log:
        direct: list[Frame] = []
        with pytest.raises(IngestError) as expected:
            for frame in log.frames():
                direct.append(frame)
        ahead: list[Frame] = []
        with pytest.raises(IngestError) as got, log.frames_ahead(worker=worker) as frames:  # type: ignore[arg-type]
            for frame in frames:
                ahead.append(frame)
    assert len(direct) == 5 and _same(ahead, direct)
    assert type(got.value) is type(expected.value) and str(got.value) == str(expected.value)
    assert "unsupported image encoding 'yuv422'" in str(got.value)


def test_a_reader_process_that_dies_is_an_ingest_error(log_path: Path) -> None:
    with open_log(log_path) as log, log.frames_ahead(worker="process", depth=4) as frames:
        iterator = iter(frames)
        next(iterator)
        os.kill(frames._runner.pid, signal.SIGKILL)
        with pytest.raises(IngestError, match=r"frame reader of .* stopped without an answer"):
            for _frame in iterator:
                pass


def test_a_daemonic_or_threaded_caller_reads_in_a_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """A celery worker's process may not have children, and a fork copies one thread of a threaded server:
    ``auto`` takes a thread there (and for a short range), a process in a single-threaded caller."""

    class Daemonic:
        daemon = True

    threads = {"count": 1}  # the test runner may hold threads of its own (xdist): the rule reads the count
    monkeypatch.setattr(reader_module.threading, "active_count", lambda: threads["count"])
    assert reader_module._worker_kind("auto") == "process"
    assert reader_module._worker_kind("auto", long_range=False) == "thread"
    threads["count"] = 2  # a server's job thread beside its event loop
    assert reader_module._worker_kind("auto") == "thread"
    threads["count"] = 1
    monkeypatch.setattr(reader_module.multiprocessing, "current_process", lambda: Daemonic())
    assert reader_module._worker_kind("auto") == "thread"
    assert reader_module._worker_kind("process") == "process"


def test_a_closed_log_cannot_read_ahead(log_path: Path) -> None:
    log = open_log(log_path)
    log.close()
    with pytest.raises(IngestError, match="closed"):
        ReadAhead(log)
