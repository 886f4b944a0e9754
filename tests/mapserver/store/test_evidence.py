"""Evidence selection (closest frame within sync_stale_sec) and JPEG encoding."""

from __future__ import annotations

import numpy as np
import pytest

from mapserver.store.evidence import EvidenceCollector, decode_jpeg, encode_jpeg


def _frame(value: int) -> np.ndarray:
    return np.full((8, 10), value, dtype=np.uint8)


def _run(frames: list[float], experiences: dict[float, int], tolerance: float) -> EvidenceCollector:
    """Feed frames (value = index × 20) and register each experience right after the frame at its stamp."""
    collector = EvidenceCollector(tolerance)
    for k, stamp in enumerate(frames):
        collector.observe(stamp, _frame(20 * k))
        for exp_stamp, exp_id in experiences.items():
            if frames[k] <= exp_stamp < (frames[k + 1] if k + 1 < len(frames) else np.inf):
                collector.experience(exp_id, exp_stamp)
    return collector


def test_the_closest_frame_within_the_tolerance_is_chosen() -> None:
    frames = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    # 0.7 → 0.5 (|0.2| beats |0.3|, a past frame); 2.26 → 2.5 (|0.24| beats |0.26|, a future frame);
    # 1.25 → 1.0 and 1.5 tie at 0.25: the earlier frame wins; 4.0 → nothing within 0.3
    collector = _run(frames, {0.7: 0, 2.26: 1, 1.25: 2, 4.0: 3}, tolerance=0.3)
    images = {img.experience: img for img in collector.finish()}
    assert sorted(images) == [0, 1, 2]
    assert collector.unmatched == [3]
    assert images[0].frame_stamp == 0.5 and images[0].offset_s == pytest.approx(-0.2)
    assert images[1].frame_stamp == 2.5 and images[1].offset_s == pytest.approx(0.24)
    assert images[2].frame_stamp == 1.0
    for exp, frame_index in ((0, 1), (1, 5), (2, 2)):
        assert abs(int(decode_jpeg(images[exp].jpeg).mean()) - 20 * frame_index) <= 1


def test_a_frame_outside_the_tolerance_is_never_used() -> None:
    collector = _run([0.0, 1.0], {0.5: 0}, tolerance=0.4)
    assert collector.finish() == []
    assert collector.unmatched == [0]


def test_large_frames_are_downscaled_and_colours_kept() -> None:
    image = np.zeros((480, 640, 3), dtype=np.uint8)
    image[..., 0] = 200  # red (RGB)
    jpeg, width, height = encode_jpeg(image)
    assert (width, height) == (320, 240)
    decoded = decode_jpeg(jpeg)
    assert decoded.shape == (240, 320, 3)
    red, green, blue = (float(decoded[..., c].mean()) for c in range(3))
    assert red > 180 and green < 20 and blue < 20
    small, w, h = encode_jpeg(np.full((20, 30), 77, dtype=np.uint8))
    assert (w, h) == (30, 20) and decode_jpeg(small).shape == (20, 30)
    assert len(jpeg) < 20_000
