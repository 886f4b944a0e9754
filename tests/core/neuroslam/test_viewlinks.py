"""NeuroSLAM's view calibration: when a template injects, how much, and that it round-trips."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.neuroslam import ConjunctivePoseCells, ViewLinks


def run(links: ViewLinks, cells: ConjunctivePoseCells, templates: list[tuple[int, bool]]) -> list[bool]:
    injected = []
    for template, created in templates:
        injected.append(links.on_view(template, created, cells))
        cells.step(0.4, 0.0, 0.0)
    return injected


def test_a_template_injects_only_when_re_entered_and_rested() -> None:
    links, cells = ViewLinks(), ConjunctivePoseCells()
    frames = [(0, True), (1, True)] + [(1, False)] * 24  # template 0 made at frame 0, then 25 frames of template 1
    assert not any(run(links, cells, frames))  # a template never injects on the frames that made it, or in a row
    stored = links.codes[0]
    cell = tuple(round(c) % 36 for c in stored[:3])
    before = cells.grid.activity[cell]
    assert links.on_view(0, False, cells)
    # decay: 2.0 at creation, 26 frames × 0.1 floors it at 0, then + 2.0 on being seen: δ (30 − e^{2.4}) / 30
    assert links.decay[0] == pytest.approx(2.0)
    assert cells.grid.activity[cell] - before == pytest.approx(0.1 * (30 - math.exp(2.4)) / 30, rel=1e-12)


def test_a_template_seen_again_soon_does_not_inject() -> None:
    links, cells = ViewLinks(), ConjunctivePoseCells()
    injected = run(links, cells, [(0, True), (1, True), (1, False), (1, False), (0, False)])
    assert injected == [False] * 5
    assert links.decay[0] == pytest.approx(2.0 - 0.4 + 2.0)  # above ln 30 / 1.2: no energy
    assert not links.first[0]  # re-entered from template 1: it may inject once rested


def test_ids_must_follow_the_view_cells() -> None:
    links, cells = ViewLinks(), ConjunctivePoseCells()
    with pytest.raises(ValueError, match="next id"):
        links.on_view(3, True, cells)
    with pytest.raises(ValueError, match="never created"):
        links.on_view(0, False, cells)


def test_view_links_round_trip() -> None:
    links, cells = ViewLinks(), ConjunctivePoseCells()
    run(links, cells, [(0, True), (1, True), (0, False), (2, True)])
    again = ViewLinks.restore(links.snapshot())
    assert np.array_equal(np.asarray(again.codes), np.asarray(links.codes))
    assert again.decay.tobytes() == links.decay.tobytes()
    assert (again.first, again.previous) == (links.first, links.previous)
