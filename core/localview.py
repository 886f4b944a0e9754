"""Local view cells: intensity templates built and matched as OpenRatSLAM's ``LocalViewMatch``.

Template construction (anchors §1.1): crop, greyscale (mean of the channels),
block-average into ``template_x_size × template_y_size`` cells (integer block
sizes; pixels past the last full block are ignored), values divided by 255,
optional global normalisation and patch normalisation. Matching compares the
current view with every stored template that passes the template-mean prefilter.

Speed: the comparison is OpenRatSLAM's own loop with its early break,
compiled (:mod:`core._match_kernel`): a (template, offset) pair is abandoned as soon as its running
sum exceeds the best so far (or ``vt_match_threshold`` when the caller only needs a match within it).
Values are compared in fixed point, exact in any summation order (a deviation, below).

Deliberate deviations from OpenRatSLAM (documented, not accidental):

* patch normalisation of a cell whose patch has σ = 0 gives 0.5 (OpenRatSLAM
  divides 0 by 0 and its clamp turns the NaN into 1.0, as ``openratslam_compat`` does);
* ``vt_shift_match`` larger than the template is narrowed to ``(tx − 1)//2``
  (OpenRatSLAM reads past the template);
* templates are stored as float32 (OpenRatSLAM: double); the mean is taken
  from the stored values so the prefilter sees what is stored;
* the matcher sums |differences| of values rounded to 2^-24 (integers): a pair's sum moves by at most
  one unit per value against float arithmetic, so only errors within ~1e-7 of each other can order
  differently;
* ``vt_shift_heading`` (ours, off by default): a forward view's best column shift
  gives its heading relative to the template, to a fraction of a column (:meth:`LocalViewCells._view_shift`),
  ``camera_fov_deg`` over the cropped image width per column. OpenRatSLAM forces ``relative_rad`` to 0 for
  forward views, so a closure there carries the robot's odometry facing whatever way the view is turned
  (``symmetric`` seed 1: loop links up to 29° off, mostly within 2.5° with the shift). The offset is returned
  in the engine's sign (the robot's heading minus the template's); ``openratslam_compat`` ignores the key.
  The angle of a column is ``camera_fov_deg`` over ``template_x_size`` when the crop keeps the full width; a
  crop of part of it takes the angle from the last image made into a template (a stored map's matcher takes
  the running session's), so an offline ``merge`` of cropped views gives forward views no heading.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, cast

import numpy as np

from core._buffers import GrowBuffer, SharedRows
from core._match_kernel import best_pair, fixed_point_bits, quantise
from core._match_kernel import load_compiled as load_compiled  # re-exported: callers load the kernel early
from core.arrays import Float32Array, FloatArray, Int32Array, IntArray, UInt8Array
from core.config import Departure

if TYPE_CHECKING:
    from core.config import Params



QUANTISE_ROWS = 512
"""Templates turned into fixed point at a time (:meth:`LocalViewCells._extend_fixed`): 8 MB for 128 × 32 templates."""


class ImageError(ValueError):
    """An image cannot be turned into a template with these parameters (shape, crop or size)."""


def greyscale(image: UInt8Array) -> FloatArray:
    """Return float64 grey values 0..255: the mean of the colour channels (OpenRatSLAM, RGB averaged)."""
    pixels = np.asarray(image)
    if pixels.ndim == 3:
        return cast(FloatArray, pixels[..., :3].astype(np.float64).mean(axis=2))
    if pixels.ndim != 2:
        msg = f"image must be (H, W) or (H, W, 3), got shape {pixels.shape}"
        raise ImageError(msg)
    return pixels.astype(np.float64)


def crop(grey: FloatArray, x_min: int, x_max: int, y_min: int, y_max: int) -> FloatArray:
    """Return ``grey[y_min:y_max, x_min:x_max]`` where −1 means "to the end" (OpenRatSLAM image_crop_*)."""
    h, w = grey.shape
    x1 = w if x_max < 0 else min(x_max, w)
    y1 = h if y_max < 0 else min(y_max, h)
    region = grey[min(y_min, h) : y1, min(x_min, w) : x1]
    if region.size == 0:
        msg = f"crop x {x_min}..{x_max}, y {y_min}..{y_max} leaves nothing of a {w}×{h} image"
        raise ImageError(msg)
    return region


def block_average(region: FloatArray, ty: int, tx: int, *, integral: bool = False) -> FloatArray:
    """Average ``region`` into ty × tx blocks of integer size; leftover rows/columns are dropped.

    With ``integral`` (every value a whole number, as a mono image's grey levels) each block's sum is exact
    in any order, so it is added up a column and then a row of the block at a time (strided slices, about
    six times faster than numpy's mean over two axes) with the same result bit for bit; otherwise numpy's mean.
    """
    h, w = region.shape
    by, bx = h // ty, w // tx
    if by == 0 or bx == 0:
        msg = f"a {w}×{h} crop is smaller than the {tx}×{ty} template"
        raise ImageError(msg)
    region = region[: by * ty, : bx * tx]
    if not integral:
        return cast(FloatArray, region.reshape(ty, by, tx, bx).mean(axis=(1, 3)))
    columns = region[:, 0::bx].copy()
    for k in range(1, bx):
        columns += region[:, k::bx]
    blocks = columns[0::by].copy()
    for k in range(1, by):
        blocks += columns[k::by]
    return cast(FloatArray, blocks / (by * bx))


def patch_normalise(values: FloatArray, radius: int, min_std: float, flat: float = 0.5) -> FloatArray:
    """Patch normalisation: ``clip(((v − μ)/σ + 3)/6, 0, 1)`` over the (2r+1)² neighbourhood.

    As OpenRatSLAM's ``convert_view_to_view_template``: positions outside the
    template are clamped to the nearest border cell (the border is replicated), so
    every patch has (2r+1)² samples; μ and σ are their mean and population standard
    deviation. Cells with σ < ``min_std`` become 0.5, and cells with σ = 0 ``flat``
    (0.5; OpenRatSLAM's 0/0 clamps to 1.0, which ``openratslam_compat`` passes).
    """
    from scipy.ndimage import uniform_filter  # here: scipy.ndimage's import is 0.25 s that most logs never need

    size = 2 * radius + 1
    mean = uniform_filter(values, size=size, mode="nearest")
    mean_sq = uniform_filter(values * values, size=size, mode="nearest")
    std = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
    out = np.full_like(values, 0.5)
    ok = (std > 0) & (std >= min_std)
    out[ok] = np.clip(((values[ok] - mean[ok]) / std[ok] + 3.0) / 6.0, 0.0, 1.0)
    if flat != 0.5:
        out[(std == 0) & (std >= min_std)] = flat
    return out


class LocalViewCells:
    """Template store and matcher (OpenRatSLAM ``LocalViewMatch`` semantics)."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self._templates = SharedRows((params.template_y_size, params.template_x_size), np.float32)
        self._means = GrowBuffer((), np.float64)
        tx = params.template_x_size
        self._span = 2 * tx - 1 if params.vt_panoramic else tx  # panoramic: first tx − 1 columns repeated
        self._bits = fixed_point_bits(self._span, 1.0)
        self._fixed = GrowBuffer((params.template_y_size, self._span), np.int32)  # the matcher's fixed point
        self.current = -1
        self.previous = -1
        self.relative_rad = 0.0
        self.last_view: Float32Array | None = None
        self.last_mean = 0.0
        self.last_error = math.inf
        self._column_rad = self._full_width_column_rad()  # heading per template column (vt_shift_heading)

    def _full_width_column_rad(self) -> float:
        """Return the heading one template column spans when the crop keeps the image's full width (else 0).

        ``camera_fov_deg`` over ``template_x_size``: known before any image, so matchers built from stored
        templates alone (a stored map's places, offline merges) give forward views their heading too. A crop
        of part of the width needs the image's width: :meth:`make_template` sets it from the first image.
        """
        p = self.params
        if p.image_crop_x_min == 0 and p.image_crop_x_max == -1:
            return math.radians(p.camera_fov_deg) / p.template_x_size
        return 0.0

    @property
    def column_rad(self) -> float:
        """Return the heading in radians one template column spans (``vt_shift_heading``; 0: not known yet)."""
        return self._column_rad

    @column_rad.setter
    def column_rad(self, value: float) -> None:
        self._column_rad = float(value)

    # -------------------------------------------------------------- accessors
    @property
    def count(self) -> int:
        """Return the number of stored templates."""
        return len(self._means)

    @property
    def templates(self) -> Float32Array:
        """Return the stored templates (N, ty, tx) float32, read-only: a view of one block, else the blocks joined."""
        return self._templates.view

    @property
    def means(self) -> FloatArray:
        """Return the template means (N,) (view)."""
        return self._means.view

    def add_templates(self, templates: Float32Array, means: np.ndarray, share: bool = False) -> None:
        """Append templates with their means and fixed-point copies (new views, merge, restore, benchmarks).

        ``share`` (before any template is made): the float32 templates are kept as given, read-only, not
        copied (:class:`core._buffers.SharedRows`); the fixed-point copies are the store's own either way.
        """
        stored = np.asarray(templates, dtype=np.float32)
        if share:
            self._templates.share(stored)
        else:
            self._templates.extend(stored)
        self._means.extend(np.asarray(means, dtype=np.float64))
        peak = float(np.maximum(stored.max(), -stored.min())) if stored.size else 0.0  # max |value|, no copy
        if peak > 1.0:  # values beyond [−1, 1]: fewer fixed-point bits
            bits = fixed_point_bits(self._span, peak)
            if bits < self._bits:
                self._bits = bits
                everything = self._templates.view
                self._fixed = GrowBuffer(self._fixed.view.shape[1:], np.int32)
                self._extend_fixed(everything[: len(everything) - len(stored)])
        self._extend_fixed(stored)

    def _extend_fixed(self, templates: Float32Array) -> None:
        """Append templates (n, ty, tx) to the fixed-point store, ``QUANTISE_ROWS`` at a time.

        The store is filled in blocks so that a restore of a large map needs temporaries of one block only.
        """
        if not len(templates):
            return
        self._fixed.reserve(len(self._fixed) + len(templates))
        for first in range(0, len(templates), QUANTISE_ROWS):
            self._fixed.extend(self._to_fixed(templates[first : first + QUANTISE_ROWS]))

    def _to_fixed(self, templates: Float32Array) -> Int32Array:
        """Return templates (n, ty, tx) in the matcher's fixed point, panoramic ones widened to wrap."""
        fixed = quantise(templates, self._bits)
        if self._span > fixed.shape[-1]:
            fixed = np.concatenate([fixed, fixed[..., : self._span - fixed.shape[-1]]], axis=-1)
        return fixed

    # ------------------------------------------------------------- templates
    def make_template(self, image: UInt8Array) -> tuple[Float32Array, float]:
        """Build the template of ``image``: (float32 (ty, tx) in [0, 1], mean).

        OpenRatSLAM ``convert_view_to_view_template``: crop, greyscale, block
        average /255, then ``v·vt_normalisation/mean`` clipped to [0, 1] when
        ``vt_normalisation`` > 0, then patch normalisation when ``vt_patch_normalise`` > 0.
        """
        p = self.params
        grey = greyscale(image)
        region = crop(grey, p.image_crop_x_min, p.image_crop_x_max, p.image_crop_y_min, p.image_crop_y_max)
        self._column_rad = math.radians(p.camera_fov_deg) * region.shape[1] / grey.shape[1] / p.template_x_size
        integral = np.ndim(image) == 2 and np.issubdtype(np.asarray(image).dtype, np.integer)
        values = block_average(region, p.template_y_size, p.template_x_size, integral=integral) / 255.0
        if p.vt_normalisation > 0:
            mean = values.mean()
            if mean > 0:
                values = np.clip(values * (p.vt_normalisation / mean), 0.0, 1.0)
        if p.vt_patch_normalise > 0:
            flat = 1.0 if p.follows_openratslam(Departure.PATCH) else 0.5
            values = patch_normalise(values, p.vt_patch_normalise, p.vt_min_patch_normalisation_std, flat)
        template = values.astype(np.float32)
        return template, float(template.mean(dtype=np.float64))

    def match(self, template: Float32Array, mean: float, limit: float | None = None) -> tuple[int, float, float]:
        """Return (best template id or −1, error, relative_rad) without creating a template.

        OpenRatSLAM ``compare``: templates whose mean differs by more than
        ``vt_match_threshold + vt_mean_prefilter_epsilon`` are skipped. Non-panoramic:
        for offsets 0..2·shift (step ``vt_step_match``) the mean absolute difference
        between the view's columns [shift, X−shift) and the template's columns
        [offset, offset + X − 2·shift); relative_rad = 0. Panoramic: every circular
        column offset (step ``vt_step_match``), error over the whole template,
        relative_rad = offset/X·2π wrapped to (−π, π] (the view is the template
        rotated by −offset columns). Ties go to the lowest template id, then the
        lowest offset.

        Args:
            template: the view's template (ty, tx).
            mean: its mean.
            limit: when given, only errors ≤ ``limit`` matter: pairs whose column-sum
                lower bound exceeds it are skipped, and (−1, inf, 0) means no template
                is within ``limit``. The answer is then the same as without ``limit``
                whenever the best error is ≤ ``limit``.
        """
        if self.count == 0:
            return -1, math.inf, 0.0
        prefilter = self.params.vt_match_threshold + self.params.vt_mean_prefilter_epsilon
        return self._best_of(template, np.flatnonzero(np.abs(self._means.view - mean) <= prefilter), limit)

    def match_among(
        self, template: Float32Array, mean: float, ids: IntArray, limit: float | None = None
    ) -> tuple[int, float, float]:
        """Return :meth:`match`'s answer restricted to the templates ``ids`` (same prefilter, bounds, ties).

        The merge verification asks whether the current view matches one of the templates that a
        stored map predicts at a place (``mapserver.merge.hypotheses``), not whether it matches any.
        """
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        prefilter = self.params.vt_match_threshold + self.params.vt_mean_prefilter_epsilon
        return self._best_of(template, ids[np.abs(self._means.view[ids] - mean) <= prefilter], limit)

    def _best_of(self, template: Float32Array, candidates: IntArray, limit: float | None) -> tuple[int, float, float]:
        """Return (best of the sorted, prefiltered template ids ``candidates`` or −1, error, relative_rad)."""
        p = self.params
        if candidates.size == 0:
            return -1, math.inf, 0.0
        view = np.asarray(template, dtype=np.float32)
        ty, tx = view.shape
        step = max(p.vt_step_match, 1)
        if p.vt_panoramic:
            offsets = np.arange(0, tx, step)
            width, start = tx, 0
        else:
            shift = min(p.vt_shift_match, (tx - 1) // 2)
            offsets = np.arange(0, 2 * shift + 1, step)
            width, start = tx - 2 * shift, shift
        norm = float(ty * width)
        unit = float(2**self._bits)
        limit_sum = np.iinfo(np.int64).max
        if limit is not None:  # plus one unit per value: the fixed point never drops a pair within the limit
            limit_sum = math.floor(limit * norm * unit) + ty * width
        fixed_view = quantise(view, self._bits)
        row, col, total = best_pair(self._fixed.view, candidates, fixed_view, offsets, width, start, limit_sum)
        if row < 0:
            return -1, math.inf, 0.0
        error = total / unit / norm
        if limit is not None and error > limit:
            return -1, math.inf, 0.0
        relative = 0.0
        if p.vt_panoramic:
            relative = float(offsets[col]) / tx * 2.0 * math.pi
            if relative > math.pi:
                relative -= 2.0 * math.pi
        elif p.vt_shift_heading and not p.openratslam_compat:
            relative = -float(self._view_shift(fixed_view, int(candidates[row]), width, start)) * self._column_rad
        return int(candidates[row]), error, relative

    def view_heading(self, template: int, view: Float32Array | None = None) -> float:
        """Return a view's heading relative to ``template`` in radians, from its column shift.

        The robot's heading minus the template's, as ``vt_shift_heading`` gives it with every match
        (:meth:`_view_shift`, ``camera_fov_deg`` over the template width per column). ``view``: a template-sized
        view (default: the last one processed). 0 for a panoramic view (its match already gives the offset),
        before the column angle is known, or with no view. ``merge_view_heading`` asks it only where two sessions
        meet: a closure joining their experiences, a merge's ties.
        """
        p = self.params
        view = self.last_view if view is None else view
        if view is None or p.vt_panoramic or self._column_rad <= 0 or not 0 <= template < self.count:
            return 0.0
        tx = int(view.shape[1])
        start = min(p.vt_shift_match, (tx - 1) // 2)
        fixed_view = quantise(np.asarray(view, dtype=np.float32), self._bits)
        return -float(self._view_shift(fixed_view, template, tx - 2 * start, start)) * self._column_rad

    def _view_shift(self, fixed_view: Int32Array, template: int, width: int, start: int) -> float:
        """Return the view's column shift against ``template`` to a fraction of a column (``vt_shift_heading``).

        The summed |difference| at every whole offset 0..2·start, then the vertex of the parabola through the
        least one and its two neighbours; the view's column ``start + j`` shows the template's column
        ``start + j + shift``, so a robot turned left of the template (a positive heading) gives a negative shift.
        """
        windows = np.lib.stride_tricks.sliding_window_view(self._fixed.view[template], width, axis=1)
        totals = np.abs(windows[:, : 2 * start + 1, :] - fixed_view[:, None, start : start + width])
        sums = totals.sum(axis=(0, 2), dtype=np.int64).astype(np.float64)
        best = int(np.argmin(sums))
        fraction = 0.0
        if 0 < best < sums.size - 1:
            curvature = sums[best - 1] - 2.0 * sums[best] + sums[best + 1]
            if curvature > 0:
                fraction = 0.5 * (sums[best - 1] - sums[best + 1]) / curvature
        return best + fraction - start

    def process(self, image: UInt8Array) -> tuple[int, float, bool]:
        """Match ``image`` or store it as a new template; return (id, relative_rad, created)."""
        template, mean = self.make_template(image)
        best, error, relative = self.match(template, mean, limit=self.params.vt_match_threshold)
        self.last_view, self.last_mean, self.last_error = template, mean, error
        self.previous = self.current
        if best >= 0 and error <= self.params.vt_match_threshold:
            self.current = best
            self.relative_rad = relative
            return best, relative, False
        self.add_templates(template[None], np.array([mean]))
        self.current = self.count - 1
        self.relative_rad = 0.0
        return self.current, 0.0, True

    # -------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the template store as plain arrays (keys ``lv_*``).

        ``lv_templates`` is read-only: the store's own rows when they are one block (templates never change once
        made, and later ones are kept after them), else the blocks joined in a new array.
        """
        return {
            "lv_templates": self._templates.view,
            "lv_means": self._means.copy(),
            "lv_current": np.asarray(self.current, dtype=np.int64),
            "lv_previous": np.asarray(self.previous, dtype=np.int64),
            "lv_relative_rad": np.asarray(self.relative_rad, dtype=np.float64),
        }

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> LocalViewCells:
        """Rebuild the store from :meth:`snapshot` arrays, exactly.

        A float32 ``lv_templates`` array is shared, read-only, not copied: the store's templates are that
        array, and templates made later are kept after it (:class:`core._buffers.SharedRows`).
        """
        cells = cls(params)
        templates = np.asarray(state["lv_templates"], dtype=np.float32)
        if templates.size:
            shape = (-1, params.template_y_size, params.template_x_size)
            cells.add_templates(templates.reshape(shape), state["lv_means"], share=True)
        cells.current = int(state["lv_current"])
        cells.previous = int(state["lv_previous"])
        cells.relative_rad = float(state["lv_relative_rad"])
        return cells
