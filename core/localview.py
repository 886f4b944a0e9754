"""Local view cells: intensity templates built and matched as OpenRatSLAM's ``LocalViewMatch``.

Template construction (anchors §1.1): crop, greyscale (mean of the channels),
block-average into ``template_x_size × template_y_size`` cells (integer block
sizes; pixels past the last full block are ignored), values divided by 255,
optional global normalisation and patch normalisation. Matching compares the
current view with every stored template at once (vectorised over templates),
after the template-mean prefilter.

Speed without changing the result: when a caller only needs to know whether
some template is within a limit (``process`` asks for ``vt_match_threshold``),
each (template, offset) pair is first bounded from below by its column sums,
``Σ_x |Σ_y v − Σ_y t| ≤ Σ_x Σ_y |v − t|`` (triangle inequality), then the pairs
that pass by the same bound over horizontal bands of rows (up to
``BOUND_BANDS`` bands: ``Σ_b Σ_x |Σ_{y∈b} v − Σ_{y∈b} t|``, tighter and still a
lower bound), and only pairs whose bounds are within the limit get the full
comparison. OpenRatSLAM's early break inside the difference loop plays the same
role there.

Deliberate deviations from OpenRatSLAM (documented, not accidental):

* patch normalisation of a cell whose patch has σ = 0 gives 0.5 (OpenRatSLAM
  divides 0 by 0 and its clamp turns the NaN into 1.0, as ``openratslam_compat`` does);
* ``vt_shift_match`` larger than the template is narrowed to ``(tx − 1)//2``
  (OpenRatSLAM reads past the template);
* templates are stored as float32 (OpenRatSLAM: double); the mean is taken
  from the stored values so the prefilter sees what is stored.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from scipy.ndimage import uniform_filter

from core._buffers import GrowBuffer, Scratch

if TYPE_CHECKING:
    from core.config import Params

BOUND_BANDS = 4  # row bands of the second matching bound (more bands: tighter bound, more work)
FLOAT32_UNIT = 2.0**-24  # unit roundoff of float32
SPLIT_MIN_ROWS = 16  # fewer templates than this left after the bounds: compare all rows in one pass


class ImageError(ValueError):
    """An image cannot be turned into a template with these parameters (shape, crop or size)."""


def greyscale(image: np.ndarray) -> np.ndarray:
    """Return float64 grey values 0..255: the mean of the colour channels (OpenRatSLAM, RGB averaged)."""
    pixels = np.asarray(image)
    if pixels.ndim == 3:
        return pixels[..., :3].astype(np.float64).mean(axis=2)
    if pixels.ndim != 2:
        msg = f"image must be (H, W) or (H, W, 3), got shape {pixels.shape}"
        raise ImageError(msg)
    return pixels.astype(np.float64)


def crop(grey: np.ndarray, x_min: int, x_max: int, y_min: int, y_max: int) -> np.ndarray:
    """Return ``grey[y_min:y_max, x_min:x_max]`` where −1 means "to the end" (OpenRatSLAM image_crop_*)."""
    h, w = grey.shape
    x1 = w if x_max < 0 else min(x_max, w)
    y1 = h if y_max < 0 else min(y_max, h)
    region = grey[min(y_min, h) : y1, min(x_min, w) : x1]
    if region.size == 0:
        msg = f"crop x {x_min}..{x_max}, y {y_min}..{y_max} leaves nothing of a {w}×{h} image"
        raise ImageError(msg)
    return region


def block_average(region: np.ndarray, ty: int, tx: int) -> np.ndarray:
    """Average ``region`` into ty × tx blocks of integer size; leftover rows/columns are dropped."""
    h, w = region.shape
    by, bx = h // ty, w // tx
    if by == 0 or bx == 0:
        msg = f"a {w}×{h} crop is smaller than the {tx}×{ty} template"
        raise ImageError(msg)
    return region[: by * ty, : bx * tx].reshape(ty, by, tx, bx).mean(axis=(1, 3))


def patch_normalise(values: np.ndarray, radius: int, min_std: float, flat: float = 0.5) -> np.ndarray:
    """Patch normalisation: ``clip(((v − μ)/σ + 3)/6, 0, 1)`` over the (2r+1)² neighbourhood.

    As OpenRatSLAM's ``convert_view_to_view_template``: positions outside the
    template are clamped to the nearest border cell (the border is replicated), so
    every patch has (2r+1)² samples; μ and σ are their mean and population standard
    deviation. Cells with σ < ``min_std`` become 0.5, and cells with σ = 0 ``flat``
    (0.5; OpenRatSLAM's 0/0 clamps to 1.0, which ``openratslam_compat`` passes).
    """
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


def band_edges(rows: int, bands: int) -> np.ndarray:
    """Return the row boundaries [0, …, rows] splitting ``rows`` into ``min(bands, rows)`` near-equal bands."""
    count = max(1, min(bands, rows))
    return (np.arange(count + 1) * rows) // count


def band_sums(templates: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Return (N, bands, tx) float64: each template's column sums over the row bands ``edges[b]:edges[b+1]``."""
    sizes = np.diff(edges)
    if np.all(sizes == sizes[0]):  # equal bands: one reduction over a reshaped view
        n, tx = templates.shape[0], templates.shape[2]
        return templates.reshape(n, sizes.size, int(sizes[0]), tx).sum(axis=2, dtype=np.float64)
    out = np.empty((templates.shape[0], edges.size - 1, templates.shape[2]), dtype=np.float64)
    for band in range(edges.size - 1):  # a handful of bands, each summed over every template at once
        templates[:, edges[band] : edges[band + 1], :].sum(axis=1, dtype=np.float64, out=out[:, band, :])
    return out


def offset_windows(a: np.ndarray, width: int, offsets: np.ndarray) -> np.ndarray:
    """Return a read-only (…, len(offsets), width) view: window k is ``a[..., o_k : o_k + width]``.

    ``offsets`` must be evenly spaced and ``a`` C-contiguous (a scratch buffer); the
    same as ``sliding_window_view(a, width, axis=-1)[..., offsets, :]`` without its
    per-call overhead, which dominates on the matcher's small arrays.
    """
    first = int(offsets[0])
    stride = int(offsets[1] - offsets[0]) if offsets.size > 1 else 1
    step = a.strides[-1]
    shape = (*a.shape[:-1], int(offsets.size), width)
    strides = (*a.strides[:-1], step * stride, step)
    view = np.ndarray(shape, dtype=a.dtype, buffer=a, offset=first * step, strides=strides)
    view.flags.writeable = False
    return view


class LocalViewCells:
    """Template store and matcher (OpenRatSLAM ``LocalViewMatch`` semantics)."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self._templates = GrowBuffer((params.template_y_size, params.template_x_size), np.float32)
        self._means = GrowBuffer((), np.float64)
        self._colsums = GrowBuffer((params.template_x_size,), np.float32)  # Σ_y per column (match bound)
        self._band_edges = band_edges(params.template_y_size, BOUND_BANDS)
        bands = self._band_edges.size - 1
        self._bandsums = GrowBuffer((bands, params.template_x_size), np.float32)  # Σ_{y∈band} per column
        self._peak = 0.0  # the largest |value| of any stored template (float32 slack of the bounds)
        self._scratch = Scratch()
        self.current = -1
        self.previous = -1
        self.relative_rad = 0.0
        self.last_view: np.ndarray | None = None
        self.last_mean = 0.0
        self.last_error = math.inf

    # -------------------------------------------------------------- accessors
    @property
    def count(self) -> int:
        """Return the number of stored templates."""
        return len(self._means)

    @property
    def templates(self) -> np.ndarray:
        """Return the stored templates (N, ty, tx) float32 (view)."""
        return self._templates.view

    @property
    def means(self) -> np.ndarray:
        """Return the template means (N,) (view)."""
        return self._means.view

    def add_templates(self, templates: np.ndarray, means: np.ndarray) -> None:
        """Append templates with their means, column and band sums (new views, merge, restore, benchmarks)."""
        stored = np.asarray(templates, dtype=np.float32)
        self._templates.extend(stored)
        self._means.extend(np.asarray(means, dtype=np.float64))
        bands = band_sums(stored, self._band_edges)
        self._colsums.extend(bands.sum(axis=1))
        self._bandsums.extend(bands)
        if stored.size:
            self._peak = max(self._peak, float(stored.max()), -float(stored.min()))

    # ------------------------------------------------------------- templates
    def make_template(self, image: np.ndarray) -> tuple[np.ndarray, float]:
        """Build the template of ``image``: (float32 (ty, tx) in [0, 1], mean).

        OpenRatSLAM ``convert_view_to_view_template``: crop, greyscale, block
        average /255, then ``v·vt_normalisation/mean`` clipped to [0, 1] when
        ``vt_normalisation`` > 0, then patch normalisation when ``vt_patch_normalise`` > 0.
        """
        p = self.params
        region = crop(greyscale(image), p.image_crop_x_min, p.image_crop_x_max, p.image_crop_y_min, p.image_crop_y_max)
        values = block_average(region, p.template_y_size, p.template_x_size) / 255.0
        if p.vt_normalisation > 0:
            mean = values.mean()
            if mean > 0:
                values = np.clip(values * (p.vt_normalisation / mean), 0.0, 1.0)
        if p.vt_patch_normalise > 0:
            flat = 1.0 if p.openratslam_compat else 0.5
            values = patch_normalise(values, p.vt_patch_normalise, p.vt_min_patch_normalisation_std, flat)
        template = values.astype(np.float32)
        return template, float(template.mean(dtype=np.float64))

    def match(self, template: np.ndarray, mean: float, limit: float | None = None) -> tuple[int, float, float]:
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
        self, template: np.ndarray, mean: float, ids: np.ndarray, limit: float | None = None
    ) -> tuple[int, float, float]:
        """Return :meth:`match`'s answer restricted to the templates ``ids`` (same prefilter, bounds, ties).

        The merge verification asks whether the current view matches one of the templates that a
        stored map predicts at a place (``mapserver.merge.hypotheses``), not whether it matches any.
        """
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        prefilter = self.params.vt_match_threshold + self.params.vt_mean_prefilter_epsilon
        return self._best_of(template, ids[np.abs(self._means.view[ids] - mean) <= prefilter], limit)

    def _best_of(self, template: np.ndarray, candidates: np.ndarray, limit: float | None) -> tuple[int, float, float]:
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
        if limit is None:
            rows = candidates
            keep = np.ones((rows.size, offsets.size), dtype=bool)
            limit_sum = math.inf
        else:
            limit_sum = limit * norm
            limit_sum += 1e-5 * (1.0 + limit_sum)  # float32 sums: never drop a pair that could be within the limit
            keep = self._bounded_pairs(view, candidates, offsets, width, start, limit_sum)
            kept_rows = keep.any(axis=1)
            rows = candidates[kept_rows]
            keep = keep[kept_rows]
            if rows.size == 0:
                return -1, math.inf, 0.0
        errors = self._errors(view, rows, keep, offsets, width, start, limit_sum) / norm  # (rows, offsets)
        flat = int(np.argmin(errors))  # row-major (id, offset) order: the first minimum wins ties
        row, col = divmod(flat, offsets.size)
        error = float(errors[row, col])
        if limit is not None and error > limit:
            return -1, math.inf, 0.0
        relative = 0.0
        if p.vt_panoramic:
            relative = float(offsets[col]) / tx * 2.0 * math.pi
            if relative > math.pi:
                relative -= 2.0 * math.pi
        return int(rows[row]), error, relative

    def _bounded_pairs(
        self, view: np.ndarray, candidates: np.ndarray, offsets: np.ndarray, width: int, start: int, limit_sum: float
    ) -> np.ndarray:
        """Return the (candidates, offsets) mask of pairs whose lower bounds are ≤ ``limit_sum``.

        First the column-sum bound ``Σ_x |Σ_y v − Σ_y t|``, then, for the templates
        with a pair left, the band bound ``Σ_b Σ_x |Σ_{y∈b} v − Σ_{y∈b} t|``; neither
        exceeds the summed absolute difference (triangle inequality). Both run in
        float32 with the limit widened by a bound on float32 rounding, so a pair is
        never dropped that exact arithmetic would keep.
        """
        view_cols = view.sum(axis=0, dtype=np.float64)[start : start + width]
        keep = self._bound_below(self._colsums.view, candidates, view_cols, offsets, width, limit_sum, "col")
        rows = np.flatnonzero(keep.any(axis=1))
        if rows.size == 0:
            return keep
        view_bands = band_sums(view[None], self._band_edges)[0, :, start : start + width]
        band_keep = self._bound_below(
            self._bandsums.view, candidates[rows], view_bands, offsets, width, limit_sum, "band"
        )
        keep[rows] &= band_keep
        return keep

    def _bound_below(
        self,
        sums: np.ndarray,
        rows: np.ndarray,
        view_sums: np.ndarray,
        offsets: np.ndarray,
        width: int,
        limit_sum: float,
        name: str,
    ) -> np.ndarray:
        """Return the (rows, offsets) mask ``Σ |windows(sums[rows]) − view_sums| ≤ limit_sum`` (float32 sums).

        ``sums`` holds per-template float32 partial sums (N, …, tx) over rows (one
        band: column sums; several: band sums); ``view_sums`` the view's same sums over
        the compared columns (…, width), float64. Panoramic templates wrap around by
        repeating their first ``width − 1`` columns. Each of the m summed terms is
        off by at most 2u·(|v| + |t|) (u = 2⁻²⁴: the two roundings to float32 and the
        subtraction) and the summation by m·u·Σ more, so the limit is widened by
        ``4(m + 2)·u·(Σ|v| + ty·width·peak)`` (peak: the largest stored |value|).
        """
        tx = self.params.template_x_size
        inner = sums.shape[1:-1]
        span = tx + width - 1 if self.params.vt_panoramic else tx
        stored = self._scratch.get(name + "sums", (rows.size, *inner, span), np.float32)
        np.take(sums, rows, axis=0, out=stored[..., :tx] if self.params.vt_panoramic else stored)
        if self.params.vt_panoramic:
            stored[..., tx:] = stored[..., : width - 1]
        windows = offset_windows(stored, width, offsets)  # (n, …, offsets, width) view
        diff = self._scratch.get(name + "diff", windows.shape, np.float32)
        np.subtract(windows, view_sums.astype(np.float32)[..., None, :], out=diff)
        np.abs(diff, out=diff)
        bound = diff.sum(axis=-1).sum(axis=tuple(range(1, 1 + len(inner))))
        terms = math.prod(inner) * width
        magnitude = float(np.abs(view_sums).sum()) + self.params.template_y_size * width * self._peak
        slack = 4.0 * (terms + 2) * FLOAT32_UNIT * magnitude
        return bound <= limit_sum + slack

    def _errors(
        self,
        view: np.ndarray,
        rows: np.ndarray,
        keep: np.ndarray,
        offsets: np.ndarray,
        width: int,
        start: int,
        limit_sum: float,
    ) -> np.ndarray:
        """Return Σ|view − template| (len(rows), len(offsets)) for the ``keep`` pairs; inf for the others.

        With a finite ``limit_sum`` and more than ``SPLIT_MIN_ROWS`` templates the rows
        are compared in two bands: a pair whose first-band sum already exceeds the
        limit is dropped (its error is inf), the vectorised counterpart of
        OpenRatSLAM's early break.
        """
        ty, tx = view.shape
        panoramic = self.params.vt_panoramic
        span = tx + width - 1 if panoramic else tx
        # two bands pay off only when many rows reach this stage; for a few the second pass is pure overhead
        split = ty // 2 if math.isfinite(limit_sum) and ty >= 2 and rows.size > SPLIT_MIN_ROWS else ty
        bands = [(0, split), (split, ty)] if split < ty else [(0, ty)]
        total = np.zeros(keep.shape, dtype=np.float64)
        alive = keep.copy()
        active = np.arange(rows.size)
        for y0, y1 in bands:
            h = y1 - y0
            chunk = max(1, (1 << 19) // (h * offsets.size * width))  # ≤ 2 MB of differences at a time
            for lo in range(0, active.size, chunk):
                part = active[lo : lo + chunk]
                n = part.size
                stored = self._scratch.get("templates", (n, h, span), np.float32)
                stored[:, :, :tx] = self._templates.view[rows[part], y0:y1, :]
                if panoramic:
                    stored[:, :, tx:] = stored[:, :, : width - 1]
                # every offset at once: a (n, h, offsets, width) view of sliding windows, no copy
                windows = offset_windows(stored, width, offsets)
                diff = self._scratch.get("diff", (n, h, offsets.size, width), np.float32)
                np.subtract(windows, view[y0:y1, None, start : start + width], out=diff)
                np.abs(diff, out=diff)
                row_sums = self._scratch.get("rowsums", (n, h, offsets.size), np.float32)
                np.sum(diff, axis=3, out=row_sums)
                total[part] += row_sums.sum(axis=1, dtype=np.float64)
            alive[active] &= total[active] <= limit_sum
            active = active[alive[active].any(axis=1)]
            if active.size == 0:
                break
        return np.where(alive, total, math.inf)

    def process(self, image: np.ndarray) -> tuple[int, float, bool]:
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
        """Return the template store as plain arrays (keys ``lv_*``)."""
        return {
            "lv_templates": self._templates.copy(),
            "lv_means": self._means.copy(),
            "lv_current": np.asarray(self.current, dtype=np.int64),
            "lv_previous": np.asarray(self.previous, dtype=np.int64),
            "lv_relative_rad": np.asarray(self.relative_rad, dtype=np.float64),
        }

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> LocalViewCells:
        """Rebuild the store from :meth:`snapshot` arrays, exactly."""
        cells = cls(params)
        templates = np.asarray(state["lv_templates"], dtype=np.float32)
        if templates.size:
            shape = (-1, params.template_y_size, params.template_x_size)
            cells.add_templates(templates.reshape(shape), state["lv_means"])
        cells.current = int(state["lv_current"])
        cells.previous = int(state["lv_previous"])
        cells.relative_rad = float(state["lv_relative_rad"])
        return cells
