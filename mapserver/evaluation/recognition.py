"""Place recognition: from a map's per-frame template record, how often a revisit recognised the place.

The share of revisiting frames that recognised the place from an earlier visit, and the share of false
matches (:func:`place_recognition`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from mapserver.evaluation.ape import interpolate_poses
from mapserver.formats import Trajectory

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RecognitionSettings:
    """Radii and gap of the place-recognition rates (defaults suit metre-scale ground robots).

    Attributes:
        revisit_radius: R: a frame revisits a place when it is within R metres of an earlier frame.
        revisit_gap_s: T: that earlier frame must be more than T seconds earlier.
        match_radius: R′: a revisit frame is recognised when its template was created within R′ metres.
        false_radius: a matched frame is a false match when its template was created more than this far.

    """

    revisit_radius: float = 1.0
    revisit_gap_s: float = 20.0
    match_radius: float = 3.0
    false_radius: float = 5.0


@dataclass(frozen=True)
class _FrameTable:
    """The map's per-frame record with each frame's ground-truth position (NaN where it has none)."""

    stamps: FloatArray
    templates: IntArray
    created: npt.NDArray[np.bool_]
    positions: FloatArray
    known: npt.NDArray[np.bool_]

    @classmethod
    def of(cls, rows: npt.ArrayLike, ground_truth: Trajectory, max_diff_s: float) -> _FrameTable:
        """Return the table of ``[stamp, template, created]`` rows with positions read from ``ground_truth``."""
        table = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
        stamps = table[:, 0]
        positions = interpolate_poses(ground_truth, stamps, max_diff_s=max_diff_s)
        return cls(stamps, table[:, 1].astype(np.int64), table[:, 2] != 0, positions, ~np.isnan(positions[:, 0]))


def _revisit_frames(frames: _FrameTable, idx: IntArray, s: RecognitionSettings) -> npt.NDArray[np.bool_]:
    """Return which frames revisit a place: within R of a frame (of ``idx``) more than T earlier."""
    revisit = np.zeros(frames.stamps.shape[0], dtype=bool)
    if idx.size:
        stamps, positions = frames.stamps, frames.positions
        tree = cKDTree(positions[idx])
        for k, neighbours in enumerate(tree.query_ball_point(positions[idx], r=s.revisit_radius)):
            i = idx[k]
            if neighbours and float(np.min(stamps[idx[neighbours]])) < stamps[i] - s.revisit_gap_s:
                revisit[i] = True
    return revisit


def _count_matches(
    frames: _FrameTable, idx: IntArray, revisit: npt.NDArray[np.bool_], s: RecognitionSettings
) -> tuple[int, int, int]:
    """Return (recognised revisits, matched frames, false matches) among the frames of ``idx``."""
    stamps, templates, created, positions = frames.stamps, frames.templates, frames.created, frames.positions
    # creating frame of every template (first created row)
    creator: dict[int, int] = {}
    for index in np.flatnonzero(created).tolist():
        creator.setdefault(int(templates[index]), index)
    recognised = 0
    matched = 0
    false = 0
    for i in idx.tolist():
        if created[i]:
            continue
        c = creator.get(int(templates[i]))
        if c is None or not frames.known[c]:
            continue
        matched += 1
        distance = float(np.linalg.norm(positions[c] - positions[i]))
        if distance > s.false_radius:
            false += 1
        if revisit[i] and stamps[c] < stamps[i] - s.revisit_gap_s and distance <= s.match_radius:
            recognised += 1
    return recognised, matched, false


def place_recognition(
    rows: npt.ArrayLike,
    ground_truth: Trajectory,
    settings: RecognitionSettings | None = None,
    *,
    max_diff_s: float = 0.05,
) -> dict[str, Any]:
    """Place-recognition rates of a processed log from its per-frame template record (map JSON ``frames``).

    Every frame gets its ground-truth position p (interpolated at its stamp t; frames outside the ground
    truth's span are left out), and every template the frame c that created it. With the settings' R, T,
    R′ and the false-match radius F:

    * **revisit frames**: frames i with an earlier frame j, ``t_j < t_i − T``, at ``‖p_j − p_i‖ ≤ R``;
    * **revisit_match_rate**: the fraction of revisit frames that matched (did not create) a template whose
      creating frame c is earlier than ``t_i − T`` and within ``‖p_c − p_i‖ ≤ R′``: the place was
      recognised from an earlier visit (for ``loop``: second-lap frames matched to first-lap templates);
    * **false_match_rate**: among all frames that matched an existing template, the fraction whose
      template was created more than F metres away.

    Args:
        rows: (N, 3) ``[stamp, template, created]`` per frame, in processing order.
        ground_truth: reference trajectory (3-D positions; planar ground truth has z = 0 or constant).
        settings: R, T, R′, F (defaults: 1 m, 20 s, 3 m, 5 m).
        max_diff_s: tolerance for stamps just outside the ground truth's span.

    Returns:
        ``{"revisit_frames", "revisit_matched", "revisit_match_rate" (None without revisits),
        "matched_frames", "false_matches", "false_match_rate" (None without matches), "frames_evaluated",
        "settings": {...}}``.

    """
    s = settings or RecognitionSettings()
    frames = _FrameTable.of(rows, ground_truth, max_diff_s)
    idx = np.flatnonzero(frames.known)
    revisit = _revisit_frames(frames, idx, s)
    recognised, matched, false = _count_matches(frames, idx, revisit, s)
    n_revisit = int(revisit.sum())
    return {
        "revisit_frames": n_revisit,
        "revisit_matched": recognised,
        "revisit_match_rate": recognised / n_revisit if n_revisit else None,
        "matched_frames": matched,
        "false_matches": false,
        "false_match_rate": false / matched if matched else None,
        "frames_evaluated": int(idx.size),
        "settings": {
            "revisit_radius": s.revisit_radius,
            "revisit_gap_s": s.revisit_gap_s,
            "match_radius": s.match_radius,
            "false_radius": s.false_radius,
        },
    }
