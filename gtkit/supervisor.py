"""The ``gtkit`` command as installed: the command runs in a child process, and a child that dies
without a word (a C++ library aborting: COLMAP's ``SQLite error: disk I/O error`` when the disk is
full or a file-size limit is reached, a failed ``Check``; the system's out-of-memory killer; a
``kill -9``) is reported in one line naming how it died, the stage it was in, the cause its log
gives and the log, exit status 2. Python errors are the child's own to report (``gtkit.cli.main``:
one line, the traceback in a file).

Why a child: an abort inside a C++ library ends the whole process at once; no Python handler runs,
and the terminal shows only the last progress bar. The parent imports nothing of gtkit's stages
(it costs a Python start, about 0.1 s).

``python -m pipelines.full`` (the main job) goes through :func:`run_supervised` too.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

# lines of a stage log that say why a library stopped the process, most telling first
CAUSE = re.compile(r"what\(\):\s*(.+)|Check failed:\s*(.+)|(SQLite error.*)|(std::bad_alloc.*)|(MemoryError.*)")
LOW_DISK_BYTES = 200 * 2**20
SUPERVISED = "GTKIT_SUPERVISED"   # set in the child's environment


def _project_of(argv: list[str]) -> Path | None:
    """The project folder named on the command line (the first argument holding a project.toml)."""
    for a in argv:
        if not a.startswith("-") and (Path(a) / "project.toml").is_file():
            return Path(a)
    return None


def _newest_log(root: Path, since: float) -> Path | None:
    logs = [p for p in (root / "work").glob("*/log.txt") if p.stat().st_mtime >= since - 1]
    logs += [p for p in (root / "work").glob("*/*/log.txt") if p.stat().st_mtime >= since - 1]
    return max(logs, key=lambda p: p.stat().st_mtime, default=None)


def _cause(log: Path) -> str | None:
    try:
        lines = log.read_text(errors="replace").splitlines()[-400:]
    except OSError:
        return None
    for line in reversed(lines):
        m = CAUSE.search(line)
        if m:
            return next(g for g in m.groups() if g).strip()
    return None


def death_line(sig: int, command: str, root: Path | None, since: float) -> str:
    """One line: how the child died, in which stage, the cause its log gives, what to do."""
    try:
        name = signal.Signals(sig).name
    except ValueError:
        name = f"signal {sig}"
    parts = [f"gtkit: error: {command} stopped: the process was ended by {name}"]
    log = _newest_log(root, since) if root is not None else None
    cause = _cause(log) if log is not None else None   # read once: the log may be long
    if log is not None:
        parts[0] += f" in stage {log.parent.relative_to(root / 'work').as_posix()}"
    if cause:
        parts.append(cause)
    if root is not None:
        free = shutil.disk_usage(root).free
        if free < LOW_DISK_BYTES:
            parts.append(f"the disk holding {root} is full ({free / 2**20:.0f} MB free): free space and run it again")
        elif "disk I/O error" in (cause or ""):
            parts.append("a file could not be written: a full disk, a file-size limit (ulimit -f) or a "
                         "read-only folder; fix it and run the command again (finished stages are kept)")
    if name == "SIGKILL":
        parts.append("killed from outside: by a user, or by the system when memory ran out (see `dmesg`); "
                     "run it again to resume")
    if log is not None:
        parts.append(f"full log: {log}")
    return "; ".join(parts)


def _die_with_parent() -> None:
    """In the child, before exec: end with the parent (Linux ``PR_SET_PDEATHSIG``), so a ``kill -9``
    of the ``gtkit`` a user started ends the work too (the project lock it held is then stale, and
    the next command takes it over)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run_supervised(child_argv: list[str], command: str, argv: list[str]) -> int:
    """Run ``child_argv`` (a Python command line) as a child with this terminal; its exit status, or
    2 with :func:`death_line` when a signal ended it. Ctrl-C reaches the child (same process group),
    which reports it itself; SIGTERM / SIGHUP sent to this process are passed on."""
    since = time.time()
    child = subprocess.Popen(child_argv, env={**os.environ, SUPERVISED: "1"}, preexec_fn=_die_with_parent if sys.platform == "linux" else None)

    def forward(signum, _frame):
        child.send_signal(signum)

    old = {s: signal.signal(s, forward) for s in (signal.SIGTERM, signal.SIGHUP)}
    old[signal.SIGINT] = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        rc = child.wait()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if rc >= 0:
        return rc
    if -rc == signal.SIGINT:
        return 130
    print("\n" + death_line(-rc, command, _project_of(argv), since), file=sys.stderr)  # after a progress bar
    return 2


def entry() -> int:
    """The installed ``gtkit`` command (``[project.scripts]``): ``gtkit.cli`` in a child process."""
    argv = sys.argv[1:]
    if os.environ.get("GTKIT_NO_CHILD"):          # debugging: run in this process
        from .cli import main

        return main(argv)
    command = "gtkit " + next((a for a in argv if not a.startswith("-")), "")
    return run_supervised([sys.executable, "-m", "gtkit.cli", *argv], command.strip(), argv)


if __name__ == "__main__":
    sys.exit(entry())
