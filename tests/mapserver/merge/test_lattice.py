"""Pose-cell lattice transform (operations ii–iii): hand-computed offsets and algebra (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.lattice import wrapped_delta
from mapserver.merge.lattice import LatticeTransform, signed_delta, splat, wrap_coords

DIMS3 = (21, 21, 36)
DIMS4 = (15, 15, 15, 8)


def test_offset_is_loaded_minus_partial() -> None:
    """The corrected Eq. 10: Δ = loaded − partial (the printed equation adds them)."""
    f = LatticeTransform.between(DIMS3, source=(5.0, 7.0, 10.0), target=(8.0, 3.0, 10.0))
    assert f.offset == pytest.approx([3.0, -4.0, 0.0])
    # Eq. 11 with Δθ = 0: a plain shift modulo each dimension
    assert f.apply([20.0, 1.0, 35.0]) == pytest.approx([2.0, 18.0, 35.0])
    assert f.apply([5.0, 7.0, 10.0]) == pytest.approx([8.0, 3.0, 10.0])


def test_heading_offset_wraps_to_the_short_way() -> None:
    f = LatticeTransform.between(DIMS3, source=(0.0, 0.0, 34.0), target=(0.0, 0.0, 1.0))
    assert f.heading_cells == pytest.approx(3.0)
    assert f.heading_rad == pytest.approx(3 * 2 * math.pi / 36)
    assert f.apply([0.0, 0.0, 35.0]) == pytest.approx([0.0, 0.0, 2.0])


def test_90_degree_heading_offset_rotates_about_the_matched_cell() -> None:
    """Δθ = 9 of 36 cells = 90°: a displacement (+2, 0) in the partial lattice is (0, +2) in the loaded one."""
    f = LatticeTransform.between(DIMS3, source=(5.0, 5.0, 0.0), target=(10.0, 10.0, 9.0))
    assert f.heading_rad == pytest.approx(math.pi / 2)
    assert f.apply([7.0, 5.0, 0.0]) == pytest.approx([10.0, 12.0, 9.0])
    assert f.apply([5.0, 8.0, 2.0]) == pytest.approx([7.0, 10.0, 11.0])
    assert f.apply([5.0, 5.0, 30.0]) == pytest.approx([10.0, 10.0, 3.0])  # heading wraps
    # (20, 5) is 15 cells +x of the anchor = 6 cells −x around the 21-cell torus: → 6 cells −y
    assert f.apply([20.0, 5.0, 0.0]) == pytest.approx([10.0, 4.0, 9.0])
    # the paper's translation-only shift would have put (7, 5) at (12, 10): off by 2√2 cells
    paper = wrap_coords(np.array([7.0, 5.0, 0.0]) + f.offset, DIMS3)
    assert float(np.linalg.norm(paper[:2] - f.apply([7.0, 5.0, 0.0])[:2])) == pytest.approx(2 * math.sqrt(2))


def test_4dof_lattice_shifts_z_and_rotates_xy_only() -> None:
    f = LatticeTransform.between(DIMS4, source=(2.0, 2.0, 3.0, 0.0), target=(7.0, 7.0, 10.0, 2.0))  # 2 of 8 = 90°
    assert f.apply([3.0, 2.0, 4.0, 1.0]) == pytest.approx([7.0, 8.0, 11.0, 3.0])
    assert f.apply([2.0, 2.0, 14.0, 0.0]) == pytest.approx([7.0, 7.0, 6.0, 2.0])  # z wraps: 3→14 is −4


def test_bad_rank_is_refused() -> None:
    with pytest.raises(ValueError, match="rank"):
        LatticeTransform((5.0, 5.0), (0.0, 0.0), (1.0, 1.0))


def test_splat_keeps_the_sub_cell_centre() -> None:
    activity = splat(DIMS3, [3.25, 20.5, 35.75])
    assert activity.sum() == pytest.approx(1.0)
    assert np.count_nonzero(activity) == 8
    # population-vector mean of each axis recovers the centre (wrapping axes)
    for axis, expected in enumerate([3.25, 20.5, 35.75]):
        marginal = activity.sum(axis=tuple(a for a in range(3) if a != axis))
        n = DIMS3[axis]
        phase = np.arange(n) * 2 * math.pi / n
        centre = math.atan2(float(marginal @ np.sin(phase)), float(marginal @ np.cos(phase))) * n / (2 * math.pi)
        assert centre % n == pytest.approx(expected, abs=0.02)


# ----------------------------------------------------------------------------- hypothesis invariants

def cells(dims: tuple[int, ...]) -> st.SearchStrategy[np.ndarray]:
    return st.tuples(*[st.floats(0.0, float(d), exclude_max=True, allow_nan=False) for d in dims]).map(np.array)


@st.composite
def transforms(draw: st.DrawFn, dims: tuple[int, ...] = DIMS3, rotate: bool = True) -> LatticeTransform:
    source = draw(cells(dims))
    target = draw(cells(dims))
    if not rotate:
        target[-1] = source[-1]
    return LatticeTransform.between(dims, source, target)


near = st.tuples(st.floats(-3.5, 3.5), st.floats(-3.5, 3.5), st.floats(-8, 8)).map(np.array)


@settings(max_examples=80, deadline=None)
@given(transforms(rotate=False), cells(DIMS3))
def test_translation_is_the_paper_shift(f: LatticeTransform, c: np.ndarray) -> None:
    """Δθ = 0: f(c) = (c + Δ) mod n exactly (Eq. 11 with the corrected sign)."""
    expected = wrap_coords(c + f.offset, DIMS3)
    assert float(np.max(wrapped_delta(f.apply(c), expected, DIMS3))) < 1e-9


@settings(max_examples=80, deadline=None)
@given(transforms(), cells(DIMS3), st.lists(st.integers(-3, 3), min_size=3, max_size=3))
def test_wrap_around_is_invisible(f: LatticeTransform, c: np.ndarray, k: list[int]) -> None:
    """Adding whole lattice periods to a coordinate changes nothing."""
    moved = c + np.asarray(k) * np.asarray(DIMS3)
    assert float(np.max(wrapped_delta(f.apply(moved), f.apply(c), DIMS3))) < 1e-9


@settings(max_examples=80, deadline=None)
@given(transforms(), cells(DIMS3))
def test_shift_then_unshift_is_identity_near_the_anchor(f: LatticeTransform, c: np.ndarray) -> None:
    """Inverse: exact for translations everywhere, for rotations within half the lattice of the anchor."""
    delta = signed_delta(c, f.source, DIMS3)
    if f.heading_cells != 0.0 and float(np.hypot(delta[0], delta[1])) >= (DIMS3[0] - 1) / 2:
        return  # beyond half the lattice a rotated wrapped displacement is ambiguous (module docstring)
    back = f.inverse().apply(f.apply(c))
    assert float(np.max(wrapped_delta(back, c, DIMS3))) < 1e-7


@settings(max_examples=60, deadline=None)
@given(transforms(DIMS4, rotate=False), cells(DIMS4))
def test_4dof_translation_round_trip(f: LatticeTransform, c: np.ndarray) -> None:
    back = f.inverse().apply(f.apply(c))
    assert float(np.max(wrapped_delta(back, c, DIMS4))) < 1e-9


@settings(max_examples=60, deadline=None)
@given(transforms(rotate=False), transforms(rotate=False), cells(DIMS3))
def test_composition_of_shifts(f: LatticeTransform, g: LatticeTransform, c: np.ndarray) -> None:
    assert float(np.max(wrapped_delta(f.then(g).apply(c), g.apply(f.apply(c)), DIMS3))) < 1e-9
    assert f.then(g).offset == pytest.approx(signed_delta(f.offset + g.offset, 0.0, DIMS3), abs=1e-9)




@settings(max_examples=60, deadline=None)
@given(transforms(), near, near)
def test_rotation_keeps_lattice_distances_near_the_anchor(f: LatticeTransform, da: np.ndarray, db: np.ndarray) -> None:
    """The transform is rigid in (x, y) about the anchor: distances between nearby coordinates are preserved."""
    a = wrap_coords(np.asarray(f.source) + da, DIMS3)
    b = wrap_coords(np.asarray(f.source) + db, DIMS3)
    before = np.hypot(*(da[:2] - db[:2]))
    after = np.hypot(*signed_delta(f.apply(a), f.apply(b), DIMS3)[:2])
    assert after == pytest.approx(before, abs=1e-7)
    # and the heading difference is kept exactly
    assert signed_delta(f.apply(a), f.apply(b), DIMS3)[2] == pytest.approx(signed_delta(da[2], db[2], 36)[()])


@settings(max_examples=60, deadline=None)
@given(transforms(), st.data())
def test_composition_with_rotations_near_the_anchor(f: LatticeTransform, data: st.DataObject) -> None:
    """Composition holds where every intermediate displacement stays within half the lattice."""
    g_source = wrap_coords(np.asarray(f.target) + data.draw(near), DIMS3)
    g = LatticeTransform.between(DIMS3, g_source, data.draw(cells(DIMS3)))
    c = wrap_coords(np.asarray(f.source) + data.draw(near), DIMS3)
    assert float(np.max(wrapped_delta(f.then(g).apply(c), g.apply(f.apply(c)), DIMS3))) < 1e-7
