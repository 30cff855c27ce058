"""The ``gtkit`` command. Subcommands live in :mod:`gtkit.commands`, one module each, found
automatically; every module defines ``register(subparsers)`` and sets ``func`` on its parser.
A subcommand only parses arguments and calls one stage or pipeline function.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
import tempfile
from pathlib import Path

from . import __version__, commands
from .errors import GtkitError
from .logs import quiet_terminal, write_traceback


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gtkit", description="Photogrammetry and ground-truth toolkit "
                                     "for UAV 6-DoF visual localization.")
    parser.add_argument("--version", action="version", version=f"gtkit {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="debug logging; COLMAP, Open3D and Qt output on the terminal (else in work/<stage>/log.txt)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if not mod.name.startswith("_"):
            importlib.import_module(f"{commands.__name__}.{mod.name}").register(sub)
    return parser


def _error_file(args) -> Path:
    """Where an unexpected failure's traceback goes: the project's work/errors/ where the command
    names a project folder, else a temporary file."""
    root = Path(str(getattr(args, "project", "") or ""))
    if str(root) and (root / "project.toml").is_file():
        return root / "work" / "errors" / f"{args.command}.txt"
    return Path(tempfile.gettempdir()) / f"gtkit-error-{os.getpid()}.txt"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    quiet = quiet_terminal(args.verbose)  # COLMAP, Open3D, Qt output -> work/<stage>/log.txt unless -v
    try:
        with quiet as log:
            rv = args.func(args)
    except GtkitError as e:
        told = getattr(e, "traceback_file", None) is not None  # the message names its own file
        print(f"gtkit: error: {e}" + (f" (full log: {log.log_path})" if log.log_path and not told else ""),
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gtkit: interrupted; finished stages are kept and a re-run resumes", file=sys.stderr)
        return 130
    except Exception as e:  # a bug, not bad input: one line on the terminal, the traceback in a file
        where = write_traceback(_error_file(args), f"gtkit {args.command}")
        first = str(e).splitlines()[0] if str(e) else ""
        print(f"gtkit: error: {args.command} failed unexpectedly ({type(e).__name__}{': ' + first if first else ''}); "
              f"the traceback is in {where} (please report it)", file=sys.stderr)
        return 2
    return int(rv or 0)


if __name__ == "__main__":
    sys.exit(main())
