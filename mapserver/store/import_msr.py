"""Import the save directory of multisession-ratslam (Menezes et al. 2023; anchors §1.3) as a stored map.

The directory holds text files with one value per line (lists space-separated on one line, possibly
empty); records are read until a ``-`` line, after which come the file's "current, previous" pair:

* ``localviewcells.txt``: TEMPLATE_SIZE, then per template ``id``, ``mean``, ``data`` (TEMPLATE_SIZE
  values), then ``-``, ``current_vt``, ``prev_vt``.
* ``posecellvisual_templates.txt``: per LVC→pose-cell link ``id`` (template), ``pc_x``, ``pc_y``, ``pc_th``,
  ``decay``, ``exps[]``, then ``-``, ``current_vt``, ``prev_vt``.
* ``posecellexperiences.txt``: per experience ``x_pc``, ``y_pc``, ``th_pc``, ``vt_id``, then ``-``,
  ``current_exp``, ``prev_exp``.
* ``experiences.txt``: per experience ``id``, ``x_m``, ``y_m``, ``th_rad``, ``vt_id``, ``links_from[]``,
  ``links_to[]``, ``time_from_current_s``, ``goal_to_current``, ``current_to_goal``, then ``-``,
  ``current_exp_id``, ``prev_exp_id``.
* ``links.txt``: per link ``d``, ``heading_rad``, ``facing_rad``, ``exp_to_id``, ``exp_from_id``,
  ``delta_time_s`` (no trailer). ``goal_list.txt`` is ignored (it may be empty or absent).

The files are read as multisession-ratslam really writes them (every quirk below is in its own
repository's ``Saves/``):

* Numbers are Python ``str(float)`` or numpy ``%.18e`` text: ids may be written ``16.0`` (a save of a
  loaded map) and any value in scientific notation (``1.38777878078e-17``).
* Empty lists are empty lines (an experience without links, a template without experiences).
* Trailers differ: ``posecellvisual_templates.txt`` of a map that was loaded and saved again ends with
  the current id and an empty line where the previous id belongs (the tool's loader reads one line too
  many there and writes back the empty string). An empty or missing previous id is -1 ("none").
* A map saved before its first frame: ``localviewcells.txt`` holds TEMPLATE_SIZE, ``-``, ``0``, ``0``;
  ``experiences.txt`` and ``posecellexperiences.txt`` hold ``-``, ``0``, ``0``;
  ``posecellvisual_templates.txt`` and ``links.txt`` are empty. A save directory may even hold only empty
  files. Such maps import as empty maps; a current id that names no record (the tool's initial 0) is -1.

What the format lacks, and what the import does about it (also returned as ``notes``):

* **Pose-cell activity is not saved**: the activity is a fresh engine's single-cell packet moved to the
  cell of the current experience (``pc_best`` = that cell).
* **No stamps**: experience stamps are rebuilt from the links' Δt along the creation order (experience
  0 at 0 s; a new experience at its creator's stamp + Δt of the link that created it).
* **No link kinds**: a link that reaches an experience no earlier link reached (a newly created one) is
  ``odometry``, every other link is ``loop``.
* A link (d, heading, facing) becomes the transform (d·cos heading, d·sin heading, 0, facing) in the
  source's frame — OpenRatSLAM's link convention, which is the engine's.
* Pose-cell links get strength 1 (OpenRatSLAM links); lattice coordinates are wrapped into the lattice.
* Every other engine key (VO profiles, gate, accumulators) starts as in a fresh engine; the odometry
  accumulator's facing is the current experience's heading.

Values are checked where they are read, with the bounds of :mod:`mapserver.bounds` (the message names the file,
the line and the field): every number must be finite; poses (``x_m``, ``y_m``) and link lengths (``d``) within
``MAX_POSITION_M``, angles (``th_rad``, ``heading_rad``, ``facing_rad``) within ``MAX_ANGLE_RAD``, a link's
``delta_time_s`` between 0 and ``MAX_TIME_S`` (and the stamps rebuilt from them within it), template values and
means within ``MAX_TEMPLATE_VALUE``. Lattice coordinates only need to be finite: they are wrapped into the
lattice.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core import Engine, LinkKind, Params
from mapserver.bounds import (
    MAX_ANGLE_RAD,
    MAX_POSITION_M,
    MAX_TEMPLATE_VALUE,
    MAX_TIME_S,
    first_out_of_bounds,
    value_problem,
)
from mapserver.errors import InputError
from mapserver.names import check_map_name
from mapserver.store.db import Database
from mapserver.store.errors import MapExistsError
from mapserver.store.mapio import save_map
from mapserver.store.maps import find_map
from mapserver.store.sessions import NewSession, find_session

FORMAT = "multisession-ratslam"
FILES = (
    "localviewcells.txt",
    "posecellvisual_templates.txt",
    "posecellexperiences.txt",
    "experiences.txt",
    "links.txt",
)


Bound = tuple[float, str, float | None]
"""(largest magnitude, unit, smallest value or None) of a field: the bounds of :mod:`mapserver.bounds`."""
POSITION: Bound = (MAX_POSITION_M, "m", None)
ANGLE: Bound = (MAX_ANGLE_RAD, "rad", None)
DURATION: Bound = (MAX_TIME_S, "s", 0.0)
INTENSITY: Bound = (MAX_TEMPLATE_VALUE, "", None)


@dataclass
class ImportedMap:
    """A map read from a save directory: engine snapshot (origin tag 0), source digest and notes."""

    snapshot: dict[str, np.ndarray]
    sha256: str
    notes: list[str] = field(default_factory=list)


class _Lines:
    """Cursor over a file's lines with line-numbered errors."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            msg = f"{FORMAT} directory lacks {path.name!r}: {str(path)!r}"
            raise InputError(msg) from None
        except (OSError, UnicodeDecodeError) as err:
            msg = f"cannot read {str(path)!r}: {err}"
            raise InputError(msg) from None
        lines = text.split("\n")
        if lines and lines[-1] == "":
            lines.pop()
        self.lines = [line.strip() for line in lines]
        self.pos = 0

    def fail(self, what: str, line: int | None = None) -> InputError:
        where = self.pos if line is None else line
        return InputError(f"{self.path}:{where}: {what}")

    def at_end(self) -> bool:
        return self.pos >= len(self.lines)

    def next(self, what: str) -> str:
        if self.at_end():
            raise self.fail(f"file ends where {what} was expected", len(self.lines))
        self.pos += 1
        return self.lines[self.pos - 1]

    def number(self, what: str, bound: Bound | None = None) -> float:
        """Return the next line as a finite number, refused beyond ``bound`` (:mod:`mapserver.bounds`)."""
        raw = self.next(what)
        try:
            value = float(raw)
        except ValueError:
            raise self.fail(f"{what} is not a number: {raw!r}") from None
        if not math.isfinite(value):
            raise self.fail(f"{what} is not finite: {raw!r}")
        if bound is not None:
            problem = value_problem(value, bound[0], bound[1], minimum=bound[2])
            if problem is not None:
                raise self.fail(f"{what} {problem}")
        return value

    def integer(self, what: str) -> int:
        value = self.number(what)
        if value != int(value):
            raise self.fail(f"{what} is not an integer: {value!r}")
        return int(value)

    def numbers(self, what: str, bound: Bound | None = None) -> np.ndarray:
        """Return the next line's finite numbers, each refused beyond ``bound`` (:mod:`mapserver.bounds`)."""
        raw = self.next(what)
        try:
            values = np.array([float(v) for v in raw.split()], dtype=np.float64)
        except ValueError:
            raise self.fail(f"{what} holds a value that is not a number") from None
        if not np.all(np.isfinite(values)):
            raise self.fail(f"{what} holds a non-finite value")
        if bound is not None:
            found = first_out_of_bounds(values, bound[0], bound[1], minimum=bound[2])
            if found is not None:
                raise self.fail(f"{what}[{found[0]}] {found[1]}")
        return values

    def records_end(self) -> bool:
        """Return True (and step past it) at the ``-`` line that ends the records."""
        if not self.at_end() and self.lines[self.pos] == "-":
            self.pos += 1
            return True
        return False

    def empty(self) -> bool:
        """Return True when the file holds no records and no trailer (only blank lines, or nothing)."""
        return all(line == "" for line in self.lines)

    def trailer(self) -> tuple[int, int]:
        """Return the (current, previous) ids after ``-``; an empty or missing previous id is -1."""
        current = self.integer("the current id after '-'")
        previous = -1
        if not self.at_end() and self.lines[self.pos] != "":
            previous = self.integer("the previous id after '-'")
        elif not self.at_end():
            self.pos += 1
        if any(self.lines[self.pos :]):
            raise self.fail("unexpected lines after the current and previous ids", self.pos + 1)
        return current, previous


def _directory_digest(directory: Path) -> str:
    digest = hashlib.sha256()
    for name in FILES:
        digest.update(name.encode("utf-8") + b"\0")
        digest.update((directory / name).read_bytes())
    return digest.hexdigest()


def _templates(directory: Path, params: Params) -> tuple[np.ndarray, np.ndarray, int, int]:
    f = _Lines(directory / "localviewcells.txt")
    ty, tx = params.template_y_size, params.template_x_size
    if f.empty():
        return np.zeros((0, ty, tx), dtype=np.float32), np.zeros(0), -1, -1
    size = f.integer("TEMPLATE_SIZE")
    if size != ty * tx:
        msg = (
            f"{f.path}:1: templates have {size} values but the parameters give template_y_size × "
            f"template_x_size = {ty} × {tx} = {ty * tx}; give the parameters the map was built with "
            "(--preset or --config)"
        )
        raise InputError(msg)
    means: list[float] = []
    data: list[np.ndarray] = []
    while not f.records_end():
        ident = f.integer("template id")
        if ident != len(means):
            raise f.fail(f"template id {ident} where {len(means)} was expected (ids must run 0, 1, 2, ...)")
        means.append(f.number("template mean", INTENSITY))
        values = f.numbers("template data", INTENSITY)
        if values.shape[0] != size:
            raise f.fail(f"template {ident} has {values.shape[0]} values, expected {size}")
        data.append(values)
    current, previous = f.trailer()
    templates = np.array(data, dtype=np.float32).reshape(-1, ty, tx)
    return templates, np.array(means, dtype=np.float64), current, previous


def _pose_cell_links(directory: Path, n_templates: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    f = _Lines(directory / "posecellvisual_templates.txt")
    ids: list[int] = []
    coords: list[tuple[float, float, float]] = []
    decays: list[float] = []
    while not f.empty() and not f.records_end():
        ident = f.integer("pose-cell template id")
        if not 0 <= ident < n_templates:
            raise f.fail(f"pose-cell link names template {ident}, but there are {n_templates} templates")
        ids.append(ident)
        coords.append((f.number("pc_x"), f.number("pc_y"), f.number("pc_th")))
        decays.append(f.number("decay"))
        f.numbers("exps[]")
    current, previous = (-1, -1) if f.empty() else f.trailer()
    return (
        np.array(ids, dtype=np.int64),
        np.array(coords, dtype=np.float64).reshape(-1, 3),
        np.array(decays, dtype=np.float64),
        current,
        previous,
    )


def _pose_cell_experiences(directory: Path) -> tuple[np.ndarray, np.ndarray]:
    f = _Lines(directory / "posecellexperiences.txt")
    coords: list[tuple[float, float, float]] = []
    vts: list[int] = []
    while not f.empty() and not f.records_end():
        coords.append((f.number("x_pc"), f.number("y_pc"), f.number("th_pc")))
        vts.append(f.integer("vt_id"))
    if not f.empty():
        f.trailer()
    return np.array(coords, dtype=np.float64).reshape(-1, 3), np.array(vts, dtype=np.int64)


def _experiences(directory: Path) -> tuple[np.ndarray, np.ndarray, int, int]:
    f = _Lines(directory / "experiences.txt")
    poses: list[tuple[float, float, float]] = []
    vts: list[int] = []
    while not f.empty() and not f.records_end():
        ident = f.integer("experience id")
        if ident != len(poses):
            raise f.fail(f"experience id {ident} where {len(poses)} was expected (ids must run 0, 1, 2, ...)")
        poses.append((f.number("x_m", POSITION), f.number("y_m", POSITION), f.number("th_rad", ANGLE)))
        vts.append(f.integer("vt_id"))
        f.numbers("links_from[]")
        f.numbers("links_to[]")
        f.number("time_from_current_s")
        f.number("goal_to_current")
        f.number("current_to_goal")
    current, previous = (-1, -1) if f.empty() else f.trailer()
    return np.array(poses, dtype=np.float64).reshape(-1, 3), np.array(vts, dtype=np.int64), current, previous


def _links(directory: Path, n_experiences: int) -> np.ndarray:
    f = _Lines(directory / "links.txt")
    if len(f.lines) % 6:
        msg = f"{f.path}: {len(f.lines)} lines is not a whole number of 6-line links"
        raise InputError(msg)
    rows = []
    while not f.at_end():
        d = f.number("d", POSITION)
        heading = f.number("heading_rad", ANGLE)
        facing = f.number("facing_rad", ANGLE)
        to_id = f.integer("exp_to_id")
        from_id = f.integer("exp_from_id")
        dt = f.number("delta_time_s", DURATION)
        for ident in (to_id, from_id):
            if not 0 <= ident < n_experiences:
                raise f.fail(f"link names experience {ident}, but there are {n_experiences} experiences")
        rows.append((from_id, to_id, d, heading, facing, dt))
    return np.array(rows, dtype=np.float64).reshape(-1, 6)


@dataclass
class _Save:
    """The five files of a save directory, parsed (ids as read; -1 = none)."""

    templates: np.ndarray
    means: np.ndarray
    lv_ids: tuple[int, int]
    pc_template: np.ndarray
    pc_coords: np.ndarray
    pc_decay: np.ndarray
    pc_ids: tuple[int, int]
    exp_pc: np.ndarray
    poses: np.ndarray
    exp_vt: np.ndarray
    em_ids: tuple[int, int]
    links: np.ndarray


def _read_save(path: Path, params: Params) -> _Save:
    """Parse the five files and check that they agree with each other (ids, counts, templates)."""
    templates, means, lv_current, lv_previous = _templates(path, params)
    n_templates = templates.shape[0]
    pc_template, pc_coords, pc_decay, pc_current, pc_previous = _pose_cell_links(path, n_templates)
    exp_pc, exp_pc_vt = _pose_cell_experiences(path)
    poses, exp_vt, em_current, em_previous = _experiences(path)
    n_exp = poses.shape[0]
    if exp_pc.shape[0] != n_exp:
        msg = f"{path}: posecellexperiences.txt has {exp_pc.shape[0]} experiences, experiences.txt {n_exp}"
        raise InputError(msg)
    if not np.array_equal(exp_pc_vt, exp_vt):
        k = int(np.flatnonzero(exp_pc_vt != exp_vt)[0])
        msg = (
            f"{path}: experience {k} has template {exp_vt[k]} in experiences.txt, "
            f"{exp_pc_vt[k]} in posecellexperiences.txt"
        )
        raise InputError(msg)
    if exp_vt.size and (exp_vt.min() < 0 or exp_vt.max() >= n_templates):
        msg = f"{path}: experiences name templates outside 0..{n_templates - 1}"
        raise InputError(msg)
    if n_exp and not 0 <= em_current < n_exp:
        msg = f"{path}/experiences.txt: the current experience {em_current} is not one of 0..{n_exp - 1}"
        raise InputError(msg)
    if n_templates and not -1 <= lv_current < n_templates:
        msg = f"{path}/localviewcells.txt: the current template {lv_current} is out of range"
        raise InputError(msg)
    return _Save(
        templates=templates,
        means=means,
        lv_ids=_ids_or_none(lv_current, lv_previous, n_templates),
        pc_template=pc_template,
        pc_coords=pc_coords,
        pc_decay=pc_decay,
        pc_ids=_ids_or_none(pc_current, pc_previous, n_templates),
        exp_pc=exp_pc,
        poses=poses,
        exp_vt=exp_vt,
        em_ids=_ids_or_none(em_current, em_previous, n_exp),
        links=_links(path, n_exp),
    )


def _ids_or_none(current: int, previous: int, count: int) -> tuple[int, int]:
    """Return (current, previous) with ids that name no record (the tool's initial 0 in an empty map) as -1."""
    return (current if 0 <= current < count else -1, previous if 0 <= previous < count else -1)


def _link_kinds_and_stamps(
    src: np.ndarray, dst: np.ndarray, dt: np.ndarray, n_exp: int
) -> tuple[np.ndarray, np.ndarray]:
    """Infer link kinds (``LinkKind.ODOMETRY`` or ``LOOP``) and experience stamps from the links in file order.

    A link reaching an experience of a higher id than any earlier link reached created it (odometry), and
    that experience's stamp is its source's stamp + Δt; experience 0 is at 0 s; an experience no link
    created (the first of a merged-in session) takes the stamp of the experience before it.
    """
    kinds = np.full(src.shape[0], LinkKind.LOOP, dtype=np.int8)
    stamps = np.full(n_exp, np.nan)
    if n_exp:
        stamps[0] = 0.0
    reached = 0
    for j, (s, t) in enumerate(zip(src.tolist(), dst.tolist(), strict=True)):
        if t > reached:
            kinds[j] = LinkKind.ODOMETRY
            reached = t
            if not math.isnan(stamps[s]):
                stamps[t] = stamps[s] + dt[j]
    for k in range(1, n_exp):
        if math.isnan(stamps[k]):
            stamps[k] = stamps[k - 1]
    return kinds, stamps


def _experience_graph(save: _Save, snapshot: dict[str, Any], dims: np.ndarray) -> None:
    """Fill the experience-map keys of ``snapshot`` (poses, lattice cells, links, stamps, current ids)."""
    n_exp = save.poses.shape[0]
    pose = np.zeros((n_exp, 4))
    pose[:, 0:2] = save.poses[:, 0:2]
    pose[:, 3] = save.poses[:, 2]
    snapshot["em_pose"] = pose
    snapshot["em_pc"] = np.mod(save.exp_pc, dims)
    snapshot["em_template"] = save.exp_vt
    snapshot["em_origin"] = np.zeros(n_exp, dtype=np.int64)
    links = save.links
    src = links[:, 0].astype(np.int64)
    dst = links[:, 1].astype(np.int64)
    d, heading, facing, dt = links[:, 2], links[:, 3], links[:, 4], links[:, 5]
    kinds, stamps = _link_kinds_and_stamps(src, dst, dt, n_exp)
    transform = np.zeros((src.shape[0], 4))
    transform[:, 0] = d * np.cos(heading)
    transform[:, 1] = d * np.sin(heading)
    transform[:, 3] = facing
    snapshot["em_stamp"] = stamps
    snapshot["em_link_from"] = src
    snapshot["em_link_to"] = dst
    snapshot["em_link_transform"] = transform
    snapshot["em_link_dt"] = dt.copy()
    snapshot["em_link_distance"] = np.abs(d)
    snapshot["em_link_kind"] = kinds
    snapshot["em_current"] = np.asarray(save.em_ids[0], dtype=np.int64)
    snapshot["em_previous"] = np.asarray(save.em_ids[1], dtype=np.int64)
    snapshot["em_relax_pending"] = np.asarray(False)
    snapshot["eng_last_stamp"] = np.asarray(stamps[-1] if n_exp else math.nan, dtype=np.float64)


def _place_activity(save: _Save, snapshot: dict[str, Any], shape: tuple[int, ...]) -> str:
    """Move a fresh engine's packet to the current experience's cell; return the note saying where."""
    current = save.em_ids[0]
    note = "the pose-cell activity is not in this format: it starts from a single-cell packet"
    if current < 0:
        return note + " at the lattice centre (no current experience)"
    dims = np.asarray(shape)
    centre = dims // 2
    cell = np.floor(np.mod(save.exp_pc[current], dims) + 0.5).astype(np.int64) % dims
    activity = np.asarray(snapshot["pc_activity"])
    snapshot["pc_activity"] = np.roll(activity, tuple((cell - centre).tolist()), axis=(0, 1, 2))
    snapshot["pc_best"] = cell.astype(np.float64)
    accum = np.zeros(6)
    accum[3] = save.poses[current, 2]
    snapshot["em_accum"] = accum
    return note + f" at the current experience's cell {tuple(cell.tolist())!r}"


def read_multisession_ratslam(directory: str | Path, params: Params) -> ImportedMap:
    """Read a multisession-ratslam save directory into an engine snapshot (see the module docstring).

    Args:
        directory: the save directory (``Saves/<name>/``).
        params: the parameters the map was built with (template size, lattice).

    Returns:
        The snapshot (origin tag 0 everywhere), the SHA-256 of the five files, and notes on what the
        format lacked.

    Raises:
        InputError: missing directory or file, a malformed line (named ``file:line``), ids out of range,
            sizes that disagree with each other or with the parameters.
    """
    path = Path(directory)
    if not path.is_dir():
        msg = f"not a {FORMAT} save directory: {str(path)!r}"
        raise InputError(msg)
    shape = tuple(int(d) for d in params.lattice_shape)
    if len(shape) != 3:
        msg = f"{FORMAT} maps use an (x, y, th) lattice; the parameters give a {len(shape)}-D lattice {shape!r}"
        raise InputError(msg)
    save = _read_save(path, params)
    dims = np.asarray(shape, dtype=np.float64)
    snapshot: dict[str, Any] = Engine(params).snapshot()
    snapshot["lv_templates"] = save.templates
    snapshot["lv_means"] = save.means
    snapshot["lv_origin"] = np.zeros(save.templates.shape[0], dtype=np.int64)
    snapshot["lv_current"] = np.asarray(save.lv_ids[0], dtype=np.int64)
    snapshot["lv_previous"] = np.asarray(save.lv_ids[1], dtype=np.int64)
    snapshot["pc_link_template"] = save.pc_template
    snapshot["pc_link_coords"] = np.mod(save.pc_coords, dims)
    snapshot["pc_link_strength"] = np.ones(save.pc_template.shape[0])
    snapshot["pc_link_decay"] = save.pc_decay
    snapshot["pc_current_vt"] = np.asarray(save.pc_ids[0], dtype=np.int64)
    snapshot["pc_prev_vt"] = np.asarray(save.pc_ids[1], dtype=np.int64)
    _experience_graph(save, snapshot, dims)
    late = first_out_of_bounds(snapshot["em_stamp"], MAX_TIME_S, "s")
    if late is not None:
        msg = f"{path}/links.txt: the links' delta_time_s add up to a stamp of experience {late[0]} that {late[1]}"
        raise InputError(msg)
    notes = [
        _place_activity(save, snapshot, shape),
        "experience stamps are rebuilt from the links' delta_time_s (the format stores none)",
        "link kinds are inferred: a link reaching a new experience is odometry, others are loops",
    ]
    snapshot = {k: np.asarray(v) for k, v in snapshot.items()}
    return ImportedMap(snapshot=snapshot, sha256=_directory_digest(path), notes=notes)


@dataclass(frozen=True)
class ImportResult:
    """The contract's ``import --json`` object plus notes."""

    map: str
    templates: int
    experiences: int
    links: int
    notes: tuple[str, ...]

    def summary(self) -> dict[str, Any]:
        """Return ``{"map", "templates", "experiences", "links", "notes"}``."""
        return {
            "map": self.map,
            "templates": self.templates,
            "experiences": self.experiences,
            "links": self.links,
            "notes": list(self.notes),
        }


def import_multisession_ratslam(
    db: Database, *, directory: str | Path, map_name: str, params: Params, settle: bool = False
) -> ImportResult:
    """Store a multisession-ratslam save directory as a new map with one session, in one transaction.

    The map keeps the poses the tool saved, unless ``settle`` moves it to the fixed point of relaxation over
    its links first (with the robust check, as a finished session's map is).

    Raises:
        InputError: the directory is malformed (see :func:`read_multisession_ratslam`) or was imported
            already, or the map name breaks the rule (:func:`mapserver.names.check_map_name`) or is taken.
    """
    check_map_name(map_name)
    imported = read_multisession_ratslam(directory, params)
    path = Path(directory)
    snap = imported.snapshot
    if settle and snap["em_pose"].shape[0]:
        engine = Engine.restore(params, snap)
        engine.settle()
        snap = engine.snapshot()
    with db.read() as conn:
        if find_map(conn=conn, name=map_name) is not None:
            msg = f"a map named {map_name!r} already exists; choose another map name"
            raise InputError(msg)
        previous = find_session(conn=conn, log_sha256=imported.sha256, topics={"format": FORMAT})
    if previous is not None:
        msg = f"{str(path)!r} was imported already as session {previous.name!r}"
        raise InputError(msg)
    session = NewSession(
        name=map_name,
        log_name=path.resolve().name,
        log_sha256=imported.sha256,
        topics={"format": FORMAT},
        params=params.to_dict(),
        status="complete",
        frames_processed=0,
        source=FORMAT,
        first_stamp=float(snap["em_stamp"][0]) if snap["em_stamp"].size else None,
        last_stamp=float(snap["em_stamp"][-1]) if snap["em_stamp"].size else None,
    )
    try:
        save_map(db, name=map_name, params=params, snapshot=snap, sessions=[session])
    except MapExistsError as err:
        raise InputError(str(err)) from err
    return ImportResult(
        map=map_name,
        templates=int(snap["lv_templates"].shape[0]),
        experiences=int(snap["em_pose"].shape[0]),
        links=int(snap["em_link_from"].shape[0]),
        notes=tuple(imported.notes),
    )
