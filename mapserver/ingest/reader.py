"""Reading mission logs: ROS 1 ``.bag``, ROS 2 bag directories and standalone ``.db3`` / ``.mcap`` files.

:func:`open_log` opens a log with ``rosbags.highlevel.AnyReader``, lists its topics, chooses the topic
mapping (rule in :mod:`mapserver.ingest.topics`) and checks, before returning, that a usable camera topic
exists and that its first image decodes. Every failure (missing path, not a bag, truncated or corrupt
data, no camera, unsupported encoding) is one :class:`~mapserver.errors.IngestError` line naming the path.

Stamps and order: images, odometry and ground truth are stamped with their message header stamp; a zero
header stamp falls back to the bag's receive time. Every stream is read in **header-stamp order** (equal
stamps in receive order), re-sequenced from the bag's receive order with bounded memory
(:mod:`mapserver.ingest.ordering`), so the result does not depend on how the log was recorded or played
back: a log recorded with other receive times, or with messages arriving out of order, gives the same
frames. Each frame's motion is the odometry integrated from the previous frame's stamp up to its own (the
odometry being a second, independent stamp-ordered stream). Since everything depends only on the message
contents and stamps, a ``.bag``, ``.db3`` and ``.mcap`` of the same data give identical frames.

Odometry mode (twist integration or pose differencing, see :mod:`mapserver.ingest.odometry`), decided per
log on first use unless given to :func:`open_log`: the odometry topic is scanned in stamp order until the
first informative message: one with a non-zero twist means **twist**; a pose that moved (more than 1e-9 m
or rad from the first message) while every twist so far was exactly zero means **pose**; a log that never
moves is treated as twist (both give zero motion).

Navigation (a log without an ``odometry`` role whose mapping has ``dvl`` and ``imu`` topics; rule in
:func:`mapserver.ingest.topics.motion_source`): the DVL, IMU and depth topics are each read in stamp order,
merged, and fused (:mod:`mapserver.ingest.fusion`, sensor mountings from ``/tf_static`` or
:class:`~mapserver.ingest.navigation.NavParams`); the fused estimates take the odometry's place and are
differenced at the frame stamps (pose mode), through the same odometry check.

Each streaming call (:meth:`MissionLog.frames`, :meth:`MissionLog.ground_truth`) opens its own readers,
so several streams of one log may be consumed interleaved (rosbags readers share file positions).
:meth:`MissionLog.frames_ahead` runs :meth:`MissionLog.frames` in a worker (a forked process, or a thread)
that reads and decodes ahead of the caller into a bounded queue: the same frames in the same order, and the
same errors at the same point of the stream (:class:`ReadAhead`).
Memory is bounded regardless of log size: messages are streamed, never loaded all at once; per topic a
stamp index of 8 bytes per message is kept, re-sequencing holds at most
:data:`~mapserver.ingest.ordering.REORDER_LIMIT` messages, and the odometry buffer holds only the
messages between two frames.
"""

from __future__ import annotations

import contextlib
import hashlib
import multiprocessing
import pickle
import queue
import signal
import threading
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_typestore

from core.config import ConfigError
from core.motion import ZERO_MOTION, Motion
from mapserver.errors import IngestError, InputError, LimitError, describe_cause
from mapserver.ingest.decode import decode_image
from mapserver.ingest.frames import Frame, IngestReport, PoseSample
from mapserver.ingest.fusion import ComplementaryFilter, NavigationReport, NavSample, fuse, merge_samples
from mapserver.ingest.navigation import (
    DVL_TYPES,
    TF_STATIC_TOPIC,
    TF_TYPE,
    NavParams,
    StaticTree,
    depth_sample,
    dvl_sample,
    imu_sample,
    linear_covariance_diagonal,
    reports_covariance,
    sensor_mount,
    static_tree,
)
from mapserver.ingest.odometry import (
    OdometryCheck,
    OdometryMode,
    OdometryState,
    OdometryTrack,
    pose_moved,
    state_from_message,
    state_problem,
    twist_is_zero,
)
from mapserver.ingest.ordering import raw_header_stamp, stamp_ordered
from mapserver.ingest.topics import TopicInfo, TopicMapping, map_topics

LOG_SUFFIXES = (".bag", ".db3", ".mcap")
_HASH_CHUNK = 1 << 20
READ_AHEAD = 64
"""Frames a :class:`ReadAhead` worker reads and decodes before the caller takes them (bounded memory)."""
_BATCH = 16
"""Frames per message from the worker; its first message carries one frame, so the first is not held back."""
_POLL_S = 0.1
"""How often a blocked thread worker, or its caller, checks that the other side is still there."""
Worker = Literal["auto", "process", "thread"]


class _Newest:
    """The newest image of a topic at or before a stamp, decoded once (the sonar modality of a frame)."""

    def __init__(self, log: Any, reader: AnyReader, topic: str) -> None:
        self._log, self._reader, self._topic = log, reader, topic
        self._stream = iter(log._ordered(reader, topic))
        self._ahead: tuple[int, Any] | None = self._next()
        self._newest: Any = None
        self._image: np.ndarray | None = None

    def _next(self) -> tuple[int, Any] | None:
        item = next(self._stream, None)
        if item is None:
            return None
        conn, receive_ns, raw = item
        msg = self._log._deserialize(self._reader, raw, conn)
        return _header_stamp(msg, receive_ns), msg

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """Return the newest image stamped at or before ``stamp_ns`` (None before the first)."""
        while self._ahead is not None and self._ahead[0] <= stamp_ns:
            self._newest, self._image = self._ahead[1], None
            self._ahead = self._next()
        if self._newest is not None and self._image is None:
            self._image = decode_image(self._newest, self._topic)
        return self._image


def _header_stamp(msg: Any, receive_ns: int) -> int:
    """Return the header stamp in ns, or the receive time when the header stamp is zero."""
    header = getattr(msg, "header", None)
    if header is None:
        return int(receive_ns)
    stamp = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return stamp if stamp != 0 else int(receive_ns)


def _check_path(path: Path) -> None:
    if not path.exists():
        msg = f"log not found: {str(path)!r}"
        raise IngestError(msg)
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            msg = f"not a ROS 2 bag directory (no metadata.yaml): {str(path)!r}"
            raise IngestError(msg)
        return
    if path.suffix.lower() not in LOG_SUFFIXES:
        msg = f"unsupported log {str(path)!r}: expected a .bag, .db3 or .mcap file or a ROS 2 bag directory"
        raise IngestError(msg)


def _new_reader(path: Path) -> AnyReader:
    """Create and open an AnyReader, translating every failure into IngestError."""
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as err:  # rosbags raises many types for broken files (ReaderError, struct, OS, ...)
        msg = f"not a readable bag (truncated or corrupt?): {str(path)!r}: {_describe(err)}"
        raise IngestError(msg) from err
    return reader


def _describe(err: BaseException) -> str:
    return describe_cause(err)


class MissionLog:
    """An open mission log; use :func:`open_log` to create one, and close it (it is a context manager).

    Attributes:
        path: the log's path.
        topics: every topic with type, message count and mean rate.
        mapping: the topics frames, odometry and ground truth are read from.
        start_ns: receive time of the first message (ns).
        end_ns: receive time of the last message (ns).

    """

    def __init__(
        self,
        path: Path,
        reader: AnyReader,
        topics: list[TopicInfo],
        mapping: TopicMapping,
        odometry_mode: OdometryMode | None = None,
        navigation: NavParams | None = None,
    ) -> None:
        self.path = path
        self.nav_params = navigation or NavParams()
        self.navigation_report: NavigationReport | None = None
        self._dvl_covariance: bool | None = None
        self.topics = topics
        self.mapping = mapping
        self._reader: AnyReader | None = reader
        self.start_ns = int(reader.start_time) if reader.message_count else 0
        self.end_ns = int(reader.end_time) if reader.message_count else 0
        self._odometry_mode = odometry_mode
        self._sha256: str | None = None
        self._stamp_indices: dict[str, npt.NDArray[np.int64]] = {}
        self.odometry_check: OdometryCheck | None = None

    # -- lifecycle -------------------------------------------------------------------------------------
    def close(self) -> None:
        """Close the underlying reader (idempotent)."""
        reader, self._reader = self._reader, None
        if reader is not None and reader.stack is not None:
            reader.close()

    def __enter__(self) -> MissionLog:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _require_open(self) -> AnyReader:
        if self._reader is None:
            msg = f"log is closed: {str(self.path)!r}"
            raise IngestError(msg)
        return self._reader

    # -- metadata --------------------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        """Seconds between the first and the last message (receive time)."""
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def sha256(self) -> str:
        """SHA-256 hex digest of the log file, or of all files of a bag directory in sorted order."""
        if self._sha256 is None:
            digest = hashlib.sha256()
            files = (
                sorted(p for p in self.path.rglob("*") if p.is_file()) if self.path.is_dir() else [self.path]
            )
            for file in files:
                with file.open("rb") as handle:
                    while chunk := handle.read(_HASH_CHUNK):
                        digest.update(chunk)
            self._sha256 = digest.hexdigest()
        return self._sha256

    def count_frames(self) -> int:
        """Return the number of camera frames (messages on the image topic)."""
        return next(t.count for t in self.topics if t.name == self.mapping.image)

    @property
    def odometry_mode(self) -> OdometryMode | None:
        """``'twist'`` or ``'pose'`` (see the module docstring), None when the log has no odometry topic."""
        if self.mapping.odometry is None:
            return None
        if self._odometry_mode is None:
            self._odometry_mode = self._detect_odometry_mode()
        return self._odometry_mode

    def _detect_odometry_mode(self) -> OdometryMode:
        reader = self._require_open()
        assert self.mapping.odometry is not None
        first: OdometryState | None = None
        for conn, receive_ns, raw in self._ordered(reader, self.mapping.odometry):
            msg = self._deserialize(reader, raw, conn)
            if not twist_is_zero(msg):
                return "twist"
            state = state_from_message(msg, _header_stamp(msg, receive_ns))
            if first is None:
                first = None if state_problem(state) is not None else state
            elif pose_moved(first, state):
                return "pose"
        return "twist"

    # -- streaming -------------------------------------------------------------------------------------
    def _connections(self, reader: AnyReader, topic: str) -> list[Connection]:
        return [c for c in reader.connections if c.topic == topic]

    def _messages(self, reader: AnyReader, topic: str) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield ``(connection, receive_ns, raw)`` of one topic in bag order, errors as IngestError."""
        connections = self._connections(reader, topic)
        if not connections:
            return
        iterator = reader.messages(connections=connections)
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                return
            except Exception as err:
                msg = f"corrupt log {str(self.path)!r} while reading {topic}: {_describe(err)}"
                raise IngestError(msg) from err
            yield item

    def _stamp_index(self, reader: AnyReader, topic: str) -> npt.NDArray[np.int64]:
        """Return the header stamps (receive time when zero) of a topic's messages in receive order (cached)."""
        cached = self._stamp_indices.get(topic)
        if cached is not None:
            return cached
        stamps: list[int] = []
        for conn, receive_ns, raw in self._messages(reader, topic):
            stamp = raw_header_stamp(raw, bool(reader.is2))
            if stamp is None:
                stamp = _header_stamp(self._deserialize(reader, raw, conn), receive_ns)
            stamps.append(stamp if stamp != 0 else int(receive_ns))
        index = np.asarray(stamps, dtype=np.int64)
        listed = next((t.count for t in self.topics if t.name == topic), index.size)
        if index.size != listed:  # a damaged file whose reader stops early (or reads on past its index)
            msg = f"corrupt log {str(self.path)!r}: {topic} has {index.size} readable messages of the {listed} listed"
            raise IngestError(msg)
        self._stamp_indices[topic] = index
        return index

    def _ordered(self, reader: AnyReader, topic: str) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield ``(connection, receive_ns, raw)`` of one topic in header-stamp order (see the module docstring)."""
        stamps = self._stamp_index(self._require_open(), topic)
        try:
            yield from stamp_ordered(stamps, lambda: self._messages(reader, topic))
        except ValueError as err:
            msg = f"corrupt log {str(self.path)!r} while reading {topic}: {err}"
            raise IngestError(msg) from err

    def _deserialize(self, reader: AnyReader, raw: bytes, conn: Connection) -> Any:
        try:
            return reader.deserialize(raw, conn.msgtype)
        except Exception as err:
            msg = f"corrupt message on {conn.topic} in {str(self.path)!r}: {_describe(err)}"
            raise IngestError(msg) from err

    def _odometry_states(self, reader: AnyReader) -> Iterator[OdometryState]:
        assert self.mapping.odometry is not None
        for conn, receive_ns, raw in self._ordered(reader, self.mapping.odometry):
            msg = self._deserialize(reader, raw, conn)
            yield state_from_message(msg, _header_stamp(msg, receive_ns))

    @property
    def motion_source(self) -> str | None:
        """``odometry``, ``navigation`` (DVL + IMU fusion) or None (:func:`~mapserver.ingest.topics.motion_source`)."""
        return "navigation" if self.mapping.fused else ("odometry" if self.mapping.odometry else None)

    def _nav_topics(self) -> list[str]:
        return [t for t in (self.mapping.dvl, self.mapping.imu, self.mapping.depth) if t is not None]

    def _static_tree(self, reader: AnyReader) -> StaticTree:
        """Return the log's static transforms (empty without a ``/tf_static`` topic)."""
        if not any(t.name == TF_STATIC_TOPIC and t.msgtype == TF_TYPE and t.count for t in self.topics):
            return {}
        messages = self._messages(reader, TF_STATIC_TOPIC)
        return static_tree(self._deserialize(reader, raw, conn) for conn, _r, raw in messages)

    def _frame_of(self, reader: AnyReader, topic: str) -> str:
        """Return the frame a sensor topic's readings are in (an ``Odometry``'s twist: its child frame)."""
        msg = None
        for conn, _r, raw in self._messages(reader, topic):
            msg = self._deserialize(reader, raw, conn)
            break
        if msg is None:
            return ""
        child = getattr(msg, "child_frame_id", None)
        return str(child if child is not None else msg.header.frame_id)

    def _dvl_reports_covariance(self, reader: AnyReader) -> bool:
        """Whether the DVL topic's messages carry a covariance (the lost-bottom rule; read once, cached)."""
        if self._dvl_covariance is None:
            topic = self.mapping.dvl
            assert topic is not None
            diagonals = (
                linear_covariance_diagonal(self._deserialize(reader, raw, conn), conn.msgtype)
                for conn, _r, raw in self._messages(reader, topic)
            )
            self._dvl_covariance = reports_covariance(diagonals)
        return self._dvl_covariance

    def _nav_samples(self, reader: AnyReader, topic: str, covariance: bool) -> Iterator[NavSample]:
        params = self.nav_params
        for conn, receive_ns, raw in self._ordered(reader, topic):
            msg = self._deserialize(reader, raw, conn)
            stamp = _header_stamp(msg, receive_ns)
            if topic == self.mapping.dvl and conn.msgtype in DVL_TYPES:
                yield dvl_sample(msg, conn.msgtype, stamp, covariance_reported=covariance)
            elif topic == self.mapping.imu:
                yield imu_sample(msg, stamp)
            else:
                yield depth_sample(msg, conn.msgtype, stamp, params)

    def _navigation_states(self, stack: ExitStack) -> Iterator[OdometryState]:
        """Open one reader per navigation topic (closed with ``stack``) and yield the fused estimates."""
        assert self.mapping.dvl is not None and self.mapping.imu is not None
        setup = _new_reader(self.path)
        try:
            tree = self._static_tree(setup)
            covariance = self._dvl_reports_covariance(setup)
            report = NavigationReport()
            mounts = {}
            for sensor, topic in (("dvl", self.mapping.dvl), ("imu", self.mapping.imu)):
                mounts[sensor] = sensor_mount(tree, self._frame_of(setup, topic), self.nav_params, sensor)
                report.mounts[sensor] = mounts[sensor].source
        finally:
            setup.close()
        streams = []
        for topic in self._nav_topics():
            topic_reader = _new_reader(self.path)
            stack.callback(topic_reader.close)
            streams.append(self._nav_samples(topic_reader, topic, covariance))
        nav_filter = ComplementaryFilter(self.nav_params, mounts["dvl"], mounts["imu"],
                                         has_depth=self.mapping.depth is not None, report=report)  # fmt: skip
        self.navigation_report = report
        return fuse(merge_samples(*streams), nav_filter)

    def _odometry_check(self) -> OdometryCheck:
        """Return a new check of the odometry, kept as :attr:`odometry_check` (its counts are :attr:`report`)."""
        if self.mapping.fused:
            messages = sum(t.count for t in self.topics if t.name in self._nav_topics())
        else:
            messages = next((t.count for t in self.topics if t.name == self.mapping.odometry), 0)
        self.odometry_check = OdometryCheck(messages=messages, frames=self.count_frames(), source=str(self.path))
        return self.odometry_check

    @property
    def report(self) -> IngestReport:
        """What the last :meth:`frames` (or :meth:`verify`) dropped, by reason (empty before either)."""
        return IngestReport() if self.odometry_check is None else self.odometry_check.report

    def verify(self) -> IngestReport:
        """Read every mapped topic through once, decoding no image; return what the odometry check dropped.

        Raises:
            IngestError: a topic has fewer (or more) readable messages than its index lists, a message does
                not read, or the odometry is unusable (see :mod:`mapserver.ingest.odometry`).
        """
        reader = self._require_open()
        for topic in self.mapping.as_dict().values():
            if topic is not None:
                self._stamp_index(reader, topic)
        check = self._odometry_check()
        if self.mapping.odometry is not None:
            for state in self._odometry_states(reader):
                check.accept(state)
        elif self.mapping.fused:
            with ExitStack() as stack:
                for state in self._navigation_states(stack):
                    check.accept(state)
        return check.report

    def first_image(self) -> Any:
        """Return the first deserialised message of the image topic (None when there is none)."""
        return self.first_message(self.mapping.image)

    def first_message(self, topic: str) -> Any:
        """Return the first deserialised message of ``topic`` in bag order (None when it has none)."""
        reader = self._require_open()
        for conn, _receive_ns, raw in self._messages(reader, topic):
            return self._deserialize(reader, raw, conn)
        return None

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[Frame]:
        """Yield camera frames in stamp order with the motion since the previous frame.

        Args:
            start: index of the first frame to yield. Earlier frames are read (not decoded) so that the
                motion of frame ``start`` is still relative to frame ``start - 1``: reading ``[0, k)`` then
                ``[k, n)`` gives the same frames as ``[0, n)``.
            stop: index after the last frame to yield (None: to the end).

        Yields:
            :class:`~mapserver.ingest.frames.Frame` objects; ``motion`` is ``Motion(0, 0, 0, 0, 0)`` for
            frame 0 and None for every frame when the log has no odometry topic.

        Raises:
            IngestError: corrupt data or an undecodable image.

        """
        self._require_open()
        mode = self.odometry_mode
        fused = mode is None and self.mapping.fused
        topic = self.mapping.image
        with ExitStack() as stack:
            reader = _new_reader(self.path)
            stack.callback(reader.close)
            track: OdometryTrack | None = None
            states: Iterator[OdometryState] = iter(())
            if mode is not None:
                odom_reader = _new_reader(self.path)
                stack.callback(odom_reader.close)
                states = self._odometry_states(odom_reader)
                track = OdometryTrack(mode, self._odometry_check())
            elif fused:
                states = self._navigation_states(stack)
                track = OdometryTrack("pose", self._odometry_check())
            sonar = None
            if self.mapping.sonar is not None:
                sonar_reader = _new_reader(self.path)
                stack.callback(sonar_reader.close)
                sonar = _Newest(self, sonar_reader, self.mapping.sonar)
            cursor: int | None = None
            for index, (conn, receive_ns, raw) in enumerate(self._ordered(reader, topic)):
                if stop is not None and index >= stop:
                    return
                msg = self._deserialize(reader, raw, conn)
                stamp = _header_stamp(msg, receive_ns)
                motion: Motion | None = None
                if track is not None:
                    while not track.covers(stamp):
                        state = next(states, None)
                        if state is None:
                            break
                        track.push(state)
                    if cursor is None:
                        motion = ZERO_MOTION
                        track.trim(stamp)
                    else:
                        motion = track.motion(cursor, stamp)
                cursor = stamp if cursor is None else max(cursor, stamp)
                if index >= start:
                    extra = None if sonar is None else sonar.at(stamp)
                    yield Frame(stamp_ns=stamp, image=decode_image(msg, topic), motion=motion, sonar=extra)

    def frames_ahead(
        self, start: int = 0, stop: int | None = None, *, depth: int = READ_AHEAD, worker: Worker = "auto"
    ) -> ReadAhead:
        """Return :meth:`frames` read and decoded ahead by a worker (:class:`ReadAhead`; use it in a ``with`` block)."""
        return ReadAhead(self, start, stop, depth=depth, worker=worker)

    def ground_truth(self) -> Iterator[PoseSample]:
        """Yield the ground-truth poses in stamp order (nothing when the log has no ground-truth topic).

        ``Odometry`` and ``PoseWithCovarianceStamped`` give ``msg.pose.pose``, ``PoseStamped`` ``msg.pose``;
        stamps are header stamps (receive time when zero).
        """
        self._require_open()
        topic = self.mapping.ground_truth
        if topic is None:
            return
        reader = _new_reader(self.path)
        try:
            yield from self._ground_truth(reader, topic)
        finally:
            reader.close()

    def _ground_truth(self, reader: AnyReader, topic: str) -> Iterator[PoseSample]:
        for conn, receive_ns, raw in self._ordered(reader, topic):
            msg = self._deserialize(reader, raw, conn)
            pose = msg.pose if conn.msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
            yield PoseSample(
                stamp_ns=_header_stamp(msg, receive_ns),
                x=float(pose.position.x),
                y=float(pose.position.y),
                z=float(pose.position.z),
                qx=float(pose.orientation.x),
                qy=float(pose.orientation.y),
                qz=float(pose.orientation.z),
                qw=float(pose.orientation.w),
            )


# -- reading ahead -------------------------------------------------------------------------------------



class ReadAhead:
    """A log's frames ``[start, stop)``, read and decoded ahead of the caller by a worker, in stamp order.

    :attr:`report` is what the worker's reading dropped (:class:`~mapserver.ingest.frames.IngestReport`), once
    every frame has been read (None before).

    The worker opens its own readers on the log and runs :meth:`MissionLog.frames`, sending the frames in
    batches over a bounded channel (about ``depth`` frames in flight); iterating yields the same frames in the
    same order. An exception in the worker (an :class:`IngestError` for a corrupt message or an undecodable
    image) is raised when the caller reaches that point of the stream, as :meth:`MissionLog.frames` raises it
    there. Leaving the ``with`` block (the end of the frames, a ``break``, an exception, KeyboardInterrupt)
    stops the worker and waits for it.

    ``worker``: ``process`` reads in a forked child (it starts with the caller's modules loaded and runs in
    parallel with the caller's computation) that writes to a pipe the caller alone reads: when either side
    ends, the other sees the pipe close (a child that dies is an IngestError, never a hang; a caller that stops
    reading ends the child). The child ignores SIGINT: the caller's interrupt stops it. ``thread`` reads in a
    thread into a queue (decoding releases the GIL, parsing does not). ``auto`` takes ``process`` where fork
    exists, the caller runs no other thread and is not a daemonic process (a celery worker's, which may not
    have children), and the range has at least ``depth`` frames (a short log is read in a thread: no fork to
    pay).
    """

    def __init__(
        self, log: MissionLog, start: int = 0, stop: int | None = None, *, depth: int = READ_AHEAD,
        worker: Worker = "auto",
    ) -> None:  # fmt: skip
        log._require_open()
        self.path = log.path
        end = log.count_frames() if stop is None else min(stop, log.count_frames())
        self.worker = _worker_kind(worker, end - start >= depth)
        batch = max(1, min(_BATCH, depth // 2))
        job = (log.path, log.topics, log.mapping, log._odometry_mode, start, stop, batch, log.nav_params)
        self._stop = threading.Event()
        self.report: IngestReport | None = None
        if self.worker == "process":
            context = multiprocessing.get_context("fork")
            self._receive, send = context.Pipe(duplex=False)
            _widen_pipe(send)
            self._runner: Any = context.Process(target=_produce_in_child, args=(job, send, self._receive), daemon=True)
            self._runner.start()
            send.close()  # the child holds the only writing end: its exit closes the pipe
        else:
            self._queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=max(1, depth // batch))
            sender = _QueueSender(self._queue, self._stop)
            self._runner = threading.Thread(target=_produce, args=(job, sender.send), daemon=True)
            self._runner.start()

    def __enter__(self) -> ReadAhead:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __iter__(self) -> Iterator[Frame]:
        while True:
            kind, payload = self._take()
            if kind == "frames":
                yield from payload
            elif kind == "end":
                self.report = payload
                return
            else:
                raise payload

    def _take(self) -> tuple[str, Any]:
        """Return the worker's next message; raise IngestError when it ended without one."""
        if self.worker == "process":
            try:
                return self._receive.recv()
            except EOFError:
                self._runner.join(timeout=1.0)
        else:
            while self._runner.is_alive() or not self._queue.empty():
                with contextlib.suppress(queue.Empty):
                    return self._queue.get(timeout=_POLL_S)
        code = getattr(self._runner, "exitcode", None)
        msg = f"the frame reader of {str(self.path)!r} stopped without an answer (exit code {code})"
        raise IngestError(msg)

    def close(self) -> None:
        """Stop the worker and wait for it (idempotent)."""
        self._stop.set()
        if self.worker == "process":
            self._receive.close()  # a child blocked writing gets a broken pipe and ends
            self._runner.join(timeout=5.0)
            if self._runner.is_alive():
                self._runner.terminate()
                self._runner.join()
        else:
            while self._runner.is_alive():  # it ends at its next send, or when its current frame is read
                with contextlib.suppress(queue.Empty):
                    self._queue.get_nowait()
                self._runner.join(timeout=_POLL_S)


class _QueueSender:
    """The thread worker's side of its queue: a blocking put that gives up once the caller stopped."""

    def __init__(self, channel: queue.Queue[tuple[str, Any]], stop: threading.Event) -> None:
        self.channel, self.stop = channel, stop

    def send(self, item: tuple[str, Any]) -> bool:
        """Put ``item``; return False (not sent) once the caller stopped the worker."""
        while not self.stop.is_set():
            with contextlib.suppress(queue.Full):
                self.channel.put(item, timeout=_POLL_S)
                return True
        return False


def _worker_kind(worker: Worker, long_range: bool = True) -> Literal["process", "thread"]:
    """Return the worker ``auto`` stands for: a forked process where that is safe and pays, else a thread.

    Fork copies the calling thread alone, so a process is forked only from a single-threaded caller (the
    CLI; not a server's worker threads, whose locks the child would inherit held), never from a daemonic
    process (a celery worker's may not have children), and only for a range long enough to repay the fork.
    """
    if worker != "auto":
        return worker
    can_fork = "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1
    return "process" if long_range and can_fork and not multiprocessing.current_process().daemon else "thread"


def _widen_pipe(connection: Any) -> None:
    """Let the pipe hold ~1 MiB (Linux; elsewhere its default) so the child can run further ahead."""
    with contextlib.suppress(ImportError, AttributeError, OSError):
        import fcntl

        fcntl.fcntl(connection.fileno(), fcntl.F_SETPIPE_SZ, 1 << 20)


def _produce_in_child(job: tuple[Any, ...], send: Any, receive: Any) -> None:
    """The forked child's body: :func:`_produce` into the pipe, SIGINT ignored, its copy of the reading end closed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller handles Ctrl-C and stops it
    receive.close()  # so that the caller's close is the pipe's last reader: a write then fails

    def deliver(item: tuple[str, Any]) -> bool:
        if item[0] == "error":
            item = ("error", _portable(item[1], job[0]))
        try:
            send.send(item)
        except OSError:  # the caller closed its end (stopped, or gone)
            return False
        return True

    _produce(job, deliver)


def _produce(job: tuple[Any, ...], deliver: Callable[[tuple[str, Any]], bool]) -> None:
    """Worker body: deliver the frames of ``job`` in batches, then ``("end", None)``, or ``("error", exception)``.

    The frames read before an error are delivered before it, so the caller sees the stream up to the failure.
    ``deliver`` returns False once the caller stopped the worker.
    """
    path, topics, mapping, mode, start, stop_at, batch, nav_params = job
    chunk: list[Frame] = []
    try:
        log = MissionLog(path, _new_reader(path), topics, mapping, mode, nav_params)
        try:
            size = 1
            for frame in log.frames(start, stop_at):
                chunk.append(frame)
                if len(chunk) >= size:
                    if not deliver(("frames", chunk)):
                        return
                    chunk, size = [], batch
            report = log.report
        finally:
            log.close()
        if deliver(("frames", chunk)):
            deliver(("end", report))
    except BaseException as err:  # every failure goes to the caller, which raises it
        if deliver(("frames", chunk)):
            deliver(("error", err))


def _portable(err: BaseException, path: Path) -> BaseException:
    """Return ``err`` when it survives pickling (to reach the parent), else an IngestError that names it."""
    try:
        pickle.loads(pickle.dumps(err))
    except Exception:  # any unpicklable exception is replaced
        return IngestError(f"reading {str(path)!r} failed: {type(err).__name__}: {_describe(err)}")
    return err


def _topic_infos(reader: AnyReader) -> list[TopicInfo]:
    duration_s = reader.duration * 1e-9 if reader.message_count else 0.0
    infos = []
    for name, info in sorted(reader.topics.items()):
        count = int(info.msgcount)
        rate = (count - 1) / duration_s if duration_s > 0 and count > 1 else 0.0
        infos.append(TopicInfo(name=name, msgtype=str(info.msgtype or ""), count=count, rate_hz=rate))
    return infos


def open_log(
    path: str | Path,
    topics: Mapping[str, str] | None = None,
    *,
    odometry_mode: Literal["auto", "twist", "pose"] = "auto",
    navigation: NavParams | None = None,
) -> MissionLog:
    """Open a mission log and choose its topics.

    Args:
        path: a ROS 1 ``.bag``, a ROS 2 bag directory (with ``metadata.yaml``), or a standalone ``.db3`` or
            ``.mcap`` file.
        topics: topic overrides, keys ``image``, ``odometry``, ``ground_truth`` (``none`` switches one off).
        odometry_mode: ``auto`` (detect, see the module docstring), or force ``twist`` or ``pose``.
        navigation: the DVL/IMU/depth constants and mountings (:class:`~mapserver.ingest.navigation.NavParams`;
            None: the defaults), used when the motion is the navigation fusion.

    Returns:
        The open log (close it, or use it as a context manager).

    Raises:
        IngestError: missing path, not a bag, truncated or corrupt, no usable camera topic, bad override,
            unsupported image encoding (checked on the first image).
        LimitError: the first image has more pixels than the limit (:mod:`mapserver.ingest.decode`).

    """
    log_path = Path(path)
    _check_path(log_path)
    reader = _new_reader(log_path)
    try:
        infos = _topic_infos(reader)
        mapping = map_topics(infos, topics, source=str(log_path))
        mode: OdometryMode | None = None if odometry_mode == "auto" else odometry_mode
        log = MissionLog(log_path, reader, infos, mapping, mode, navigation)
        first = log.first_image()
        if first is None:
            msg = f"{log_path}: camera topic {mapping.image!r} has no readable messages"
            raise IngestError(msg)
        try:
            decode_image(first, mapping.image)
        except LimitError as err:
            msg = f"{err} in {str(log_path)!r}"
            raise LimitError(msg, limit=err.limit) from err
        except IngestError as err:
            msg = f"{err} in {str(log_path)!r}"
            raise IngestError(msg) from err
    except (InputError, ConfigError):  # IngestError, a bad override, a first frame over the pixel limit, a bad limit
        reader.close()
        raise
    except Exception as err:
        reader.close()
        msg = f"not a readable bag (truncated or corrupt?): {str(log_path)!r}: {_describe(err)}"
        raise IngestError(msg) from err
    return log
