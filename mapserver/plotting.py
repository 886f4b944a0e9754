"""Plotting: the one module that imports matplotlib; every figure mapserver draws is made and saved here.

Figures are ``matplotlib.figure.Figure`` objects on the Agg canvas of their own (the object-oriented API):
no pyplot, no global backend or state, no lock, so any number of threads may draw at once. matplotlib is
imported when the first figure is made, not when a module that may draw one is imported. The drawing itself
(what goes on the axes) stays with its concept: the export's plot of a stored map (:mod:`mapserver.store.export`),
the map against ground truth (:mod:`mapserver.evaluation.plots`), the report's figures (:mod:`mapserver.report`).
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["Axes", "Figure", "add_segments", "new_figure", "png_bytes", "session_colour"]

Segments = Sequence[tuple[npt.ArrayLike, npt.ArrayLike]] | npt.NDArray[np.float64]
"""Line segments: pairs of (x, y) end points, or an (N, 2, 2) array of them."""


def new_figure(size: tuple[float, float], *, dpi: float = 100.0) -> Figure:
    """Return an empty figure of ``size`` inches at ``dpi``, on an Agg canvas of its own."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig: Figure) -> bytes:
    """Return a figure rendered as PNG."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def add_segments(ax: Axes, segments: Segments, **style: Any) -> None:
    """Draw line segments on ``ax`` as one collection (``style``: ``LineCollection``'s colors, linestyles, ...)."""
    from matplotlib.collections import LineCollection

    ax.add_collection(LineCollection(segments, **style))  # type: ignore[arg-type]  # the stubs take a sequence; an (N, 2, 2) array is valid


def session_colour(k: int) -> tuple[float, float, float, float]:
    """Return the RGBA colour of the ``k``-th session (matplotlib's ``tab10`` cycle)."""
    from matplotlib import colormaps

    return colormaps["tab10"](k % 10)
