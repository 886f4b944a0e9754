"""Command-line entry point: ``mapserver COMMAND ...``.

Each command lives in its own module in this package and exposes
``register(subparsers) -> None``, which adds its parser and sets ``func`` to a
callable ``run(args) -> int``. The dispatcher discovers the modules, so adding a
command never touches this file. Errors become one line on stderr here, and only
here: ``InputError``/``NotFoundError`` and the engine's ``ConfigError`` (a bad preset, config file or
``--set``) exit 2, any other ``MapServerError`` exits 1.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
from collections.abc import Sequence

from core.config import ConfigError
from mapserver.errors import InputError, MapServerError


def command_modules() -> list[str]:
    """Return the names of the command modules of this package (found without importing them)."""
    return sorted(info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_"))


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Build the top-level parser with one subparser per command module (or only the module ``only``).

    Importing every command pulls in FastAPI, SQLAlchemy, alembic and scipy (seconds on a slow
    machine), so :func:`main` registers just the command it runs; the full parser serves
    ``mapserver --help`` and unknown commands.
    """
    parser = argparse.ArgumentParser(prog="mapserver", description="Multisession map server for RatSLAM-family SLAM")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages on stderr")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in command_modules() if only is None else [only]:
        module = importlib.import_module(f"{__name__}.{name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
    return parser


def _command_module(argv: Sequence[str]) -> str | None:
    """Return the module of the command named in ``argv`` (its first non-option word), if any.

    A command module may register a command of another spelling (``import_`` registers ``import``,
    ``ground_truth`` ``ground-truth``).
    """
    word = next((a for a in argv if not a.startswith("-")), None)
    if word is None:
        return None
    modules = command_modules()
    for name in (word, f"{word}_", word.replace("-", "_")):
        if name in modules:
            return name
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI and return its exit code (0 ok, 1 failure, 2 bad input)."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    only = _command_module(arguments)
    args = build_parser(only).parse_args(arguments)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    try:
        code = int(args.func(args))
    except (MapServerError, ConfigError) as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return exit_code(err)
    except KeyboardInterrupt:
        print("ERROR: interrupted", file=sys.stderr)
        return 1
    return code


def exit_code(err: MapServerError | ConfigError) -> int:
    """Return the exit code of an error: its class's, and an input error's (2) for the engine's ``ConfigError``."""
    return InputError.exit_code if isinstance(err, ConfigError) else err.exit_code


def entry() -> None:
    """Console-script entry: exit with :func:`main`'s code."""
    sys.exit(main())
