"""The plot of a map aligned to ground truth (top view; maps with height: z against time as well)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from mapserver.evaluation.maps import MapEvaluation, align_map
from mapserver.formats import PathLike, Trajectory, atomic_write_bytes
from mapserver.plotting import add_segments, new_figure, png_bytes

if TYPE_CHECKING:
    from mapserver.plotting import Axes


def plot_map_vs_ground_truth(
    doc: Mapping[str, Any],
    gt: Trajectory,
    path: PathLike,
    *,
    odometry: Trajectory | None = None,
    title: str | None = None,
    max_diff_s: float = 0.05,
    session: str | None = None,
) -> None:
    """Plot a map, aligned to ground truth as in :func:`evaluate_map`, and write it as a PNG atomically.

    Top view with equal axes: the ground truth as a line, the aligned experiences as dots joined by their
    links (odometry links solid, loop/merge/manual links dashed), the aligned odometry dashed, and a legend
    with the APE RMSEs and the Hausdorff distance. Maps with height get a second panel, z against time.
    Drawn on a figure of :mod:`mapserver.plotting` (no pyplot, no global backend change).

    Args:
        doc: map JSON document.
        gt: ground-truth trajectory.
        path: destination PNG; its directory must exist.
        odometry: raw dead-reckoning trajectory, optional (else the map's ``"odometry"`` key).
        title: figure title (default: session names and experience count).
        max_diff_s: as for :func:`evaluate_map`.
        session: as for :func:`evaluate_map`.

    Raises:
        InputError: as for :func:`evaluate_map`.

    """
    ev = align_map(doc, gt, odometry=odometry, max_diff_s=max_diff_s, session=session)
    three_d = ev.dims == 3
    fig = new_figure((13.0, 6.0) if three_d else (8.0, 7.0), dpi=110)
    if three_d:
        ax = fig.add_subplot(1, 2, 1)
        ax_z = fig.add_subplot(1, 2, 2)
    else:
        ax = fig.add_subplot(1, 1, 1)
        ax_z = None

    _plot_top_view(ax, ev)
    if ax_z is not None:
        _plot_height(ax_z, ev)

    if title is None:
        names = ev.session or ", ".join(str(s.get("name")) for s in doc.get("sessions", [])) or "map"
        title = f"{names}: {len(ev.exp_ids)} experiences vs ground truth"
    fig.suptitle(title)
    fig.tight_layout()
    atomic_write_bytes(path, png_bytes(fig))


def _plot_top_view(ax: Axes, ev: MapEvaluation) -> None:
    """Draw the top view: ground truth, aligned odometry, experiences joined by their links, legend."""
    ax.plot(ev.gt_xyz[:, 0], ev.gt_xyz[:, 1], "-", color="k", lw=1.2, label="ground truth")
    if ev.odo_aligned is not None and ev.odo_ape is not None:
        ax.plot(
            ev.odo_aligned[:, 0],
            ev.odo_aligned[:, 1],
            "--",
            color="C1",
            lw=1.0,
            label=f"odometry (APE RMSE {ev.odo_ape.rmse:.3f} m)",
        )
    xy = ev.exp_aligned[:, :2]
    odo_links = [(xy[i], xy[j]) for i, j, kind in ev.links if kind == "odometry"]
    other_links = [(xy[i], xy[j]) for i, j, kind in ev.links if kind != "odometry"]
    if odo_links:
        add_segments(ax, odo_links, colors="C0", linewidths=0.8, alpha=0.6)
    if other_links:
        add_segments(ax, other_links, colors="C3", linewidths=0.8, linestyles="dashed", alpha=0.7)
    ax.scatter(
        xy[:, 0],
        xy[:, 1],
        s=9,
        color="C0",
        zorder=3,
        label=f"experiences (APE RMSE {ev.ape.rmse:.3f} m, Hausdorff {ev.hausdorff:.3f} m)",
    )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _plot_height(ax: Axes, ev: MapEvaluation) -> None:
    """Draw the height panel: ground truth, aligned odometry and experiences, z against time."""
    ax.plot(ev.gt.stamps_s, ev.gt_xyz[:, 2], "-", color="k", lw=1.2, label="ground truth")
    if ev.odo_aligned is not None and ev.odo_stamps is not None:
        ax.plot(ev.odo_stamps, ev.odo_aligned[:, 2], "--", color="C1", lw=1.0, label="odometry")
    ax.scatter(ev.exp_stamps, ev.exp_aligned[:, 2], s=9, color="C0", zorder=3, label="experiences")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("z (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
