"""Robust relaxation: find the loop links inconsistent with the rest of the graph and switch them off.

Model: switchable constraints (Sünderhauf & Protzel, "Switchable Constraints for Robust Pose
Graph SLAM", IROS 2012) with binary switches: every loop and merge link l carries a switch
s_l ∈ {0, 1}, and so does every manual link; odometry links are never switched. The switches minimise the
truncated least squares (TLS) cost of Yang, Antonante, Tzoumas & Carlone ("Graduated
Non-Convexity for Robust Spatial Perception", RA-L 2020, Eq. 2 with the TLS loss)

    C(s) = γ·Σ_odometry z_l² + Σ_switchable min(z_l², c̄²),

with the poses at the relaxation's least-squares fixed point over the links switched on
(:func:`core.relaxation.solve`), so a link over the threshold costs a constant and stops
pulling. γ = 1/4 (``ODOMETRY_WEIGHT``, chosen on the ``loop`` and ``cave3d`` simulations):
with γ = 1 a true closure of a long cycle costs the whole cycle's spread misclosure, more than
c̄², and switching it off looks cheaper (measured: ``cave3d`` loses its closure to the first
experience); with γ = 0 the odometry no longer resists a bend and false links that bend it
are kept (``loop``, 20 wrong links). It is minimised by greedy descent (:func:`switch_off_outliers`) rather than by
GNC's continuation: on long odometry chains GNC's convex start down-weights every loop
link at once, the loop opens and true closures are rejected with the false ones (measured
on the ``loop`` simulation). Greedy: switch off the link with the largest normalised
residual while it exceeds c̄, re-solving each time (a false link's error also shows,
smaller, on its true neighbours, so one link at a time). False links that agree with one another (a
look-alike place closed several times) bend the graph until none exceeds c̄; so the descent also starts
from the odometry alone with the switchable links that fit it switched on, and keeps the cheaper of the
two starts (measured: session 2 of ``symmetric``, five false closures 19–30 m long, none above c̄ in
the bent map; C 92 with them, 35 with none). Then it tries each strained loop or merge link off (``z >
c̄/2``, largest first, kept off when C falls): a wrong link within the map's own closure error bends its
neighbours until none exceeds c̄ (``cave3d``, a link 0.85 m off at z 3.25: C 53.1 with it, 43.7 without;
bench/robust_relaxation.py rows within 1.25× of the clean APE: 24 → 26 of 30). Then it tries to switch each
switched-off link back on, kept on while the elimination re-runs from there, and keep the
change when it lowers C: a switched-off link comes back on when later evidence makes it consistent,
and a true closure removed early is swapped back for the false link it was mistaken for. When the
first descent switched anything off, a third start is tried the same way: the largest set of pairwise
consistent links of Pairwise Consistency Maximisation (Mangelson et al., ICRA 2018; :mod:`core.pcm`),
with the others off, then switched back on one by one. It replaces the answer only when its C is lower
by more than c̄² (one outlier's worth). Wrong links that outnumber the true closures near them bend the
all-links solution until several fit it, and the descent from there keeps them; a true closure agrees
with the true closures near it along the route, a random wrong one does not. But false closures of a
self-aliased place agree with one another too (a corridor that matches itself shifted), and there the
clique holds them: accepted at any lower C, the clique start bent merged ``twin-overlap`` maps (APE
ratio 1.81 → 6.39 at 40 m seed 5, C lower by 4.5-6.6; 2.11 → 16.86 with turns at 20 m seed 7, where the
descent had found no outlier) while fixing ``symmetric-overlap`` seed 8 (2.01 → 0.99, C lower by 38).
The margin keeps the last and neither of the first. A fourth start: the status quo — the switches the
map stood on at its previous check, with the links added since off, then switched back on one by one
(``loop`` map seed 3: five wrong links of 2 m beside a lap closure that is itself 1.8 m off; from all
links on, the descent kept two of them and switched both true closures off at a cost of 117.9-121.6,
where the map as it stood costs 82.4). It replaces the answer at any lower C: the map as it stood is an
answer the map already held, and new links have to earn their place against it. It is tried whenever the answer
switches off a link the map stood on, not only after a first descent that switched something off: the
strain pass below trades too (merged ``twin-overlap`` map seed 3, one wrong link of 2 m, injection seed 3: with it
and the stored closure 139 → 86 both on nothing exceeds c̄, C 46.1; the strain pass switched the closure off for it,
C 37.4; the map as it stood costs 21.1; APE 1.40× the clean map's, now 1.00×). A merge link that was on
costs the answer one more outlier's worth to switch off (``MERGE_LINK_HOLD``): it joined two maps after
the merge passed its probation, and TLS charges any link off at c̄² whatever it is, so a batch of new links could
buy its way in by switching off as many merge links as it adds, for a few tenths of an outlier's worth of
residual (merged ``symmetric`` map, 20 wrong links of 5 m, injection seed 1: 3 kept on for 2 merge links and a
loop closure off, C 223.8 against 233.8 as the map stood, c̄² = 10.4; APE 3.2× the clean map's). A prior on
those switches at their previous values (Sünderhauf & Protzel's switch prior, here one outlier's worth each). It
is a term of C itself, ``MERGE_LINK_HOLD``·c̄² for each merge link that was on as the map stood and is
off, so every start weighs it, not only the comparison between the starts' answers: the status quo's own start traded
a merge link for a wrong link that, switched back on alone, lowered C with the merge link off for it (merged
``twin-overlap`` map seed 3, 20 wrong links of 5 m, injection seed 7: 2 → 104 on for 108 → 0; APE 1.72×, now 1.00×).
The loop links a finished session left on carry the same prior (``STORED_LINK_HOLD``; stored: the links the map held
when it was restored or last settled, :meth:`core.experience_map.ExperienceMap.settle`): a link that contradicts one
costs it one outlier's worth more than the trade TLS otherwise sees as even (same map, 5 wrong links of 5 m, seed 5:
90 → 138 on for the closure 139 → 86; APE 1.49×, now 1.00×). A running session's own links carry none, so its later
closures still correct its earlier ones at once (the same prior on those delayed them: the online sweeps' single
routes got worse, ``twin-overlap`` turns alike 40 m seed 4 0.825 → 1.249 m).
New links that only fit together hold the same against them (``NEW_LINK_HOLD``): the status quo's start
switches each new link back on alone and keeps it when the cost falls, so a new link the answer keeps on and the
status quo left off lowers the cost only with others beside it — two or more wrong links that agree with one
another (neighbouring pairs of a batch of injected links join neighbouring places with the same error) and bend
the map between them until each fits within c̄. Each such link costs the answer one outlier's worth against the
map as it stood, the prior of a switch that was off (merged ``twin-overlap`` map seed 3, 5 wrong links of 2 m,
injection seed 5: two neighbouring ones, 82 → 133 and 81 → 132, kept on at C 61.7 against 69.1 as the map stood,
c̄² = 16; APE 1.73× the clean map's, now 1.00×). A new link that lowers the cost alone is kept as before, so a
true closure that fits the map is not held back; true closures of a new lap that bend the map only together are
delayed until they outweigh one outlier's worth each. Not in the check that settles a new merge: the closures an
offline merge adds with it (``mapserver.merge.offline_evidence.OfflineEvidence.closures``) are view matches its
evidence walk found where the alignment puts them, and held there, true ones stayed off with no later check to
bring them back (offline ``twin-overlap`` 40 m with turns, seeds 3 and 8: merged APE 0.45 → 0.51 m, 0.68 → 0.77 m).
(With the clique's margin instead of any lower C, the injected-link bench's ``cave3d`` maps of seeds 1 and 4 kept
wrong links at a C 0.7-15.2 above the status quo's, APE up to 3.6× the clean map's; without the joint least squares
of merged maps, taking it at any lower C bent a merged ``twin-overlap`` map, 1.47 → 6.54 m. Measured:
docs/journal.md, "every start of the robust search gets its own budget".)

Normalisation (the threshold rule). Odometry drifts by about ``drift`` metres and
``yaw_drift`` radians per metre travelled. Least squares spreads a cycle's misclosure
evenly over its links (unit weights), so a consistent link's residual is about the drift
of one link length, whatever the cycle's length: with ``s`` the map's median odometry
link length,

    z_l = √( (‖r_xyz‖ / (drift·s))² + (r_ψ / (yaw_drift·s))² ),

and a link is an outlier when ``z_l > c̄`` (``exp_robust_threshold``, 4 by default: 3 switched off a true link of the
two-session ``cave3d`` map, largest z 3.48; drift
0.1 m/m and 0.1 rad/m). The same ``z`` gives the map's health figure: the RMS of ``z``
over the active links (0.5 on the simulator's clean ``loop`` map).

Two things the TLS cost cannot see (measured on session 2 of ``symmetric`` seed 0, a point-symmetric
world: alone 12.05 m APE, 2.62 m now, 2.92 m for the log's odometry):

- *Folds.* RatSLAM relocalises on a loop closure: the robot continues from the matched experience, and
  the next experience it creates is linked by odometry to that one. A false closure then carries the
  false place on through odometry links, which were never switchable: switching the closure off left the
  fold. So the engine keeps, for each experience created after a relocalisation, its reckoning link (the
  robot's own odometry from the experience it created before: :meth:`core.experience_map.ExperienceMap.
  _record_reckoning`); here the odometry link the relocalisation made is switchable, and its reckoning
  link is on standby (``standby``): on exactly when that link is off. Left out while the relocalisation
  stands, a reckoning link that the map misses by more than its own length counts as two outliers
  (:meth:`_Problem.overreached`), so keeping such a relocalisation costs more than undoing it.
- *Folds agree with themselves.* A mirror world folded onto itself bends every link a little (TLS cost 96
  with the fold, 128 with its eight links off). But each false closure contradicts the odometry of the
  route between its own ends: the one-link cycle test of :func:`core.pcm.single_consistency` against the
  dead reckoning (odometry and standby links, no fold) flags it, and flagged links are switched off
  whatever the cost (:func:`contradicts_odometry`) (``UNARY_THRESHOLD`` has the measured figures). Over a
  long cycle the odometry's heading bias shrinks a mirror closure's turn (π + b·S) until it passes for
  drift, so the turn is also tested with the bias the map's long cycles show taken out
  (:func:`core.pcm.heading_bias`).
- *Folds across sessions.* Links whose ends the odometry does not join (a session joined to the map
  only by merge links) are tested along the merge links, by the heading their cycle turns only: a merge
  turns a map by a few degrees, a place that looks like its mirror image turns it by about π
  (``symmetric`` seeds 0 and 8 merged: 13.15 and 13.73 m APE before, 0.39 and 0.55 m after;
  ``BRIDGED_TURN`` has the measured figures).
- *Wrong links across the sessions of a stored map that turn it no more than a merge does.* Their heading passes,
  and bending the long path between their ends through the merge links may cost less than an outlier's worth, so
  the TLS cost keeps them. Each such link is also weighed against the stored map as it stood (the links a finished
  session left, on at the previous check, solved) over the shortest path between its ends through that map: the
  translation part of the unary test with that path in place of the odometry's (:func:`contradicts_the_map`,
  :func:`core.pcm.map_consistency`). Measured at the robust checks of the online sweeps (``symmetric`` seeds 0-9,
  ``twin-overlap`` with turns alike 20 m seeds 0-9 and 40 m 0-1), links between sessions: true ones (ends
  < 3 m apart in the world) 0-0.36 where the map they were weighed against held the sessions truly; false ones 2.6
  and over where a path joined their ends. But a running session's own map can be wrong, and the truth then
  contradicts it (3.3 and 4.1 against a false merge on probation; a true lap closure refuted against a
  relocalisation along a look-alike corridor, straight ``twin-overlap`` 20 m seed 7, APE 0.83 → 7.80 m), so only
  links between experiences the stored map joins are weighed. Refuted links count as outliers found, so the
  search's other starts are tried (``bench/robust_merged.py --seeds 10``: merged ``twin-overlap`` map, 20 wrong
  links of 5 m, 1.83 → 1.00).

Headings are dead-reckoned along a spanning forest of the never-switched links
(:func:`chain_headings`) and the relaxation's heading windings are taken from them, so a
false link that bent the current map cannot change how many turns a cycle makes. A
switched-off link never disconnects the graph (:func:`keep_connected`). An odometry link a check
switched off stays switchable (:meth:`core.experience_map.ExperienceMap.check_links`), and costs within
``TIE`` of each other are a tie: a link that fits comes back on at a tie if nothing else goes off for it,
and at a tie the map as it stood wins (two merge links, either of which alone joins a session without
strain, cost the same; rounding noise chose between them). Everything is deterministic (no random numbers
outside the test hook :func:`false_loop_links`).

Scoring. Each set of switches the search tries is scored without a factorisation of its own
(:meth:`_Problem.state`): :class:`core.relaxation.SwitchedRelaxation` updates one factorisation by the links
that differ (Sherman–Morrison–Woodbury) and solves the graph's 2-core only (the trees hanging from it fit
exactly), each run of odometry links between two closures as one link, and each run's ``z`` is taken once for its
links (:meth:`_Problem.state`). From ``COMPILED_FROM`` links of the 2-core on, a state is scored in one compiled call
(:class:`core._switched_kernel.CompiledScoring`: the update, the residuals, ``z`` and the cost; on the ``light`` log
a check scores up to 1,200 states, and their Python calls were most of its time). Its residuals agree with the full
solve's (:func:`core.relaxation.solve`) to rounding, about 3e-9 of ``z`` (up to 2.5e-7 on the ``matching`` log).
Where rounding could make the choice — two ``z`` that the search orders within ``ROUNDING`` of each other (links in
series through experiences with two links carry the same ``z`` exactly, and the full solve's rounding has always
ordered them), a ``z`` at a threshold, two costs at the edge of a comparison — that state is solved in full, so the
search makes the full solve's choices, state by state; the answer is solved in full too.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

if TYPE_CHECKING:
    from core.config import Params

from core._switched_kernel import CompiledScoring, ScoreTerms
from core.arrays import BoolArray, IntArray
from core.links import SWITCHABLE_KINDS, LinkKind
from core.pcm import (
    MAX_LINKS,
    PAIR_THRESHOLD,
    UNARY_THRESHOLD,
    TreePaths,
    greedy_clique,
    heading_consistency,
    map_consistency,
    pair_consistency,
    single_consistency,
    turn_allowance,
)
from core.relaxation import (
    COMPILED_FROM,
    LinkComponents,
    SwitchedRelaxation,
    length_weights,
    refine_jointly,
    residuals,
    roots,
    solve,
    sums_to_root,
)

MERGE_KIND = LinkKind.MERGE
#: γ, the weight of the never-switched links' terms in the TLS cost (module docstring)
ODOMETRY_WEIGHT = 0.25
#: outliers' worth (c̄² each) by which the status-quo start must beat the answer to replace it (module docstring)
STATUS_QUO_MARGIN = 0.0
#: outliers' worth the TLS cost adds for each merge link that was on as the map stood and is off: their switch prior
#: (module docstring)
MERGE_LINK_HOLD = 1.0
#: outliers' worth the status quo holds for each link added since the previous check that is on in the answer and
#: that the status quo's own switch-back-on left off (module docstring)
NEW_LINK_HOLD = 1.0
#: outliers' worth the TLS cost adds for each loop link of a finished session (stored) that was on as the map stood
#: and is off: their switch prior (module docstring)
STORED_LINK_HOLD = 1.0
#: Costs this close (relative) are a tie: at 1e-9 a wrong bridge won on rounding noise (offline merge of
#: ``symmetric`` seed 4: 18.76023303 against 18.76023308); at 1e-7 a test's wrong links stayed on
#: (``test_the_joint_scoring_switches_wrong_links_off_where_ratslams_does``).
TIE = 1e-8
#: Relative gap within which two ``z`` values, a ``z`` and a threshold, or two costs about to be compared are decided
#: on the full solve (:meth:`_Problem.exact`) rather than the low-rank one: the two agree to about 3e-9 (``z``) and
#: 2e-11 (costs) relative on the bench's maps, and links in series along experiences with two links carry the same
#: ``z`` exactly, so that rounding decides which of them the full solve puts first.
ROUNDING = 1e-6
#: The same for costs (relative to the larger): 50 times the gap measured, a tenth of ``TIE``
COST_ROUNDING = 1e-9


@dataclass(frozen=True, slots=True)
class Drift:
    """The expected odometry drift that normalises link residuals (see the module docstring)."""

    drift: float  # metres per metre travelled
    yaw_drift: float  # radians per metre travelled
    threshold: float  # c̄ of the truncated quadratic, in normalised units
    view_m: float = 0.0  # a view link's own position uncertainty (m): a view match places the robot this near
    view_rad: float = 0.0  # and this near in heading (rad)

    @property
    def heading_weight(self) -> float:
        """Return the weight of a radian of heading against a metre of position (``drift / yaw_drift``)."""
        return self.drift / self.yaw_drift

    @classmethod
    def of(cls, params: Params) -> Drift:
        """Return the drift that ``params`` expect (``exp_robust_*``).

        With ``exp_robust_view`` a view link (loop or merge) also carries the uncertainty of the view match that
        made it: a closure is made when the packet lies within ``exp_delta_pc_threshold`` cells of the matched
        experience, so the robot stood within that gate, not at the place — half of it,
        ``exp_delta_pc_threshold·pc_cell_x_size/2`` metres; a forward view matches over ``±vt_shift_match``
        columns of ``camera_fov_deg/template_x_size`` degrees with no heading offset — half that span; a
        panorama's match gives the heading to half a step of ``vt_step_match`` columns.
        """
        view_m = view_rad = 0.0
        if params.exp_robust_view:
            view_m = params.exp_delta_pc_threshold * params.pc_cell_x_size / 2.0
            column = 2.0 * math.pi / params.template_x_size
            if params.vt_panoramic:
                view_rad = params.vt_step_match * column / 2.0
            else:
                shift = min(params.vt_shift_match, (params.template_x_size - 1) // 2)  # the matcher's own bound
                view_rad = shift * math.radians(params.camera_fov_deg) / params.template_x_size / 2.0
        return cls(params.exp_robust_drift, params.exp_robust_yaw_drift, params.exp_robust_threshold, view_m, view_rad)


@dataclass(frozen=True, slots=True)
class RobustResult:
    """The outcome of one robust check over a link graph."""

    active: np.ndarray  # (K,) bool: links that stay on
    weight: np.ndarray  # (K,) the switches as weights: 1 on, 0 off
    z: np.ndarray  # (K,) normalised residuals at the robust solution
    iterations: int  # solves run (1 when every link was consistent at once)
    pose: np.ndarray  # (E, 4) relaxed poses over the active links


def switchable(kind: np.ndarray) -> np.ndarray:
    """Return a mask (K,) of the links that may be switched off (loop closures and merges, never odometry)."""
    return np.isin(np.asarray(kind), SWITCHABLE_KINDS)


def link_length(distance: np.ndarray, kind: np.ndarray) -> float:
    """Return ``s``: the median odometry link length (m), else the median positive link length, else 1 m."""
    distance = np.asarray(distance, dtype=np.float64)
    odometry = distance[(np.asarray(kind) == LinkKind.ODOMETRY) & (distance > 0)]
    if odometry.size:
        return float(np.median(odometry))
    positive = distance[distance > 0]
    return float(np.median(positive)) if positive.size else 1.0


def normalised_residuals(
    pose: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
    length: float,
    drift: Drift,
    view: np.ndarray | None = None,
) -> np.ndarray:
    """Return ``z_l`` (K,): each link's residual divided by the drift expected over one link length.

    ``view`` (K,) marks the view links (loop and merge links), whose expected error adds the view match's own
    (``drift.view_m``, ``drift.view_rad``) in quadrature.
    """
    res = residuals(pose, src, dst, transform)
    return _normalise(np.sqrt(np.einsum("ij,ij->i", res[:, :3], res[:, :3])), res[:, 3], length, drift, view)


def _normalise(
    distance: np.ndarray, turn: np.ndarray, length: float, drift: Drift, view: np.ndarray | None = None
) -> np.ndarray:
    """Return ``z_l`` from each link's translation residual (m) and heading residual (rad) (module docstring).

    A view link (``view``) expects ``√((drift·s)² + view_m²)`` metres and ``√((yaw_drift·s)² + view_rad²)``
    radians: a view match says the robot stood near the matched place, within the closure gate, not at it.
    """
    scale_t, scale_y = _scales(length, drift, view)
    return np.hypot(distance / scale_t, turn / scale_y)


def _scales(
    length: float, drift: Drift, view: np.ndarray | None = None
) -> tuple[float, float] | tuple[np.ndarray, np.ndarray]:
    """Return the translation (m) and heading (rad) residuals one link is expected to carry: ``z``'s denominators.

    Two numbers, or per link where ``view`` marks view links and the view match has an uncertainty of its own
    (:func:`_normalise`).
    """
    scale_t = max(drift.drift * length, 1e-12)
    scale_y = max(drift.yaw_drift * length, 1e-12)
    if view is None or not (drift.view_m > 0.0 or drift.view_rad > 0.0):
        return scale_t, scale_y
    return (np.where(view, math.hypot(scale_t, drift.view_m), scale_t),
            np.where(view, math.hypot(scale_y, drift.view_rad), scale_y))  # fmt: skip


def switch_off_outliers(
    pose: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
    kind: np.ndarray,
    distance: np.ndarray,
    anchor: np.ndarray,
    drift: Drift,
    max_solves: int = 400,
    standby: np.ndarray | None = None,
    also_switchable: np.ndarray | None = None,
    standby_closure: np.ndarray | None = None,
    joint: bool = False,
    previous: np.ndarray | None = None,
    standing: np.ndarray | None = None,
    stored: np.ndarray | None = None,
) -> RobustResult:
    """Return which links stay on: binary switches minimising the TLS cost (module docstring).

    ``standby`` (M,): the last M links are on standby, each on exactly when the link it names is
    off (an odometry link's replacement: :meth:`core.experience_map.ExperienceMap.check_links`);
    ``also_switchable`` marks links that are switchable whatever their kind (a mask over the first
    links). Standby links are not switchable and do not count in the link length ``s``.
    ``standby_closure`` (M,): per standby link, the loop link that began its relocalisation (−1: none);
    the standby link is also on while that link is off. ``joint`` (``exp_relax_joint``): the residuals are
    taken at the joint least squares over positions and headings (:func:`core.relaxation.refine_jointly`)
    instead of RatSLAM's fixed point, where a loop whose closures carry heading errors misses in position by
    that error times its lever arm and a true closure of a long cycle can cost more than an outlier.
    ``previous`` (a mask over the first links): the switches the map stood on before this check, with the
    links added since off — the status quo, a start of its own (:func:`_search`). ``standing`` (a mask over
    the first links): which links are on as the map stands (:func:`chain_headings` walks those first); those on in
    ``standing`` and off in ``previous`` are the links added since, each held by ``NEW_LINK_HOLD`` (:func:`_hold`).
    ``stored`` (a mask over the first links): the links a finished session left (the map's links when it was
    restored or last settled); those of them that are loop links on as the map stood carry ``STORED_LINK_HOLD``
    in the cost when off, as the merge links that stood carry ``MERGE_LINK_HOLD``.

    ``pose`` gives the anchors' poses and the experiences' positions to start from; the
    decision depends on the links only. When every switchable link is within ``c̄`` of the
    plain least-squares solution, nothing is switched off after one solve. Each start of the
    search (:func:`_search`: the first descent with its polish, the pairwise clique, the status
    quo) runs at most ``max_solves`` relaxation solves, so at most three times that in all. One
    budget shared by the three was reached: on the merged ``cave3d`` map with 20 wrong links of
    1 m, polishing the first two starts took all 400 solves and the status quo, the answer, was
    never tried (APE 4.4× the clean map's).
    """
    k = src.size
    partner = np.zeros(0, np.int64) if standby is None else np.asarray(standby, dtype=np.int64)
    real = k - partner.size
    can = switchable(kind)
    if also_switchable is not None:
        can[: np.size(also_switchable)] |= np.asarray(also_switchable, dtype=bool)
    start = pose.copy()
    length = link_length(np.asarray(distance)[:real], np.asarray(kind)[:real])
    off = None if standing is None else ~np.r_[np.asarray(standing, dtype=bool), np.ones(k - np.size(standing), bool)]
    start[:, 3] = chain_headings(pose[:, 3], src, dst, transform, can, anchor, off)
    gated = contradicts_odometry(start, src, dst, transform, np.asarray(distance, dtype=np.float64), can, length, drift,
                                 bridge=np.asarray(kind) == MERGE_KIND)  # fmt: skip
    refuted = np.zeros(k, dtype=bool)
    if previous is not None and stored is not None:
        held = np.zeros(k, dtype=bool)  # the stored map as it stood: links a finished session left, on then
        m = min(np.size(previous), np.size(stored))
        held[:m] = np.asarray(previous, dtype=bool)[:m] & np.asarray(stored, dtype=bool)[:m]
        refuted = contradicts_the_map(start, (src, dst, transform, np.asarray(distance, dtype=np.float64)), can,
                                      can & ~gated & ~held, held, length, drift)  # fmt: skip
        gated |= refuted
    problem = _Problem(start, src, dst, transform, can & ~gated, anchor, length, drift, max_solves)
    problem.standby, problem.gated, problem.refuted = (np.arange(real, k), partner), gated, refuted
    problem.standby_scale = length / np.maximum(length, np.asarray(distance, dtype=np.float64)[real:])
    if standby_closure is not None:
        problem.standby_closure = np.asarray(standby_closure, dtype=np.int64)
    problem.joint = joint
    if joint:  # only the joint least squares weighs links by the odometry they span
        problem.weight = length_weights(np.asarray(distance, dtype=np.float64), length)
    problem.closures = problem.can & switchable(kind)  # not a relocalisation's odometry link
    problem.merge = np.asarray(kind) == MERGE_KIND
    problem.view = switchable(kind)  # loop and merge links: a view match's uncertainty in their z
    status_quo = None
    if previous is not None:
        status_quo = np.ones(k, dtype=bool)
        status_quo[: np.size(previous)] = np.asarray(previous, dtype=bool)
        if standing is not None:  # the links added since the previous check: on as the map stands, off in previous
            problem.new[: np.size(previous)] = np.asarray(standing, dtype=bool) & ~np.asarray(previous, dtype=bool)
        problem.prior = _switch_prior(problem, status_quo, stored)
    best = _search(problem, problem.eliminate(np.ones(k, dtype=bool)), distance, status_quo)
    return RobustResult(best.active, best.active.astype(np.float64), best.z, problem.solves, best.pose)


def contradicts_odometry(
    start: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
    distance: np.ndarray,
    can: np.ndarray,
    length: float,
    drift: Drift,
    bridge: np.ndarray | None = None,
) -> np.ndarray:
    """Return a mask (K,) of switchable links whose own cycle with the odometry fails (pcm.single_consistency).

    The odometry is every never-switched link (standby reckoning links included, so a
    relocalisation's fold is not part of it), dead-reckoned from ``start``. Flagged:
    ``z > UNARY_THRESHOLD``. A link whose ends the odometry does not join (sessions joined only by
    merge or loop links) is tested along the merge links ``bridge`` too, but by its heading only
    (:func:`core.pcm.heading_consistency`): along a merge link the cycle's translation carries the
    merge's own error times a lever arm, which flagged true closures of ``twin-overlap`` (z up to 2.4,
    docs/journal.md, "folds"), while a merge turns the map by a few degrees at most, and a look-alike place
    seen the other way round turns it by about π. Flagged there: ``|E_ψ| > BRIDGED_TURN +
    BRIDGED_TURN_DRIFT·L``.
    """
    out = np.zeros(src.size, dtype=bool)
    links = np.flatnonzero(can)
    if links.size == 0:
        return out
    graph = (src, dst, transform, distance)
    dead_reckoned, paths = _dead_reckoning(start, graph, ~can)
    z = single_consistency(dead_reckoned, (src[links], dst[links], transform[links]), paths,
                           (length, drift.drift, drift.yaw_drift))  # fmt: skip
    out[links[np.isfinite(z) & (z > UNARY_THRESHOLD)]] = True
    across = links[~np.isfinite(z)]
    if bridge is None or across.size == 0 or not np.any(bridge):
        return out
    dead_reckoned, paths = _dead_reckoning(start, graph, ~can | bridge)
    turn, travelled = heading_consistency(dead_reckoned, (src[across], dst[across], transform[across]), paths)
    out[across] = np.isfinite(travelled) & (np.abs(turn) > turn_allowance(travelled))
    return out


def contradicts_the_map(
    start: np.ndarray,
    graph: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    can: np.ndarray,
    tested: np.ndarray,
    held: np.ndarray,
    length: float,
    drift: Drift,
) -> np.ndarray:
    """Return a mask (K,) of the ``tested`` links that the stored map as it stood contradicts.

    ``held``: the links the stored map stood on (a finished session's links, on at the previous check). They are
    solved from ``start`` and each tested link whose ends the never-switched links (``~can``) do not join (sessions
    joined by merge links, which :func:`contradicts_odometry` tests by their heading alone) is weighed against that
    map over the shortest path between its ends through it (:func:`core.pcm.map_consistency`); flagged above
    ``UNARY_THRESHOLD``. A link with an end the stored map does not hold (the running session's) has no such path
    and is left to the other tests: a running session's map can itself be wrong, and the truth then contradicts it
    (a true lap closure of the straight ``twin-overlap`` 20 m, seed 7, against a relocalisation along the look-alike
    corridor, and true closures against a false merge on probation in ``symmetric`` seeds 7 and 8, were refuted by
    the map as it stood when the running session's links were part of it: APE 0.83 → 7.80 m).

    Why: a wrong link between two sessions of a stored map that turns the map no more than a merge does bends it
    cheaply where the path between its ends is long, and passes the TLS cost (merged ``twin-overlap`` map seed 3,
    20 wrong links of 5 m, injection seed 6: 79 → 127 on at z 0.5 for 2.8 of the cost's 16 per outlier, then
    77 → 115 with a relocalisation's odometry link traded for it; APE 1.83× the clean map's).
    """
    src, dst, transform, distance = graph
    out = np.zeros(src.size, dtype=bool)
    if not tested.any() or not held.any():
        return out
    n = start.shape[0]
    fixed = np.flatnonzero(~can)
    labels = connected_components(sp.csr_matrix((np.ones(fixed.size), (src[fixed], dst[fixed])), shape=(n, n)),
                                  directed=False)[1]  # fmt: skip
    on = np.flatnonzero(held)
    stored_part = connected_components(sp.csr_matrix((np.ones(on.size), (src[on], dst[on])), shape=(n, n)),
                                       directed=False)[1]  # fmt: skip
    # only ends the stored map joins have a path to weigh against: the others (the running session's) cost no solve
    links = np.flatnonzero(tested & (labels[src] != labels[dst]) & (stored_part[src] == stored_part[dst]))
    if links.size == 0:
        return out
    pose = solve(start, src[on], dst[on], transform[on], component_anchors(n, src[on], dst[on]), passes=1)
    z = map_consistency(pose, (src[links], dst[links], transform[links]), (src[on], dst[on], distance[on]),
                        (length, drift.drift))  # fmt: skip
    out[links[z > UNARY_THRESHOLD]] = True
    return out


def _dead_reckoning(
    start: np.ndarray, graph: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tree: np.ndarray
) -> tuple[np.ndarray, TreePaths]:
    """Return the poses dead-reckoned from ``start`` along the links ``tree`` (a mask), and its path lengths."""
    src, dst, transform, distance = graph
    n, tree = start.shape[0], np.flatnonzero(tree)
    anchors = component_anchors(n, src[tree], dst[tree])
    dead_reckoned = solve(start, src[tree], dst[tree], transform[tree], anchors, passes=1)
    return dead_reckoned, TreePaths(n, src[tree], dst[tree], distance[tree], anchors)


def _switch_prior(problem: _Problem, status_quo: np.ndarray, stored: np.ndarray | None) -> np.ndarray:
    """Return each link's switch prior (K,), in outliers' worth, charged by the cost when the link is off.

    ``MERGE_LINK_HOLD`` for a merge link on as the map stood, ``STORED_LINK_HOLD`` for a loop link on as the map
    stood that a finished session left (``stored``); nothing for the links added since the previous check.
    """
    k = problem.src.size
    was = np.zeros(k, dtype=bool)
    if stored is not None:
        was[: np.size(stored)] = np.asarray(stored, dtype=bool)
    stood = status_quo & ~problem.new
    loops = problem.closures & ~problem.merge & was & ~problem.gated
    return MERGE_LINK_HOLD * (problem.merge & stood) + STORED_LINK_HOLD * (loops & stood)


def _search(problem: _Problem, best: _State, distance: np.ndarray, status_quo: np.ndarray | None = None) -> _State:
    """Return the cheapest switches found from the first descent ``best`` and the other starts (module docstring).

    Two more starts are tried, each switched back on link by link: when the first descent switched anything
    off, the greedy clique of pairwise-consistent links (:func:`_pairwise_start`), taken only when its cost
    is lower by more than ``c̄²`` (one outlier's worth); and when the first descent switched anything off or the
    answer switches off a link the map stood on (the strain pass may trade one), the status quo — the switches the
    map stood on at its previous check, the links added since off (``status_quo``) — taken when its cost is lower by
    more than ``STATUS_QUO_MARGIN`` outliers' worth (0: at any lower cost), or at the same cost (:func:`_tie`),
    or by no more than what it holds against the answer (:func:`_hold`: the new links the answer keeps on that
    the status quo, trying each alone, left off; the merge links it switched off are in the cost). A batch of new
    links that outnumbers the closures the map already holds bends the all-links solution, and the descent
    from there can keep the batch and switch the old closures off although the map as it stood, with the
    batch off, costs less (``loop`` map seed 3, five wrong links of 2 m, injection seeds 1-3: found
    117.9-121.6, status quo 82.4; the two wrong links kept sit beside the true lap closure, 2.9 m off where
    it is 1.8 m off, so the greedy clique prefers them too). Each start has its own budget of solves
    (:meth:`_Problem.fresh_budget`), so a long polish of one cannot keep the next from being tried.
    """
    fixed = ~problem.can & ~problem.gated  # never switched: odometry and the standby reckoning links
    first_active = best.active
    strained = float(best.z[fixed & best.active].max(initial=0.0)) > 0.5 * problem.drift.threshold
    strained = strained or problem.overreached(best.active, best.z) > 0
    # outliers found: by the descent, or new links the map as it stood refuted (the others may fit only beside them)
    descended = not first_active[problem.can].all() or bool(problem.refuted.any())
    if problem.can.any() and (strained or descended):
        bare_active = problem.couple(problem.keep_connected(fixed, best.z, best), best.z, best)  # bridges stay on
        bare = problem.state(bare_active)
        # Links that agree with one another bend the graph until none of them stands out (a look-alike place
        # closed again and again): start also from the odometry alone, with the switchable links that fit it on.
        if strained:
            fits = problem.eliminate(problem.keep_connected(fixed | (bare.z <= problem.drift.threshold), bare.z, bare))
            if _better(fits, best):
                best = fits
    best = problem.switch_back_on(problem.switch_off_strained(best))
    margin = problem.drift.threshold**2  # one outlier's worth
    # Wrong links that outnumber the true ones near them: start also from a pairwise-consistent set where the descent
    # found outliers (docstring; ``descended`` implies ``bare`` was solved above), and from the status quo where it
    # did or where the answer switches off a link the map stood on.
    if descended:
        problem.fresh_budget()
        clique = _pairwise_start(problem, bare, bare_active, distance)
        if clique is not None:
            clique = problem.switch_back_on(clique)
            if _better(clique, best, margin):
                best = clique
    if status_quo is not None and (descended or bool((problem.can & status_quo & ~best.active).any())):
        problem.fresh_budget()
        kept = _status_quo_start(problem, status_quo)
        if kept is not None and _holds(kept, best, _hold(problem, kept, best) * margin):
            best = kept
    return problem.exact(best)


def _hold(problem: _Problem, status_quo: _State, best: _State) -> float:
    """Return the outliers' worth by which the map as it stood may cost more than ``best`` and still stand.

    ``NEW_LINK_HOLD`` for each link added since the previous check that ``best`` keeps on and the status quo
    left off (its switch-back-on tried each alone and none lowered the cost: they fit only together), less
    ``STATUS_QUO_MARGIN`` (module docstring). Not for the links of a check that holds a new merge link: that
    check settles the merge, and the closures that came with it were weighed by the merge's own evidence.
    """
    joined = 0
    if not (problem.new & problem.merge).any():
        joined = int(np.count_nonzero(problem.new & best.active & ~status_quo.active))
    return NEW_LINK_HOLD * joined - STATUS_QUO_MARGIN


def _status_quo_start(problem: _Problem, status_quo: np.ndarray) -> _State | None:
    """Return the status quo (the previous check's switches, new links off) eliminated and switched back on."""
    if problem.solves >= problem.limit:
        return None
    # links added since the last check may be all that joins a component (a merge's links): those stay on, the
    # ones that fit the map as it stood first (not the descent's answer, which may have bent the map round another)
    z_then = normalised_residuals(problem.start, problem.src, problem.dst, problem.transform, problem.length,
                                  problem.drift, problem.view)  # fmt: skip
    whole = problem.keep_connected(status_quo, z_then)
    return problem.switch_back_on(problem.eliminate(whole))


def _pairwise_start(problem: _Problem, bare: _State, bare_active: np.ndarray, distance: np.ndarray) -> _State | None:
    """Return the elimination started from the greedy clique of pairwise-consistent links (:mod:`core.pcm`)."""
    links = np.flatnonzero(problem.can & ~bare_active)
    if links.size < 2 or links.size > MAX_LINKS or problem.solves >= problem.limit:
        return None
    n = problem.start.shape[0]
    on = np.flatnonzero(bare_active)
    paths = TreePaths(n, problem.src[on], problem.dst[on], np.asarray(distance, dtype=np.float64)[on], problem.anchor)
    z = pair_consistency(bare.pose, problem.src[links], problem.dst[links], problem.transform[links], paths,
                         problem.length, problem.drift.drift, problem.drift.yaw_drift)  # fmt: skip
    active = bare_active.copy()
    active[links[greedy_clique(z <= PAIR_THRESHOLD)]] = True
    return problem.eliminate(active)


def _better(trial: _State, best: _State, margin: float = 0.0) -> bool:
    """Return whether ``trial`` has the lower TLS cost (by more than ``margin``, and more than a tie: :func:`_tie`)."""
    trial, best = _settled(trial, best, lambda t, b: t.cost - b.cost + max(margin, TIE * max(1.0, b.cost)))
    return trial.cost < best.cost - max(margin, TIE * max(1.0, best.cost))


def _close(values: np.ndarray) -> bool:
    """Return whether two of ``values`` are within rounding of each other (``ROUNDING``, relative)."""
    if values.size < 2:
        return False
    ordered = np.sort(values)
    return bool(np.any(np.diff(ordered) <= ROUNDING * np.maximum(1.0, np.abs(ordered[1:]))))


def _settled(trial: _State, best: _State, gap: Callable[[_State, _State], float]) -> tuple[_State, _State]:
    """Return the two states, solved in full (:meth:`_Problem.exact`) where ``gap`` is within rounding of 0."""
    if (trial.solved is None or best.solved is None) and abs(gap(trial, best)) <= COST_ROUNDING * max(
        1.0, abs(trial.cost), abs(best.cost)
    ):
        return trial.problem.exact(trial), best.problem.exact(best)
    return trial, best


def _holds(status_quo: _State, best: _State, hold: float) -> bool:
    """Return whether the map as it stood keeps its switches: ``best`` not cheaper by more than ``hold`` (or a tie).

    A negative ``hold``: the status quo must itself be cheaper by more than −``hold``.
    """
    status_quo, best = _settled(status_quo, best, lambda q, b: q.cost - b.cost - hold)
    return status_quo.cost <= best.cost + hold or _tie(status_quo, best)


def _tie(trial: _State, best: _State) -> bool:
    """Return whether ``trial`` costs what ``best`` costs (to ``TIE``, relative).

    E.g. two links, either of which alone joins a part that then hangs on it without strain: the graph
    cannot tell them apart, the map as it stood can.
    """
    trial, best = _settled(trial, best, lambda t, b: abs(t.cost - b.cost) - TIE * max(1.0, b.cost))
    return abs(trial.cost - best.cost) <= TIE * max(1.0, best.cost)


@dataclass(frozen=True, slots=True)
class _State:
    """One set of switches scored: the links on, their ``z``, the TLS cost, and the poses when solved in full."""

    active: np.ndarray
    z: np.ndarray
    cost: float
    problem: _Problem
    solved: np.ndarray | None = None  # the poses, where the state was solved in full (:meth:`_Problem.exact`)

    @property
    def pose(self) -> np.ndarray:
        """Return the poses at the fixed point over ``active`` (:func:`core.relaxation.solve`, solved on demand)."""
        return self.solved if self.solved is not None else self.problem.exact(self).pose


class _Problem:
    """One robust check's fixed data, and the greedy elimination over it."""

    def __init__(
        self,
        start: np.ndarray,
        src: np.ndarray,
        dst: np.ndarray,
        transform: np.ndarray,
        can: np.ndarray,
        anchor: np.ndarray,
        length: float,
        drift: Drift,
        max_solves: int,
    ) -> None:
        self.start, self.src, self.dst, self.transform = start, src, dst, transform
        self.can, self.anchor, self.length, self.drift = can, anchor, length, drift
        self.budget = max_solves  # solves allowed per start (:meth:`fresh_budget`)
        self.limit = max_solves  # the current start's last solve
        self.solves = 0
        self.standby: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        self.gated = np.zeros(src.size, dtype=bool)  # off whatever the cost: contradicts_odometry, contradicts_the_map
        self.refuted = np.zeros(src.size, dtype=bool)  # of those, the ones the map as it stood contradicts
        self.closures = can  # loop and merge links: those :meth:`switch_off_strained` tries
        self.new = np.zeros(src.size, dtype=bool)  # links added since the previous check: NEW_LINK_HOLD each
        self.merge = np.zeros(src.size, dtype=bool)  # merge links
        self.prior = np.zeros(src.size)  # outliers' worth each link costs when off: its switch prior (_switch_prior)
        self.standby_scale = np.ones(0)  # s / max(s, L) of each standby link: its z over its own length
        self.weight = np.ones(0)  # each link's weight in the joint least squares (length_weights)
        self.standby_closure = np.zeros(0, np.int64)  # the loop link that began each one's relocalisation, or −1
        self.joint = False  # score on the joint least squares (exp_relax_joint), not RatSLAM's fixed point
        self.view = np.zeros(src.size, dtype=bool)  # loop and merge links (Drift.view_m, view_rad)
        self._solver: tuple[LinkComponents, SwitchedRelaxation, np.ndarray, np.ndarray] | None = None  # on first use
        self._can = np.zeros(0, np.int64)  # the switchable links
        self._core = (np.zeros(0, np.int64), np.zeros(0, bool))  # the 2-core's links, and which may be switched
        self._held = np.zeros(0, np.int64)  # the links with a switch prior
        self._held_prior = np.zeros(0)  # and their priors
        # the 2-core's never-switched links, their runs, and the runs of its switchable ones (:meth:`_core_cost`)
        self._core_runs = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
        self._run_view: np.ndarray | None = None  # per run of the 2-core: view links (None: a run mixes them)
        self._scorer: CompiledScoring | None = None  # a state's score in one compiled call (:meth:`_compiled`)
        self._exact: dict[bytes, _State] = {}  # states solved in full, by their switches

    def fresh_budget(self) -> None:
        """Give the next start of the search its own ``max_solves`` solves."""
        self.limit = self.solves + self.budget

    def couple(
        self, active: np.ndarray, z: np.ndarray | None = None, scored: _State | None = None, near: _State | None = None
    ) -> np.ndarray:
        """Return ``active`` with gated links off and each standby link on when its partner is off.

        A standby link is also on when the loop link that began its relocalisation is off: the robot
        may have relocalised twice between the two experiences it created (a false closure, then a true
        one), and then the partner stands while nothing else joins the experience it left (``symmetric``
        seed 1: 117 closed falsely onto 23, the robot relocalised onto 69 and made 118 from there; 21 m of
        session 2 hung from one end).

        Then the links that keep every component whole are turned back on (:func:`keep_connected`,
        in increasing ``z``; ``scored``: the state ``z`` is of, and ``near`` the state ``active`` comes from, if not
        that one: :meth:`keep_connected`).
        """
        links, partner = self.standby
        gated, began = self._prepared()[2:]
        if not links.size and not gated.size:
            return active
        active = active.copy()
        active[gated] = False
        on = ~active[partner]
        if began.size:
            on[began] |= ~active[self.standby_closure[began]]
        active[links] = on
        return self.keep_connected(active, np.zeros(active.size) if z is None else z, scored, near)

    def keep_connected(
        self, active: np.ndarray, z: np.ndarray, scored: _State | None = None, near: _State | None = None
    ) -> np.ndarray:
        """Return :func:`keep_connected` of ``active`` over this graph (Kruskal only where a part is split).

        Off links whose ends ``active`` already joins are never turned on, so Kruskal's loop runs over the others
        alone (in the same order), and a set that joins every part (:meth:`core.relaxation.LinkComponents.whole`)
        is returned as it is without one. ``scored``: the state ``z`` is of, solved in full (:meth:`exact`) where
        two of the links the loop orders are within rounding of each other. ``near`` (default ``scored``): a state
        ``active`` was made from; when that one joins every part and ``active`` lacks at most one of its links,
        on a cycle there, ``active`` joins every part too (:meth:`core.relaxation.LinkComponents.whole`).
        """
        parts = self._prepared()[0]
        near = scored if near is None else near
        if parts.whole(active, None if near is None or self.joint else (near.active, near.z)):
            return active.copy()
        labels = parts.labels(active)
        if labels is None:
            return keep_connected(self.start.shape[0], self.src, self.dst, active, z)
        part = labels[parts.node]
        a, b = part[self.src], part[self.dst]
        out = active.copy()
        joins = np.flatnonzero(~active & (a != b))
        if scored is not None and _close(z[joins]):
            z = self.exact(scored).z
        parent = np.arange(int(labels.max()) + 1)
        for link in joins[np.argsort(z[joins], kind="stable")].tolist():
            ra, rb = _find(parent, int(a[link])), _find(parent, int(b[link]))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
                out[link] = True
        parts.remember(out)
        return out

    def state(self, active: np.ndarray) -> _State:
        """Score the relaxation's fixed point over ``active`` (windings from the start headings).

        The residuals come from :class:`core.relaxation.SwitchedRelaxation` (low-rank updates of one
        factorisation, the 2-core's links only; the others' are 0) where it applies: RatSLAM's fixed point
        (not ``joint``) and a set of switches that keeps every part whole; otherwise from a full solve
        (:meth:`exact`). The two agree to rounding (about 1e-10 m on the bench's maps). On large graphs the state
        is scored, ``z`` and cost, by one compiled call (:meth:`_compiled`), the same steps to rounding.
        """
        self.solves += 1
        switched = None if self.joint else self._prepared()[1]
        scored = None if self._scorer is None else self._scorer.score(active)
        if scored is not None:
            z, cost, near = scored
            return self.exact(_State(active, z, 0.0, self)) if near else _State(active, z, cost, self)
        found = None if switched is None else switched.run_residuals(active)
        if switched is None or found is None:
            return self.exact(_State(active, np.zeros(0), 0.0, self))
        z = np.zeros(self.src.size)
        if self._run_view is None:  # a run mixes view links and others: each link its own z
            runs = None
            core = _normalise(found[0][switched.run], found[1][switched.run], self.length, self.drift,
                              self.view[switched.links])  # fmt: skip
        else:  # every link of a run takes the run's z (hypot is even in the heading's sign)
            runs = _normalise(*found, self.length, self.drift, self._run_view)
            core = runs[switched.run]
        z[switched.links] = core
        links, _ = self.standby
        off = ~active[links]
        if self._at_threshold(core if runs is None else runs, z[links[off]] * self.standby_scale[off]):
            return self.exact(_State(active, z, 0.0, self))
        return _State(active, z, self._core_cost(active, z, core, runs), self)

    def _at_threshold(self, core: np.ndarray, own: np.ndarray) -> bool:
        """Return whether a ``z`` lies within rounding of a threshold the search compares it with.

        ``c̄`` (outliers) and ``c̄/2`` (strain) for the 2-core's ``z`` (``core``; the others' are 0), and the reach
        of a standby link left out (``own``, :meth:`overreached`).
        """
        c = self.drift.threshold
        reach = 1.0 / self.drift.drift
        return bool(np.any(np.abs(np.abs(core - 0.75 * c) - 0.25 * c) <= ROUNDING * max(1.0, c))
                    or (own.size and np.any(np.abs(own - reach) <= ROUNDING * max(1.0, reach))))  # fmt: skip

    def _core_cost(self, active: np.ndarray, z: np.ndarray, core: np.ndarray, runs: np.ndarray | None = None) -> float:
        """Return :meth:`cost` where only the 2-core's links (``z`` ``core``) have a residual.

        ``runs``: the runs' ``z`` where each link takes its run's (squared per run, the same squares).
        """
        links, can = self._core
        c2 = self.drift.threshold**2
        if runs is None:
            square = core * core
            cost = float(ODOMETRY_WEIGHT * np.sum(square[~can & active[links]]) + np.sum(np.minimum(square[can], c2)))
        else:  # the same squares in the same order, gathered from the runs'
            fixed_links, fixed_runs, can_runs = self._core_runs
            square = runs * runs
            on = active[fixed_links]
            fixed = square[fixed_runs] if on.all() else square[fixed_runs[on]]
            cost = float(ODOMETRY_WEIGHT * np.sum(fixed) + np.sum(np.minimum(square[can_runs], c2)))
        cost += c2 * float(np.sum(self._held_prior[~active[self._held]]))
        return cost + 2.0 * c2 * self.overreached(active, z)

    def decided(self, state: _State, links: np.ndarray, top: bool = False) -> _State:
        """Return ``state``, solved in full (:meth:`exact`) where two of ``links``' ``z`` are within rounding.

        The search orders ``links`` by ``z`` (``top``: takes the largest only); the full solve's rounding is the
        order the check has always taken where they tie.
        """
        if state.solved is not None or links.size < 2:
            return state
        z = state.z[links]
        if top:
            z = np.partition(z, links.size - 2)[-2:]
        return self.exact(state) if _close(z) else state

    def exact(self, state: _State) -> _State:
        """Return ``state`` solved in full (:func:`core.relaxation.solve`, and the joint refinement if ``joint``)."""
        if state.solved is not None:
            return state
        key = state.active.tobytes()
        if key in self._exact:
            return self._exact[key]
        if len(self._exact) >= 16:
            self._exact.clear()
        self._exact[key] = solved = self._solve(state.active)
        return solved

    def _solve(self, active: np.ndarray) -> _State:
        """Return the state over ``active`` from a full solve (as :meth:`state` before its low-rank form)."""
        on = np.flatnonzero(active)
        graph = (self.src[on], self.dst[on], self.transform[on])
        pose = solve(self.start, *graph, self.anchor, passes=1)
        scored = pose
        if self.joint:
            scored = refine_jointly(pose, *graph, self.anchor, heading_weight=self.drift.heading_weight,
                                    weight=self.weight[on])  # fmt: skip
        z = normalised_residuals(scored, self.src, self.dst, self.transform, self.length, self.drift, self.view)
        return _State(active, z, self.cost(active, z), self, pose)

    def cost(self, active: np.ndarray, z: np.ndarray) -> float:
        """Return the TLS cost C of the switches ``active`` with residuals ``z`` (module docstring)."""
        c2 = self.drift.threshold**2
        fixed = ~self.can & active  # standby links count while they stand in
        cost = float(ODOMETRY_WEIGHT * np.sum(z[fixed] ** 2) + np.sum(np.minimum(z[self.can] ** 2, c2)))
        cost += c2 * float(np.sum(self.prior[~active]))  # the switch priors of the links that stood
        return cost + 2.0 * c2 * self.overreached(active, z)

    def _prepared(self) -> tuple[LinkComponents, SwitchedRelaxation, np.ndarray, np.ndarray]:
        """Return the search's fixed structures, built once: parts, solver, gated links, standby links begun.

        The graph's parts over the links the search may switch (:class:`core.relaxation.LinkComponents`), the
        low-rank solver, the gated links, and the standby links whose relocalisation a loop link began.
        """
        if self._solver is None:
            changing = self.can | self.gated
            changing[self.standby[0]] = True
            parts = LinkComponents(self.start.shape[0], self.src, self.dst, ~changing)
            switched = SwitchedRelaxation(self.start, self.src, self.dst, self.transform, self.anchor, parts)
            began = np.flatnonzero(self.standby_closure >= 0) if self.standby_closure.size else np.zeros(0, np.int64)
            self._solver = (parts, switched, np.flatnonzero(self.gated), began)
            self._core = switched.links, self.can[switched.links]
            self._held = np.flatnonzero(self.prior)
            self._held_prior = self.prior[self._held]
            self._can = np.flatnonzero(self.can)
            fixed = np.flatnonzero(~self._core[1])
            self._core_runs = (switched.links[fixed], switched.run[fixed], switched.run[self._core[1]])
            view = self.view[switched.links]
            self._run_view = np.zeros(switched.length.size, dtype=bool)
            self._run_view[switched.run] = view
            if not np.array_equal(self._run_view[switched.run], view):
                self._run_view = None
            self._scorer = self._compiled(switched)
        return self._solver

    def _compiled(self, switched: SwitchedRelaxation) -> CompiledScoring | None:
        """Return the compiled scoring of states (:class:`core._switched_kernel.CompiledScoring`) where it applies.

        From ``COMPILED_FROM`` links of the 2-core on (below, numba's import and the kernel's load outweigh what it
        saves), on RatSLAM's fixed point (not ``joint``), where every link of a run is a view link or none is.
        """
        if self.joint or self._run_view is None or switched.links.size < COMPILED_FROM:
            return None
        runs = switched.length.size
        scale = np.empty((2, runs))
        scale[0], scale[1] = _scales(self.length, self.drift, self._run_view)
        fixed_links, fixed_runs, can_runs = self._core_runs
        terms = ScoreTerms(scale, np.stack([fixed_links, fixed_runs]), can_runs, self._held, self._held_prior,
                           self.standby[0], self.standby_scale, self.drift.threshold, 1.0 / self.drift.drift,
                           ROUNDING, ODOMETRY_WEIGHT)  # fmt: skip
        return CompiledScoring(switched, terms, self.src.size)

    def overreached(self, active: np.ndarray, z: np.ndarray) -> int:
        """Return how many reckoning links left on standby miss the map by more than their own length.

        A relocalisation's odometry link says the robot went on from the experience it matched; its
        reckoning link, the robot's own odometry from the experience it created before, stands by. Left
        out while its partner stands, it costs nothing, however far the relocalisation put the robot; so a
        false relocalisation and a link that contradicts it cost one outlier each, a tie broken by the
        descent's order (``twin-overlap`` 40 m seed 6: 11 → 13 claims 0.5 m where the truth is 3.6 m, the
        reckoning link says 2.17 m). Here a reckoning link left out whose residual exceeds its own length
        ``L`` (``z_own = z·s/max(s, L) > 1/d``: the relocalisation put the robot further from where its
        odometry says than it drove) costs two outliers, ``2·c̄²``: the odometry it contradicts is never
        switched off, so in a one-against-one contest with a view match (the contradicting loop link gated
        off already) the robot's own odometry wins. Below that it counts nothing: a run of relocalisations
        0.7-1 m off their 1.4-5 m reckoning links, counted as odometry (``γ·z_own²``) or as outliers at any
        size, outvoted a true lap closure of the same scenario's single route (APE 1.30 → 9.91 m).
        """
        links, _ = self.standby
        off = ~active[links]
        own = z[links[off]] * self.standby_scale[off]
        return int(np.count_nonzero(own > 1.0 / self.drift.drift))

    def switch_off_strained(self, best: _State) -> _State:
        """Try each strained loop or merge link off (``z > c̄/2``, elimination re-run); keep what lowers the cost.

        A wrong link within the map's own closure error bends its neighbours until no residual
        exceeds ``c̄`` (``cave3d``: a link 0.85 m off, z 3.25), so the descent never tries it; the
        TLS cost still falls when it goes (53.1 → 43.7 there). A relocalisation's odometry link is
        not tried: off, its reckoning link stands in, the robot's odometry over what may be tens of
        metres (``twin-overlap`` 40 m seed 5: a 0.64 m link for a 28 m one, merged APE 0.95 → 1.71 m).
        """
        improved = True
        while improved and self.solves < self.limit:
            improved = False
            strained = np.flatnonzero(best.active & self.closures & (best.z > 0.5 * self.drift.threshold))
            best = self.decided(best, strained)
            for link in strained[np.argsort(-best.z[strained], kind="stable")].tolist():
                if self.solves >= self.limit:
                    break
                trial_active = best.active.copy()
                trial_active[link] = False
                trial = self.eliminate(trial_active, near=best)
                if _better(trial, best):
                    best, improved = trial, True
                    break
        return best

    def switch_back_on(self, best: _State) -> _State:
        """Try each switched-off link back on (elimination re-run from there); keep what lowers the cost."""
        improved = True
        while improved and self.solves < self.limit:
            improved = False
            off = np.flatnonzero(~best.active & self.can)
            best = self.decided(best, off)
            for link in off[np.argsort(best.z[off], kind="stable")].tolist():
                if best.active[link] or self.solves >= self.limit:
                    continue
                trial_active = best.active.copy()
                trial_active[link] = True
                trial = self.eliminate(trial_active, keep_on=link, near=best)
                # a link that fits as the map stands comes back on at no cost, if nothing else goes off for it
                if _better(trial, best) or (_tie(trial, best) and not (best.active & ~trial.active).any()):
                    best, improved = trial, True
        return best

    def eliminate(self, active: np.ndarray, keep_on: int = -1, near: _State | None = None) -> _State:
        """Switch off the worst active switchable link while one exceeds ``c̄`` (never a bridge nor ``keep_on``).

        ``near``: the state ``active`` differs from by a link (:meth:`keep_connected`'s shortcut).
        """
        current = self.state(self.couple(active, near=near))
        while self.solves < self.limit:
            can = self._can
            candidates = can[current.active[can] & (current.z[can] > self.drift.threshold) & (can != keep_on)]
            if not candidates.size:
                break
            current = self.decided(current, candidates, top=True)
            trial = current.active.copy()
            trial[candidates[np.argmax(current.z[candidates])]] = False
            trial = self.couple(trial, current.z, current)
            trial = self.keep_connected(trial, current.z, current)
            if np.array_equal(trial, current.active):  # only bridges exceed the threshold
                break
            current = self.state(trial)
        return current


def chain_headings(
    yaw: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
    avoid: np.ndarray,
    anchor: np.ndarray,
    off: np.ndarray | None = None,
) -> np.ndarray:
    """Return unwrapped headings dead-reckoned from each anchor along a spanning forest of the links.

    The forest prefers links not in ``avoid`` (odometry), so the headings are those the
    odometry measured, however a false loop link has bent the current map; the
    relaxation's heading windings (turns of 2π around each cycle) are then taken from
    them (:func:`core.relaxation.solve` with ``passes=1``). Experiences not reached
    (no links) keep ``yaw``; anchors keep theirs. Among avoided links those switched ``off`` (K,)
    as the map stands come last: by link order alone the forest took a merge link the map had
    switched off, where only merge links join two sessions, and turned a whole session by 3.6 rad
    (``symmetric`` seed 4, offline merge). (Ordering avoided links by their residual in the map as
    it stands instead fixed that too, but moved the start of every merged map's check, and two
    ``symmetric-overlap`` merged maps got worse, 0.46 → 0.91 m and 0.76 → 1.08 m.)
    """
    n = yaw.size
    out = yaw.astype(np.float64).copy()
    k = src.size
    if k == 0:
        return out
    # unique costs (odometry, then avoided links on, then those off; each in link order) make the forest deterministic
    tier = np.asarray(avoid, dtype=np.int64)
    if off is not None:
        tier += np.asarray(avoid, dtype=bool) & np.asarray(off, dtype=bool)
    cost = (tier * (k + 1) + np.arange(1, k + 1)).astype(np.float64)
    lookup = np.full(3 * k + 3, -1, dtype=np.int64)
    lookup[cost.astype(np.int64)] = np.arange(k, dtype=np.int64)
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    # two links between one pair (a loop link beside a standby one) would add their costs: keep the cheaper
    order = np.lexsort((cost, hi, lo))
    first = np.r_[True, (lo[order][1:] != lo[order][:-1]) | (hi[order][1:] != hi[order][:-1])]
    pick = order[first]
    forest = minimum_spanning_tree(sp.csr_matrix((cost[pick], (lo[pick], hi[pick])), shape=(n, n))).tocoo()
    link = lookup[np.round(forest.data).astype(np.int64)]
    rows = np.concatenate([forest.row, forest.col])
    cols = np.concatenate([forest.col, forest.row])
    which = sp.csr_matrix((np.tile(link + 1, 2), (rows, cols)), shape=(n, n))
    parent = np.arange(n)
    degree = np.bincount(np.concatenate([src, dst]), minlength=n)
    for root in np.flatnonzero(anchor & (degree > 0)).tolist():
        visit, pred = breadth_first_order(which, root, directed=False, return_predecessors=True)
        parent[visit[1:]] = pred[visit[1:]]
    child = np.flatnonzero(parent != np.arange(n))
    delta = np.zeros(n)
    used = np.asarray(which[parent[child], child]).ravel().astype(np.int64) - 1
    delta[child] = np.where(src[used] == parent[child], transform[used, 3], -transform[used, 3])
    total, root_of = sums_to_root(parent, delta)  # heading = anchor heading + Σ of the steps up the tree
    out[child] = out[root_of[child]] + total[child]
    return out


def keep_connected(n: int, src: np.ndarray, dst: np.ndarray, active: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Return ``active`` with switched-off links turned back on where needed to keep every component whole.

    Kruskal's rule over the switched-off links in increasing ``z``: a link whose ends lie
    in different components of the active graph is turned back on (a bridge has no
    redundancy, so nothing can contradict it).
    """
    active = active.copy()
    off = np.flatnonzero(~active)
    if off.size == 0:
        return active
    on = np.flatnonzero(active)
    graph = sp.csr_matrix((np.ones(on.size), (src[on], dst[on])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    parent = np.arange(int(labels.max()) + 1 if n else 0)
    for link in off[np.argsort(z[off], kind="stable")].tolist():
        a, b = _find(parent, int(labels[src[link]])), _find(parent, int(labels[dst[link]]))
        if a != b:
            parent[max(a, b)] = min(a, b)
            active[link] = True
    return active


def _find(parent: np.ndarray, node: int) -> int:
    while parent[node] != node:
        parent[node] = parent[parent[node]]
        node = int(parent[node])
    return node


def health(
    pose: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
    kind: np.ndarray,
    distance: np.ndarray,
    active: np.ndarray,
    drift: Drift,
) -> dict[str, float | int]:
    """Return a map's health: RMS and largest ``z`` over its active links, links switched off, and links.

    ``residual`` (RMS) ≈ 0.5 on the simulator's clean ``loop`` map, 1.2 on ``cave3d``; ``worst``
    above ``drift.threshold`` means some active link contradicts the rest (both 0.0 for a
    map without links). ``unmeasured``: active links whose ``z`` is not finite (a stored link transform
    or pose holding an infinity), left out of both figures so that the figure stays a number JSON can
    carry (PostgreSQL's JSON refuses ``Infinity``); 0 for any map the engine made.
    """
    src = np.asarray(src, dtype=np.int64)
    active = np.asarray(active, dtype=bool)
    on = np.flatnonzero(active)
    residual = worst = 0.0
    unmeasured = 0
    if on.size:
        length = link_length(distance, kind)
        with np.errstate(invalid="ignore", over="ignore"):  # ∞ − ∞ in a stored transform: unmeasured, below
            z = normalised_residuals(pose, src[on], np.asarray(dst)[on], np.asarray(transform)[on], length, drift,
                                     switchable(np.asarray(kind)[on]))  # fmt: skip
        finite = z[np.isfinite(z)]
        unmeasured = int(z.size - finite.size)
        if finite.size:
            residual, worst = float(np.sqrt(np.mean(finite * finite))), float(finite.max())
    return {"residual": residual, "worst": worst, "switched_off": int(src.size - on.size), "links": int(src.size),
            "unmeasured": unmeasured}  # fmt: skip


def false_loop_links(
    pose: np.ndarray, count: int, separation: float, seed: int, jitter: float = 0.2, min_gap: int = 5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``count`` wrong loop links (src, dst, transform (count, 4)): a test hook.

    Each joins two experiences whose current poses lie between ``separation`` and
    ``1.5·separation`` apart (about ``separation`` metres of error; small is the hard
    case) and at least ``min_gap`` ids apart (not trajectory neighbours, which odometry
    links already join), with the transform a true loop closure would carry — the target a few
    centimetres to ``jitter`` metres from the source, heading change within ±0.2 rad —
    so the link looks plausible on its own. Pairs are drawn with a seeded generator
    (deterministic); fewer are returned when fewer pairs qualify.
    """
    rng = np.random.default_rng(seed)
    n = pose.shape[0]
    xyz = pose[:, :3]
    gap = np.sqrt(((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(axis=2))
    i, j = np.nonzero(np.triu((gap >= separation) & (gap <= 1.5 * separation), k=min_gap))
    if i.size == 0 or count <= 0 or n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4))
    pick = rng.choice(i.size, size=min(count, i.size), replace=False)
    src, dst = i[pick].astype(np.int64), j[pick].astype(np.int64)
    angle = rng.uniform(-math.pi, math.pi, src.size)
    reach = rng.uniform(0.0, jitter, src.size)
    transform = np.zeros((src.size, 4))
    transform[:, 0] = reach * np.cos(angle)
    transform[:, 1] = reach * np.sin(angle)
    transform[:, 3] = rng.uniform(-0.2, 0.2, src.size)
    return src, dst, transform


def component_anchors(n: int, src: IntArray, dst: IntArray) -> BoolArray:
    """Return a mask (n,) of each connected component's lowest-id experience (the relaxation anchors)."""
    parent = np.arange(n, dtype=np.int64)
    if src.size:
        graph = sp.csr_matrix((np.ones(src.size), (src, dst)), shape=(n, n))
        _, labels = connected_components(graph, directed=False)
        first = np.full(int(labels.max()) + 1, n, dtype=np.int64)
        np.minimum.at(first, labels, np.arange(n, dtype=np.int64))
        parent = first[labels]
    return cast(BoolArray, roots(parent) == np.arange(n))
