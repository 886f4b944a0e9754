"""Damaged simulator logs through the upload check and ``mapserver process``: refused, whole, or shorter.

Usage: python bench/corrupt_logs.py [--out DIR] [--seeds 40] [--formats bag,db3,mcap]

For each format, ``mapserver simulate loop --scale 0.25 --param laps=1`` writes a clean log (35 frames), and
this script writes damaged copies of its bytes:

* ``truncated-*``: cut at 10 %, 25 %, 50 %, 75 %, 90 % and 99 % of the file, and 1, 64 and 4096 bytes before
  its end (the last chunk, index or footer cut);
* ``header-*``: one byte inverted at offsets 0, 4, 13, 64, 200 and 1000 (magic, version, the first records);
* ``zeros-*``: 4 KiB zeroed at 5 %, 30 %, 60 % and 95 % of the file;
* ``seed-*``: :func:`tests.mapserver.hostile.damaged` for seeds 0 … N − 1 (truncated, a bit flipped, 8 bytes
  zeroed, 4 bytes randomised).

Each copy goes through the API's upload check (``open_log``, ``count_frames``, ``verify``) and through
``mapserver process --preset circle --json`` in this process. Outcomes of ``process``:

* ``refused``: exit 2 with one ``ERROR:`` line, no traceback, no exception name, no bare number as reason;
* ``whole``: exit 0 with the clean log's frame count;
* ``shorter``: exit 0 with fewer frames (a damaged file processed into a shorter map);
* ``bad``: anything else (another exit code, a traceback, an exception's name or a bare number as the message).

The upload check is ``refused`` (an ``InputError``), ``passed`` or ``bad`` (another exception). Last line:
one JSON object with the counts per format and kind, and every case that was ``shorter`` or ``bad``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapserver.cli import main as cli_main  # noqa: E402
from mapserver.errors import InputError  # noqa: E402
from mapserver.ingest.reader import open_log  # noqa: E402
from tests.mapserver.hostile import damaged  # noqa: E402

FRACTIONS = (0.10, 0.25, 0.50, 0.75, 0.90, 0.99)
TAIL_CUTS = (1, 64, 4096)
HEADER_OFFSETS = (0, 4, 13, 64, 200, 1000)
ZERO_AT = (0.05, 0.30, 0.60, 0.95)


def corruptions(data: bytes, seeds: int) -> dict[str, bytes]:
    """Return the damaged copies of ``data`` by name (see the module docstring)."""
    out: dict[str, bytes] = {}
    for f in FRACTIONS:
        out[f"truncated-{int(f * 100)}%"] = data[: int(len(data) * f)]
    for cut in TAIL_CUTS:
        out[f"truncated-end-{cut}"] = data[: len(data) - cut]
    for at in HEADER_OFFSETS:
        flipped = bytearray(data)
        flipped[at] ^= 0xFF
        out[f"header-{at}"] = bytes(flipped)
    for f in ZERO_AT:
        zeroed = bytearray(data)
        at = int(len(data) * f)
        zeroed[at : at + 4096] = bytes(len(zeroed[at : at + 4096]))
        out[f"zeros-{int(f * 100)}%"] = bytes(zeroed)
    for seed in range(seeds):
        kind, damaged_bytes = damaged(data, seed)
        out[f"seed-{seed}-{kind}"] = damaged_bytes
    return out


def bad_message(text: str) -> bool:
    """Return True when an error text is not one clear line: a traceback, an exception name, a bare number."""
    lines = [line for line in text.strip().splitlines() if line.startswith("ERROR")]
    if len(lines) != 1 or "Traceback" in text:
        return True
    line = lines[0]
    reason = line.rstrip(".").split(": ")[-1]
    return "Error" in line.removeprefix("ERROR") or reason.strip().isdigit()


def upload_check(path: Path) -> tuple[str, str]:
    """Return (``passed`` | ``refused`` | ``bad``, message) of the API's upload check on ``path``."""
    try:
        with open_log(path, None) as log:
            log.count_frames()
            log.verify()
    except InputError as err:
        return "refused", str(err).replace(str(path.parent), "")
    except Exception as err:
        return "bad", f"{type(err).__name__}: {err}"
    return "passed", ""


def process(path: Path, frames: int | None) -> tuple[str, int | None, str]:
    """Return (outcome, frames processed or None, last stderr line) of ``mapserver process`` on ``path``."""
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli_main(["process", str(path), "--preset", "circle", "--json"])
    except BaseException as exc:
        return "bad", None, f"{type(exc).__name__}: {exc}"
    text = err.getvalue()
    last = (text.strip().splitlines() or [""])[-1].replace(str(path.parent), "")
    if code == 0:
        got = int(json.loads(out.getvalue().strip().splitlines()[-1])["frames"])
        return ("whole" if frames is None or got == frames else "shorter"), got, last
    if code == 2 and not bad_message(text):
        return "refused", None, last
    return "bad", None, f"exit {code}: {last}"


def clean_log(work: Path, fmt: str) -> Path:
    """Simulate the clean log of ``fmt`` and return its path."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = cli_main(["simulate", "loop", "--out", str(work / fmt), "--scale", "0.25", "--param", "laps=1",
                         "--format", fmt])  # fmt: skip
    if code != 0:
        msg = f"simulate failed for {fmt}"
        raise SystemExit(msg)
    return next(p for p in (work / fmt).iterdir() if p.name.startswith("single."))


def run_format(work: Path, fmt: str, seeds: int) -> dict[str, Any]:
    """Damage one format's clean log every way and return the counts and the cases worth reading."""
    clean = clean_log(work, fmt)
    outcome, frames, line = process(clean, None)
    if outcome != "whole":
        msg = f"the clean {fmt} log does not process: {line}"
        raise SystemExit(msg)
    counts: Counter[str] = Counter()
    cases: list[dict[str, Any]] = []
    damaged_copies = corruptions(clean.read_bytes(), seeds)
    for name, data in damaged_copies.items():
        path = work / f"damaged-{name}{clean.suffix}"
        path.write_bytes(data)
        check, check_msg = upload_check(path)
        result, got, last = process(path, frames)
        path.unlink()
        counts[f"upload_{check}"] += 1
        counts[f"process_{result}"] += 1
        if check == "passed":
            counts[f"passed_then_{result}"] += 1
        case = {"format": fmt, "case": name, "upload": check, "process": result, "frames": got, "message": last}
        print(json.dumps(case), flush=True)
        if result in ("shorter", "bad") or check == "bad":
            cases.append({**case, "upload_message": check_msg})
    return {"frames": frames, "files": len(damaged_copies), "counts": dict(counts), "cases": cases}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--seeds", type=int, default=40)
    parser.add_argument("--formats", default="bag,db3,mcap")
    args = parser.parse_args()
    work = args.out or Path(tempfile.mkdtemp(prefix="corrupt-"))
    work.mkdir(parents=True, exist_ok=True)
    results = {fmt: run_format(work, fmt, args.seeds) for fmt in args.formats.split(",")}
    total: Counter[str] = Counter()
    for result in results.values():
        total.update(result["counts"])
    print(json.dumps({"formats": results, "total": dict(total)}))


if __name__ == "__main__":
    main()
