"""Stamp order with bounded memory: re-sequencing a topic's messages from receive order to header-stamp order.

A bag stores messages in receive (record) order, which depends on how the log was recorded or played back
(network delays, several publishers, a replay at another rate). Processing must not: every stream is read
in **header-stamp order**, ties kept in receive order (a stable sort).

How, with memory bounded regardless of the log's size: a first pass reads only the header stamps of the
topic (8 bytes per message, parsed from the serialised bytes, see :func:`raw_header_stamp`). From them
:func:`reorder_window` computes how many messages must be held back at most to emit them in stamp order in a
single receive-order pass. When that window is at most ``limit`` messages (normal logs: a few messages of
jitter), one pass with a buffer of that many messages re-sequences the stream; otherwise the stream is
read in ``ceil(n/limit)`` passes, each emitting the next ``limit`` messages in stamp order. Either way no
more than ``limit`` messages are held at once.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

import numpy as np
import numpy.typing as npt

T = TypeVar("T")

REORDER_LIMIT = 256
"""Most messages held back at once while re-sequencing a stream."""

_CDR_LE = b"\x00\x01"
_CDR_BE = b"\x00\x00"


def raw_header_stamp(raw: bytes | memoryview, ros2: bool) -> int | None:
    """Read the ``std_msgs/Header`` stamp at the start of a serialised message, in nanoseconds.

    Every message type the reader streams (``Image``, ``CompressedImage``, ``Odometry``, ``PoseStamped``,
    ``PoseWithCovarianceStamped``) starts with a header. ROS 1: ``uint32 seq, uint32 sec, uint32 nsec``
    little-endian; ROS 2 CDR: a 4-byte encapsulation header (``00 01`` little-endian, ``00 00`` big-endian),
    then ``int32 sec, uint32 nanosec``.

    Args:
        raw: the serialised message.
        ros2: CDR (ROS 2) rather than ROS 1 serialisation.

    Returns:
        The stamp, or None when the bytes are too short or the CDR encapsulation is not plain CDR.

    """
    data = bytes(raw[:12])
    if len(data) < 12:
        return None
    if ros2:
        kind = data[:2]
        if kind == _CDR_LE:
            sec, nsec = struct.unpack_from("<iI", data, 4)
        elif kind == _CDR_BE:
            sec, nsec = struct.unpack_from(">iI", data, 4)
        else:
            return None
    else:
        sec, nsec = struct.unpack_from("<II", data, 4)
    return int(sec) * 1_000_000_000 + int(nsec)


def reorder_window(stamps: npt.ArrayLike) -> int:
    """Return the most messages a single receive-order pass must hold back to emit them in stamp order.

    With ``order`` the stable argsort of the stamps, the message of stamp rank ``k`` can be emitted once the
    messages of ranks ``0..k`` have all arrived, i.e. after receive index ``T_k = max(order[0..k])``. After
    receiving ``i + 1`` messages, ``#{k : T_k ≤ i}`` have been emitted and the rest are held.

    Args:
        stamps: (n,) stamps in receive order.

    Returns:
        The largest number held at once (0 when the stamps are already in order).

    """
    s = np.asarray(stamps, dtype=np.int64).reshape(-1)
    n = s.shape[0]
    if n == 0:
        return 0
    release = np.maximum.accumulate(np.argsort(s, kind="stable"))
    received = np.arange(1, n + 1)
    emitted = np.searchsorted(release, np.arange(n), side="right")
    return int(np.max(received - emitted))


def stamp_ordered(
    stamps: npt.ArrayLike, read_pass: Callable[[], Iterable[T]], limit: int = REORDER_LIMIT
) -> Iterator[T]:
    """Yield a stream's items in stamp order (stable), holding at most ``limit`` items at once.

    Args:
        stamps: (n,) stamps of the items in receive order (from a first pass).
        read_pass: returns a fresh iterator over the n items in receive order (called once, or once per
            chunk of ``limit`` items when the stream is too far out of order for one pass).
        limit: most items held at once (≥ 1).

    Yields:
        The items, sorted by stamp; equal stamps keep their receive order.

    Raises:
        ValueError: a pass yields another number of items than ``stamps`` holds.

    """
    s = np.asarray(stamps, dtype=np.int64).reshape(-1)
    n = s.shape[0]
    if n == 0:
        return
    order = np.argsort(s, kind="stable")
    if bool(np.all(order == np.arange(n))):
        yield from _checked(read_pass(), n)
        return
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    ranks = rank.tolist()
    if reorder_window(s) <= limit:
        held: dict[int, T] = {}
        following = 0
        for index, item in enumerate(_checked(read_pass(), n)):
            held[ranks[index]] = item
            while following in held:
                yield held.pop(following)
                following += 1
        return
    for first in range(0, n, limit):
        chunk: dict[int, T] = {}
        for index, item in enumerate(_checked(read_pass(), n)):
            if first <= ranks[index] < first + limit:
                chunk[ranks[index]] = item
        for k in range(first, min(first + limit, n)):
            yield chunk.pop(k)


def _checked(items: Iterable[T], n: int) -> Iterator[T]:
    count = 0
    for item in items:
        count += 1
        if count > n:
            break
        yield item
    if count != n:
        msg = f"stream changed between passes: expected {n} messages, read {count}"
        raise ValueError(msg)
