"""The ``gtkit`` command. Subcommands live in :mod:`gtkit.commands`, one module each, found
automatically; every module defines ``register(subparsers)`` and sets ``func`` on its parser.
A subcommand only parses arguments and calls one stage or pipeline function.

Every command that names a project folder writes it, and holds the project's lock while it runs
(:mod:`gtkit.project_lock`: a second writer is refused in one line, exit 2), except those that set
``writes=False`` on their parser (``info``, ``view``, ``gcp status``, ``meta``; ``annotate`` takes
the lock for each save itself).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import pkgutil
import sys
import tempfile
from pathlib import Path

from . import __version__, commands
from .errors import GtkitError
from .logs import exception_words, quiet_terminal, write_traceback
from .write_errors import machine_cause


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gtkit", description="Photogrammetry and ground-truth toolkit "
                                     "for UAV 6-DoF visual localization.")
    parser.add_argument("--version", action="version", version=f"gtkit {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="every log record (debug and info) and COLMAP, Open3D and Qt output on the terminal "
                             "(else only warnings there, the rest in work/<stage>/log.txt)")
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


def project_written(args) -> Path | None:
    """The project folder this command writes (its lock is held while it runs), or None: a
    read-only command (``writes=False``), or no project folder named (``init``, ``sample create``)."""
    if not getattr(args, "writes", True):
        return None
    root = getattr(args, "project", None) or getattr(args, "dir", None)
    return Path(root) if root and (Path(root) / "project.toml").is_file() else None


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from .project_lock import ProjectLocked, project_lock

    root = project_written(args)
    quiet = quiet_terminal(args.verbose)  # COLMAP, Open3D, Qt output -> work/<stage>/log.txt unless -v
    log = None   # bound once the terminal is quiet (a lock refused before it is not)
    try:
        with project_lock(root) if root else contextlib.nullcontext(), quiet as log:
            rv = args.func(args)
    except ProjectLocked as e:   # a second writer: one line naming the holder, nothing else
        print(f"gtkit: error: {e}", file=sys.stderr)
        return 2
    except GtkitError as e:
        told = getattr(e, "traceback_file", None) is not None  # the message names its own file
        print(f"gtkit: error: {e}" + (f" (full log: {log.log_path})" if getattr(log, "log_path", None) and not told else ""),
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gtkit: interrupted; finished stages are kept and a re-run resumes", file=sys.stderr)
        return 130
    except OSError as e:    # the machine's (a full disk, a read-only folder ...), not a bug
        cause = machine_cause(e)
        if cause is None:
            return _unexpected(args, e)
        print(f"gtkit: error: {args.command}: {cause}", file=sys.stderr)
        return 2
    except Exception as e:  # a bug, not bad input: one line on the terminal, the traceback in a file
        return _unexpected(args, e)
    return int(rv or 0)


def _unexpected(args, e: BaseException) -> int:
    where = write_traceback(_error_file(args), f"gtkit {args.command}")
    print(f"gtkit: error: {args.command} failed unexpectedly ({exception_words(e)}); "
          f"the traceback is in {where} (please report it)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
