"""Quiet terminal, full logs on disk.

Inside :func:`quiet_terminal` the terminal shows warnings, errors, progress bars and what a command
prints (its one line per stage, its summary); everything else - log records below WARNING (gtkit's
INFO lines: each step's figures, which files were written), COLMAP's glog lines, Ceres, Open3D, Qt
and pymeshlab messages, worker processes' output - goes to the log of the stage that runs,
``work/<stage>/log.txt`` (every stage starts its clock through :func:`gtkit.project.start_stage_clock`,
which calls :func:`stage_started`), so a run can be read afterwards. Before the first stage starts
the descriptors are left alone; log records below WARNING are held then (the last
:data:`PENDING_MAX`) and written at the top of the first stage's log (a run whose stages are all up
to date opens none: its "up to date" records are dropped). Issue 58: the README's main job printed
114 lines, 42 of them INFO records; the terminal is for what a user acts on.

How: the C libraries write to file descriptors 1 and 2, so those are pointed at the stage's log
(``dup2``), while Python's ``sys.stdout`` / ``sys.stderr`` and the logging handlers that wrote to
the terminal are moved to duplicates of the original descriptors. ``-v`` (or ``GTKIT_LOG=terminal``)
leaves everything on the terminal as before. Not used where the process's stdio is not its own
(``sys.stderr`` replaced, as under pytest's capture): nothing changes there.
"""
from __future__ import annotations

import collections
import contextlib
import logging
import os
import sys
from pathlib import Path

LOG_NAME = "log.txt"
_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
PENDING_MAX = 500


class _Pending(logging.Handler):
    """The records logged before the first stage's log opens (written there when it does)."""

    def __init__(self, capture: "_Capture"):
        super().__init__(logging.DEBUG)
        self.capture = capture
        self.setFormatter(logging.Formatter(_FORMAT))
        self.lines: collections.deque[str] = collections.deque(maxlen=PENDING_MAX)

    def emit(self, record: logging.LogRecord) -> None:
        if self.capture.log_path is None:
            self.lines.append(self.format(record))


class _Capture:
    def __init__(self):
        self.saved: dict[int, int] = {}      # fd -> duplicate of the terminal's descriptor
        self.terminal: dict[int, object] = {}
        self.log_file = None
        self.log_path: Path | None = None
        self.opened: set[Path] = set()
        self.handler: logging.Handler | None = None
        self.pending = _Pending(self)

    @staticmethod
    def terminal_filter(record: logging.LogRecord) -> bool:
        """The terminal's log handlers: WARNING and up."""
        return record.levelno >= logging.WARNING

    def switch(self, path: Path) -> None:
        """Send descriptors 1 and 2 (and gtkit's DEBUG log) to ``path`` from now on."""
        path = Path(path)
        if path == self.log_path:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        if path not in self.opened:  # a stage's first run in this process starts its log afresh
            path.write_text("")
            self.opened.add(path)
        new = open(path, "a", buffering=1, encoding="utf-8", errors="replace")
        for stream in (sys.__stdout__, sys.__stderr__):
            with contextlib.suppress(Exception):
                stream.flush()
        for fd in (1, 2):
            os.dup2(new.fileno(), fd)
        if self.pending.lines:            # what was logged before the first stage
            new.write("\n".join(self.pending.lines) + "\n")
            self.pending.lines.clear()
        if self.handler is None:
            self.handler = logging.StreamHandler(new)
            self.handler.setLevel(logging.DEBUG)
            self.handler.setFormatter(logging.Formatter(_FORMAT))
            logging.getLogger().addHandler(self.handler)
        else:
            self.handler.setStream(new)
        if self.log_file is not None:
            self.log_file.close()
        self.log_file, self.log_path = new, path


_ACTIVE: _Capture | None = None


def stage_started(stage_dir: str | Path) -> None:
    """Called when a stage starts (its clock): its log becomes ``stage_dir/log.txt``."""
    if _ACTIVE is not None:
        try:
            _ACTIVE.switch(Path(stage_dir) / LOG_NAME)
        except OSError:  # a read-only or vanished folder: the output stays where it went
            pass


def current_log() -> Path | None:
    """The log the C libraries write to now (None: the terminal)."""
    return None if _ACTIVE is None else _ACTIVE.log_path


@contextlib.contextmanager
def quiet_terminal(verbose: bool = False):
    """See the module doc. Yields an object whose ``log_path`` is the last stage log written (None:
    none), still readable after the block; nests (an inner call changes nothing)."""
    global _ACTIVE
    if (verbose or _ACTIVE is not None or os.environ.get("GTKIT_LOG") == "terminal"
            or sys.stderr is not sys.__stderr__ or sys.stdout is not sys.__stdout__
            or sys.__stderr__ is None or sys.__stdout__ is None):
        yield _Capture()
        return
    cap = _Capture()
    old_out, old_err = sys.stdout, sys.stderr
    try:
        old_out.flush()
        old_err.flush()
        for fd, old in ((1, old_out), (2, old_err)):
            cap.saved[fd] = os.dup(fd)
            cap.terminal[fd] = os.fdopen(cap.saved[fd], "w", buffering=1, encoding=getattr(old, "encoding", None)
                                         or "utf-8", errors="replace", closefd=False)
    except (OSError, ValueError, AttributeError):  # no real descriptors (embedded, closed)
        for fd in cap.saved.values():
            os.close(fd)
        yield _Capture()
        return
    moved = []
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) in (old_err, old_out):
            moved.append((h, h.stream))
            h.setStream(cap.terminal[2] if h.stream is old_err else cap.terminal[1])
            h.addFilter(cap.terminal_filter)
    sys.stdout, sys.stderr = cap.terminal[1], cap.terminal[2]
    logging.getLogger().addHandler(cap.pending)
    _ACTIVE = cap
    try:
        yield cap
    finally:
        _ACTIVE = None
        for s in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
            with contextlib.suppress(Exception):
                s.flush()
        for fd, saved in cap.saved.items():
            os.dup2(saved, fd)
        sys.stdout, sys.stderr = old_out, old_err
        for h, stream in moved:
            h.setStream(stream)
            h.removeFilter(cap.terminal_filter)
        logging.getLogger().removeHandler(cap.pending)
        if cap.handler is not None:
            logging.getLogger().removeHandler(cap.handler)
        if cap.log_file is not None:
            cap.log_file.close()
        for fd in (1, 2):
            cap.terminal[fd].close()
            os.close(cap.saved[fd])



def exception_words(e: BaseException) -> str:
    """An exception in a few words for a one-line message: ``TypeError: its first line`` (or the
    type alone where it says nothing)."""
    first = str(e).splitlines()[0] if str(e) else ""
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def write_traceback(path: str | Path, what: str) -> Path:
    """Write the exception being handled (its traceback) to ``path`` (a fresh file, folders made) with
    a first line saying ``what`` failed; returns the path it went to (a temporary file where ``path``
    cannot be written). For the one-line message that replaces a traceback on the terminal."""
    import tempfile
    import time
    import traceback

    text = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {what} failed unexpectedly:\n{traceback.format_exc()}"
    try:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    except OSError:
        fd, name = tempfile.mkstemp(prefix="gtkit-error-", suffix=".txt")
        with os.fdopen(fd, "w") as f:
            f.write(text)
        path = Path(name)
    return path
