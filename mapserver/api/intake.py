"""From a received upload to a checked mission log in the upload directory, ready to be queued.

A ``.bag``/``.db3``/``.mcap`` file is kept as it is; a ``.zip``/``.tar`` archive is unpacked safely
(:mod:`mapserver.api.archives`) and must hold one ROS 2 bag directory (``metadata.yaml``) or one log
file. The log is then opened with :func:`mapserver.ingest.open_log` — the check ``process`` makes — and
read through once (:meth:`~mapserver.ingest.MissionLog.verify`: every mapped topic as long as its index
says, the odometry within its bounds), so a file that is not a bag, a truncated or damaged bag, a log
without a usable camera topic or with unusable odometry is refused with 400 and the reason, and a first
frame over the pixel limit with 413, before any job exists.
"""

from __future__ import annotations

import json
import logging
import secrets
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mapserver.api.archives import ARCHIVE_SUFFIXES, ArchiveLimits, archive_suffix, extract_archive
from mapserver.api.uploads import ReceivedUpload
from mapserver.errors import InputError, LimitError
from mapserver.ingest import LOG_SUFFIXES, LogIdentity, open_log, parse_topics_arg
from mapserver.names import check_map_name, default_map_name
from mapserver.params import DEFAULT_PRESET, require_storable, resolve_params

logger = logging.getLogger(__name__)

KNOWN_FIELDS = ("preset", "map", "into", "topics", "merge")


@dataclass(frozen=True, slots=True)
class UploadOptions:
    """The form fields of an upload, checked.

    Attributes:
        preset: engine preset (default ``circle``).
        map_name: name for a new map, None for the default (the log's name).
        topics: topic overrides (``image``, ``odometry``, ``ground_truth``), or None.
        merge: merge the session into stored maps it connects to (``process`` without ``--no-merge``).
        into: the existing map the session must merge into (None: any map it connects to, or a new one).
    """

    preset: str
    map_name: str | None
    topics: dict[str, str] | None
    merge: bool
    into: str | None = None


def parse_options(fields: Mapping[str, str]) -> UploadOptions:
    """Check the text fields of an upload.

    ``topics`` is ``image=/cam,odometry=/odom`` (the CLI syntax) or a JSON object; ``merge`` is
    ``true``/``false``.

    Raises:
        InputError: unknown field, unknown preset, a map name that breaks the rule
            (:func:`mapserver.names.check_map_name`), bad topics or merge flag; both ``map`` and ``into``,
            or ``into`` with ``merge=false``.
    """
    unknown = sorted(set(fields) - set(KNOWN_FIELDS))
    if unknown:
        msg = f"unknown form field(s) {', '.join(map(repr, unknown))}; expected file, {', '.join(KNOWN_FIELDS)}"
        raise InputError(msg)
    preset = (fields.get("preset") or "").strip() or DEFAULT_PRESET
    require_storable(resolve_params(preset))  # ConfigError (400) names the valid presets
    map_name = fields.get("map")
    if map_name is not None:
        map_name = check_map_name(map_name.strip())
    topics = _topics(fields.get("topics"))
    merge_text = (fields.get("merge") or "true").strip().lower()
    if merge_text not in ("true", "false", "1", "0", "yes", "no"):
        msg = f"merge must be true or false, got {fields.get('merge')!r}"
        raise InputError(msg)
    merge = merge_text in ("true", "1", "yes")
    return UploadOptions(preset, map_name, topics, merge, _into(fields.get("into"), map_name=map_name, merge=merge))


def _into(text: str | None, *, map_name: str | None, merge: bool) -> str | None:
    """Return the checked ``into`` field (the map to merge into), None when it is not given."""
    if text is None or not text.strip():
        return None
    into = check_map_name(text.strip())
    if map_name is not None:
        msg = (
            f"give either map (the name of a new map, {map_name!r}) or into (an existing map to merge into, "
            f"{into!r}), not both"
        )
        raise InputError(msg)
    if not merge:
        msg = f"into={into!r} merges the session into that map; it cannot be combined with merge=false"
        raise InputError(msg)
    return into


def _topics(text: str | None) -> dict[str, str] | None:
    if text is None or not text.strip():
        return None
    stripped = text.strip()
    if stripped.startswith("{"):
        try:
            value: Any = json.loads(stripped)
        except ValueError as err:
            msg = f"topics is not valid JSON: {err}"
            raise InputError(msg) from err
        if not isinstance(value, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in value.items()):
            msg = 'topics must be a JSON object of strings, e.g. {"image": "/camera/image"}'
            raise InputError(msg)
        return dict(value)
    try:
        return parse_topics_arg(stripped)
    except InputError as err:  # the parser speaks of the CLI flag; this is the form field
        raise InputError(str(err).replace("--topics", "topics")) from err


@dataclass(frozen=True, slots=True)
class StoredLog:
    """A checked log in the upload directory.

    Attributes:
        path: the log (file or ROS 2 bag directory) to process.
        folder: the upload's own folder (holds ``path``; delete it to drop the upload).
        name: the default name of the log's map (:func:`mapserver.names.default_map_name`).
        identity: the log's SHA-256, topic mapping and frame count, read here once and handed on to the job.
    """

    path: Path
    folder: Path
    name: str
    identity: LogIdentity

    def discard(self) -> None:
        """Delete the upload's folder."""
        shutil.rmtree(self.folder, ignore_errors=True)


def _log_root(root: Path) -> Path:
    if (root / "metadata.yaml").is_file():
        return root
    bag_dirs = sorted(p.parent for p in root.rglob("metadata.yaml") if p.is_file())
    if len(bag_dirs) == 1:
        return bag_dirs[0]
    if len(bag_dirs) > 1:
        msg = f"the archive holds {len(bag_dirs)} ROS 2 bag directories; upload one log at a time"
        raise InputError(msg)
    files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in LOG_SUFFIXES)
    if len(files) == 1:
        return files[0]
    msg = (
        "the archive holds no ROS 2 bag directory (metadata.yaml) and no single .bag/.db3/.mcap file"
        if not files
        else f"the archive holds {len(files)} log files; upload one log at a time"
    )
    raise InputError(msg)


def store_log(
    upload: ReceivedUpload, *, uploads_dir: Path, topics: Mapping[str, str] | None, limits: ArchiveLimits
) -> StoredLog:
    """Move (or unpack) a staged upload into its own folder and check that it is a usable log.

    The log's identity is read here: a log kept as it was uploaded is identified by the upload's SHA-256
    (the same bytes, hashed while they streamed in); an unpacked log is hashed once, here.

    Raises:
        LimitError: the archive passes one of ``limits``, or the first camera frame passes the pixel limit.
        InputError: unsupported file type, unsafe or unreadable archive, not a bag, truncated or
            corrupt bag, no usable camera topic, bad topic override. Nothing is kept then.
    """
    folder = uploads_dir / secrets.token_hex(8)
    folder.mkdir(parents=True, exist_ok=False)
    try:
        kind = archive_suffix(upload.filename)
        suffix = Path(upload.filename).suffix.lower()
        if kind is not None:
            stem = upload.filename[: -len(kind)] or "log"
            extract_archive(upload.path, folder / stem, kind=kind, limits=limits)
            upload.discard()
            path = _log_root(folder / stem)
        elif suffix in LOG_SUFFIXES:
            path = folder / upload.filename
            upload.path.replace(path)
        else:
            msg = (
                f"unsupported upload {upload.filename!r}: send a {', '.join(LOG_SUFFIXES)} file or a ROS 2 bag "
                f"directory as {', '.join(ARCHIVE_SUFFIXES)}"
            )
            raise InputError(msg)
        try:
            with open_log(path, topics) as log:
                identity = LogIdentity.of(log, sha256=upload.sha256 if kind is None else None)
                log.verify()  # every stream reads through as its index says; the odometry is usable
        except InputError as err:  # the message names the server's path: show the upload's name instead
            text = str(err).replace(str(path), upload.filename).replace(str(folder), "")
            raise (LimitError(text, limit=err.limit) if isinstance(err, LimitError) else type(err)(text)) from err
        if identity.frames == 0:
            msg = f"{upload.filename!r}: the camera topic has no frames"
            raise InputError(msg)
    except BaseException:
        upload.discard()
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return StoredLog(path=path, folder=folder, name=default_map_name(path), identity=identity)
