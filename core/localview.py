"""Local view cells: intensity templates built and matched as OpenRatSLAM's ``LocalViewMatch``.

Template construction (anchors §1.1): crop, greyscale (mean of the channels),
block-average into ``template_x_size × template_y_size`` cells (integer block
sizes; pixels past the last full block are ignored), values divided by 255,
optional global normalisation and patch normalisation. Matching compares the
current view with every stored template at once (vectorised over templates, a
loop only over the column offsets), after the template-mean prefilter.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from scipy.ndimage import uniform_filter

from core._buffers import GrowBuffer

if TYPE_CHECKING:
    from core.config import Params


def greyscale(image: np.ndarray) -> np.ndarray:
    """Return float64 grey values 0..255: the mean of the colour channels (OpenRatSLAM, RGB averaged)."""
    pixels = np.asarray(image)
    if pixels.ndim == 3:
        return pixels[..., :3].astype(np.float64).mean(axis=2)
    if pixels.ndim != 2:
        msg = f"image must be (H, W) or (H, W, 3), got shape {pixels.shape}"
        raise ValueError(msg)
    return pixels.astype(np.float64)


def crop(grey: np.ndarray, x_min: int, x_max: int, y_min: int, y_max: int) -> np.ndarray:
    """Return ``grey[y_min:y_max, x_min:x_max]`` where −1 means "to the end" (OpenRatSLAM image_crop_*)."""
    h, w = grey.shape
    x1 = w if x_max < 0 else min(x_max, w)
    y1 = h if y_max < 0 else min(y_max, h)
    region = grey[min(y_min, h) : y1, min(x_min, w) : x1]
    if region.size == 0:
        msg = f"crop x {x_min}..{x_max}, y {y_min}..{y_max} leaves nothing of a {w}×{h} image"
        raise ValueError(msg)
    return region


def block_average(region: np.ndarray, ty: int, tx: int) -> np.ndarray:
    """Average ``region`` into ty × tx blocks of integer size; leftover rows/columns are dropped."""
    h, w = region.shape
    by, bx = h // ty, w // tx
    if by == 0 or bx == 0:
        msg = f"a {w}×{h} crop is smaller than the {tx}×{ty} template"
        raise ValueError(msg)
    return region[: by * ty, : bx * tx].reshape(ty, by, tx, bx).mean(axis=(1, 3))


def patch_normalise(values: np.ndarray, radius: int, min_std: float) -> np.ndarray:
    """Patch normalisation: ``clip(((v − μ)/σ + 3)/6, 0, 1)`` over the (2r+1)² neighbourhood.

    μ and σ are the mean and population standard deviation of the cells within the
    window clipped at the template border (the window shrinks at the edges, as
    OpenRatSLAM's loop bounds do); cells with σ < ``min_std`` (or σ = 0) become 0.5.
    """
    size = 2 * radius + 1
    ones = np.ones_like(values)
    count = uniform_filter(ones, size=size, mode="constant", cval=0.0)
    mean = uniform_filter(values, size=size, mode="constant", cval=0.0) / count
    mean_sq = uniform_filter(values * values, size=size, mode="constant", cval=0.0) / count
    std = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
    out = np.full_like(values, 0.5)
    ok = (std > 0) & (std >= min_std)
    out[ok] = np.clip(((values[ok] - mean[ok]) / std[ok] + 3.0) / 6.0, 0.0, 1.0)
    return out


class LocalViewCells:
    """Template store and matcher (OpenRatSLAM ``LocalViewMatch`` semantics)."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self._templates = GrowBuffer((params.template_y_size, params.template_x_size), np.float32)
        self._means = GrowBuffer((), np.float64)
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
        """Append templates in bulk (merge, restore, benchmarks)."""
        self._templates.extend(np.asarray(templates, dtype=np.float32))
        self._means.extend(np.asarray(means, dtype=np.float64))

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
            values = patch_normalise(values, p.vt_patch_normalise, p.vt_min_patch_normalisation_std)
        template = values.astype(np.float32)
        return template, float(template.mean(dtype=np.float64))

    def match(self, template: np.ndarray, mean: float) -> tuple[int, float, float]:
        """Return (best template id or −1, error, relative_rad) without creating a template.

        OpenRatSLAM ``compare``: templates whose mean differs by more than
        ``vt_match_threshold + vt_mean_prefilter_epsilon`` are skipped. Non-panoramic:
        for offsets 0..2·shift (step ``vt_step_match``) the mean absolute difference
        between the view's columns [shift, X−shift) and the template's columns
        [offset, offset + X − 2·shift); relative_rad = 0. Panoramic: every circular
        column offset, error over the whole template, relative_rad = offset/X·2π
        wrapped to (−π, π] (the view is the template rotated by −offset columns).
        Ties go to the lowest template id, then the lowest offset.
        """
        p = self.params
        n = self.count
        if n == 0:
            return -1, math.inf, 0.0
        limit = p.vt_match_threshold + p.vt_mean_prefilter_epsilon
        candidates = np.flatnonzero(np.abs(self._means.view - mean) <= limit)
        if candidates.size == 0:
            return -1, math.inf, 0.0
        stored = self._templates.view[candidates]
        view = np.asarray(template, dtype=np.float32)
        ty, tx = view.shape
        if p.vt_panoramic:
            offsets = np.arange(0, tx, max(p.vt_step_match, 1))
            errors = np.empty((candidates.size, offsets.size), dtype=np.float64)
            for j, offset in enumerate(offsets.tolist()):
                rolled = np.roll(stored, -offset, axis=2)
                errors[:, j] = np.abs(rolled - view).sum(axis=(1, 2), dtype=np.float64)
            errors /= tx * ty
        else:
            shift = min(p.vt_shift_match, (tx - 1) // 2)
            width = tx - 2 * shift
            offsets = np.arange(0, 2 * shift + 1, max(p.vt_step_match, 1))
            window = view[:, shift : shift + width]
            errors = np.empty((candidates.size, offsets.size), dtype=np.float64)
            for j, offset in enumerate(offsets.tolist()):
                errors[:, j] = np.abs(stored[:, :, offset : offset + width] - window).sum(axis=(1, 2), dtype=np.float64)
            errors /= ty * width
        flat = int(np.argmin(errors))  # first minimum: lowest candidate (= lowest id), then lowest offset
        row, col = divmod(flat, offsets.size)
        best = int(candidates[row])
        error = float(errors[row, col])
        relative = 0.0
        if p.vt_panoramic:
            relative = float(offsets[col]) / tx * 2.0 * math.pi
            if relative > math.pi:
                relative -= 2.0 * math.pi
        return best, error, relative

    def process(self, image: np.ndarray) -> tuple[int, float, bool]:
        """Match ``image`` or store it as a new template; return (id, relative_rad, created)."""
        template, mean = self.make_template(image)
        best, error, relative = self.match(template, mean)
        self.last_view, self.last_mean, self.last_error = template, mean, error
        self.previous = self.current
        if best >= 0 and error <= self.params.vt_match_threshold:
            self.current = best
            self.relative_rad = relative
            return best, relative, False
        self._templates.append(template)
        self._means.append(mean)
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
