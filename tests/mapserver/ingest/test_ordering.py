"""Stamp-order re-sequencing with bounded memory (mapserver.ingest.ordering)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapserver.ingest.ordering import raw_header_stamp, reorder_window, stamp_ordered
from tests.mapserver.ingest.conftest import ROS1, ROS2, image_msg, odometry_msg

STAMP = 1_700_000_123_456_789_012


@pytest.mark.parametrize("build", [image_msg, odometry_msg])
def test_raw_stamp_matches_deserialised_header(build: object) -> None:
    for store, ros2 in ((ROS1, False), (ROS2, True)):
        msg = build(store, STAMP)  # type: ignore[operator]
        raw = store.serialize_cdr(msg, msg.__msgtype__) if ros2 else store.serialize_ros1(msg, msg.__msgtype__)
        assert raw_header_stamp(raw, ros2) == STAMP


def test_raw_stamp_big_endian_cdr_short_and_unknown_encapsulation() -> None:
    big = b"\x00\x00\x00\x00" + struct.pack(">iI", 12, 34) + b"rest"
    assert raw_header_stamp(big, True) == 12 * 1_000_000_000 + 34
    assert raw_header_stamp(b"\x00\x01\x00\x00\x01", True) is None
    assert raw_header_stamp(b"\x00\x07\x00\x00" + bytes(8), True) is None  # not plain CDR


def test_reorder_window_hand_computed() -> None:
    assert reorder_window([]) == 0
    assert reorder_window([1, 2, 2, 5]) == 0
    # receive stamps 0, 2, 1, 3: stamp 2 must wait for stamp 1 (one held)
    assert reorder_window([0, 2, 1, 3]) == 1
    # fully reversed: everything is held until the last message arrives
    assert reorder_window([4, 3, 2, 1, 0]) == 4
    # 1 and 2 swapped with 5 in between: 5 waits, then 2 waits for 1
    assert reorder_window([0, 2, 5, 1, 6]) == 2


def _passes(items: list[int]) -> tuple[list[int], object]:
    calls: list[int] = []

    def read_pass() -> list[int]:
        calls.append(1)
        return list(items)

    return calls, read_pass


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(0, 6), min_size=0, max_size=40), st.integers(1, 8))
def test_stamp_ordered_is_the_stable_sort_with_bounded_holding(stamps: list[int], limit: int) -> None:
    items = list(range(len(stamps)))  # item = receive index
    calls, read_pass = _passes(items)
    out = list(stamp_ordered(stamps, read_pass, limit))  # type: ignore[arg-type]
    assert out == sorted(items, key=lambda i: (stamps[i], i))
    window = reorder_window(stamps)
    expected_passes = 0 if not stamps else (1 if window <= limit else math.ceil(len(stamps) / limit))
    assert len(calls) == expected_passes


def test_stamp_ordered_reports_a_stream_that_changed() -> None:
    with pytest.raises(ValueError, match="expected 3"):
        list(stamp_ordered([2, 1, 0], lambda: [0, 1], 8))
    with pytest.raises(ValueError, match="expected 2"):
        list(stamp_ordered(np.array([0, 1]), lambda: [0, 1, 2], 8))
