"""Evidence: for each experience, the camera frame closest to its stamp, as a small JPEG.

A frame counts when it lies within ``sync_stale_sec`` (PoseidonSLAM's sensor-sync tolerance, a
``Params`` key) of the experience's stamp; the closest one wins (the earlier one on a tie). Frames
wider or taller than :data:`MAX_SIDE` pixels are downscaled (area interpolation) before encoding.
:class:`EvidenceCollector` follows a frame stream with bounded memory: it keeps only the frames
within the tolerance of the newest one and encodes each experience's frame once, when no later frame
can be closer. Rows are keyed by the experience's stable identity (session, index), so they survive
the renumbering of a merge.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from sqlalchemy import Connection, and_, select, tuple_

from mapserver.errors import NotFoundError, StoreError
from mapserver.store.bulk import bulk_insert
from mapserver.store.models import Evidence, Experience

MAX_SIDE = 320
"""Largest width or height (pixels) of a stored evidence image."""

JPEG_QUALITY = 85
MEDIA_TYPE = "image/jpeg"


@dataclass(frozen=True, slots=True)
class EvidenceImage:
    """An encoded evidence frame for one experience (map-local id at capture time)."""

    experience: int
    experience_stamp: float
    frame_stamp: float
    width: int
    height: int
    jpeg: bytes

    @property
    def offset_s(self) -> float:
        """Return frame stamp − experience stamp (seconds)."""
        return self.frame_stamp - self.experience_stamp


def encode_jpeg(image: np.ndarray, *, max_side: int = MAX_SIDE, quality: int = JPEG_QUALITY) -> tuple[bytes, int, int]:
    """Encode a uint8 grey (H, W) or RGB (H, W, 3) image as JPEG, downscaled to at most ``max_side`` pixels.

    Returns:
        ``(jpeg bytes, width, height)`` of the stored image.

    Raises:
        StoreError: the image has an unsupported shape or the encoder fails.
    """
    pixels = np.asarray(image)
    if pixels.dtype != np.uint8:
        pixels = np.clip(pixels, 0, 255).astype(np.uint8)
    if pixels.ndim == 3 and pixels.shape[2] == 3:
        pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
    elif pixels.ndim != 2:
        msg = f"evidence image must be (H, W) or (H, W, 3), got {pixels.shape!r}"
        raise StoreError(msg)
    h, w = pixels.shape[:2]
    scale = max_side / max(h, w)
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        pixels = cv2.resize(pixels, size, interpolation=cv2.INTER_AREA)
        h, w = pixels.shape[:2]
    ok, buffer = cv2.imencode(".jpg", np.ascontiguousarray(pixels), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        msg = "the JPEG encoder failed on an evidence image"
        raise StoreError(msg)
    return buffer.tobytes(), int(w), int(h)


def decode_jpeg(data: bytes) -> np.ndarray:
    """Decode stored evidence back to uint8 pixels (grey (H, W) or RGB (H, W, 3))."""
    pixels = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        msg = "stored evidence is not a readable JPEG"
        raise StoreError(msg)
    return cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB) if pixels.ndim == 3 else pixels


class EvidenceCollector:
    """Pick, for each experience, the frame closest to its stamp within ``tolerance_s``.

    Feed frames in stream order with :meth:`observe` and new experiences with :meth:`experience`
    (right after the frame that created them); :meth:`finish` returns the encoded images.

    Args:
        tolerance_s: largest |frame stamp − experience stamp| accepted (``sync_stale_sec``).
        max_side: downscale limit (pixels).
    """

    def __init__(self, tolerance_s: float, *, max_side: int = MAX_SIDE) -> None:
        self.tolerance_s = float(tolerance_s)
        self.max_side = max_side
        self._frames: deque[tuple[float, np.ndarray]] = deque()
        self._pending: dict[int, tuple[float, float, float, np.ndarray | None]] = {}
        self._done: list[EvidenceImage] = []
        self.unmatched: list[int] = []

    def observe(self, stamp_s: float, image: np.ndarray) -> None:
        """Take one camera frame (stamp in seconds)."""
        for exp_id, (exp_stamp, best_offset, _stamp, _image) in list(self._pending.items()):
            offset = abs(stamp_s - exp_stamp)
            if offset <= self.tolerance_s and offset < best_offset:
                self._pending[exp_id] = (exp_stamp, offset, stamp_s, image)
            elif stamp_s - exp_stamp > self.tolerance_s:
                self._finalise(exp_id)
        self._frames.append((stamp_s, image))
        while self._frames and stamp_s - self._frames[0][0] > self.tolerance_s:
            self._frames.popleft()

    def experience(self, experience_id: int, stamp_s: float) -> None:
        """Register a new experience (its stamp in seconds) against the frames seen so far."""
        best: tuple[float, float, np.ndarray | None] = (np.inf, np.nan, None)
        for frame_stamp, image in self._frames:
            offset = abs(frame_stamp - stamp_s)
            if offset <= self.tolerance_s and offset < best[0]:
                best = (offset, frame_stamp, image)
        self._pending[experience_id] = (stamp_s, best[0], best[1], best[2])

    def replace_from(self, first_id: int, items: Sequence[tuple[int, float, np.ndarray]]) -> None:
        """Forget experiences ``first_id`` and later, then take ``items`` (id, stamp, its own frame) instead.

        A merge rolled back by its verification: the experiences the merged engine made are gone, and
        those the session's own engine made meanwhile come with the frames that created them.
        """
        self._pending = {k: v for k, v in self._pending.items() if k < first_id}
        self._done = [img for img in self._done if img.experience < first_id]
        self.unmatched = [k for k in self.unmatched if k < first_id]
        for experience_id, stamp_s, image in items:
            self._pending[experience_id] = (stamp_s, 0.0, stamp_s, image)

    def _finalise(self, experience_id: int) -> None:
        exp_stamp, _offset, frame_stamp, image = self._pending.pop(experience_id)
        if image is None:
            self.unmatched.append(experience_id)
            return
        jpeg, width, height = encode_jpeg(image, max_side=self.max_side)
        self._done.append(EvidenceImage(experience_id, exp_stamp, frame_stamp, width, height, jpeg))

    def finish(self) -> list[EvidenceImage]:
        """Settle every pending experience with the frames seen; return all images by experience id."""
        for exp_id in sorted(self._pending):
            self._finalise(exp_id)
        return sorted(self._done, key=lambda item: item.experience)


def save_evidence(*, conn: Connection, session_id: int, items: Sequence[tuple[int, EvidenceImage]]) -> int:
    """Store evidence rows ``(origin_index, image)`` of one session (replacing rows with the same key).

    Returns:
        The number of rows written.
    """
    if not items:
        return 0
    keys = [(session_id, int(index)) for index, _ in items]
    for start in range(0, len(keys), 500):
        chunk = keys[start : start + 500]
        conn.execute(
            Evidence.__table__.delete().where(tuple_(Evidence.session_id, Evidence.origin_index).in_(chunk))
        )
    rows = [
        (session_id, int(index), img.frame_stamp, img.offset_s, img.width, img.height, MEDIA_TYPE, img.jpeg)
        for index, img in items
    ]
    columns = ("session_id", "origin_index", "frame_stamp", "offset_s", "width", "height", "media_type", "data")
    bulk_insert(conn, Evidence.__table__, columns, rows)
    return len(rows)


@dataclass(frozen=True, slots=True)
class StoredEvidence:
    """One stored evidence image."""

    session_id: int
    origin_index: int
    frame_stamp: float
    offset_s: float
    width: int
    height: int
    media_type: str
    data: bytes


def get_evidence(*, conn: Connection, map_id: int, experience: int) -> StoredEvidence:
    """Return the evidence image of experience ``experience`` (map-local id) of a map.

    Raises:
        NotFoundError: no such experience, or it has no evidence (e.g. an imported map).
    """
    row = conn.execute(
        select(
            Evidence.session_id, Evidence.origin_index, Evidence.frame_stamp, Evidence.offset_s, Evidence.width,
            Evidence.height, Evidence.media_type, Evidence.data,
        ).join(
            Experience,
            and_(Experience.session_id == Evidence.session_id, Experience.origin_index == Evidence.origin_index),
        ).where(Experience.map_id == map_id, Experience.local_id == experience)
    ).first()  # fmt: skip
    if row is None:
        msg = f"experience {experience!r} of this map has no evidence image"
        raise NotFoundError(msg)
    return StoredEvidence(int(row[0]), int(row[1]), row[2], row[3], int(row[4]), int(row[5]), str(row[6]), row[7])
