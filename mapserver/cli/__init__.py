"""Command-line entry point: ``mapserver COMMAND ...``.

Each command lives in its own module in this package and exposes
``register(subparsers) -> None``, which adds its parser and sets ``func`` to a
callable ``run(args) -> int``. The dispatcher discovers the modules, so adding a
command never touches this file. Errors become one line on stderr here, and only
here: ``InputError``/``NotFoundError`` exit 2, any other ``MapServerError`` exits 1.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
from collections.abc import Sequence

from mapserver.errors import MapServerError


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with one subparser per command module."""
    parser = argparse.ArgumentParser(prog="mapserver", description="Multisession map server for RatSLAM-family SLAM")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages on stderr")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI and return its exit code (0 ok, 1 failure, 2 bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    try:
        code = int(args.func(args))
    except MapServerError as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("ERROR: interrupted", file=sys.stderr)
        return 1
    return code


def entry() -> None:
    """Console-script entry: exit with :func:`main`'s code."""
    sys.exit(main())
