"""One writer per project: the project lock (``work/.lock``).

Every command that writes a project (``gtkit run``, each stage command, ``python -m
pipelines.full``, the annotator's saves) holds the lock while it writes; a second writer is refused
at once with one line naming the holder (its command, process id, host and since when)::

    with project_lock(root):        # raises ProjectLocked (a GtkitError) when another process holds it
        ...

How: the lock is an ``fcntl.flock`` on ``work/.lock``, a file that is never replaced or removed.
The kernel drops a flock when its process ends in any way (exit, crash, ``kill -9``), so a killed
holder never blocks the next run, whatever its process id became. Who holds it is written beside
it, atomically, in ``work/.lock.json`` (command line, pid, host, start time) and removed on release;
a ``.lock.json`` found with the flock free is a holder that did not release (crashed or killed):
the new writer takes the lock over and prints one line saying whose it was. Where the file system
has no flock, the record alone decides: a holder whose pid is no longer alive on this host is stale.

Re-entrant within a process (a stage run inside ``gtkit run``, ``pipelines.full`` calling
``gtkit run``'s loop, the annotator's saves): a nested acquire of a lock this process holds counts
up and returns at once. A forked child (a worker process) does not own its parent's lock: it
closes its inherited copy of the lock file at once and never releases the parent's.
Read-only commands (``gtkit info``, ``gtkit view``, ``gtkit gcp status``) do not take it;
:func:`holder` says, without taking it, whether another process writes the project (the annotator
shows it and does not save while it does).
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shlex
import socket
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from .errors import GtkitError

try:
    import fcntl
except ImportError:             # no flock (not POSIX): the record alone decides
    fcntl = None

LOCK_FILE = ".lock"             # in work/: the flock'd file (empty, never replaced)
HOLDER_FILE = ".lock.json"      # in work/: who holds it (atomic; removed on release)
LOCK_EXIT = 2                   # the exit code of a refused second writer


class ProjectLocked(GtkitError):
    """Another process holds the project's lock (the message names it)."""

    def __init__(self, message: str, path=None, holder: "Holder | None" = None):
        super().__init__(message, path)
        self.holder = holder


@dataclass
class Holder:
    command: str
    pid: int
    host: str
    since: float                  # unix time
    flock: bool = True            # it holds the flock (False: a file system without flock; the record decides)

    def since_text(self) -> str:
        t = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(self.since))
        age = max(0.0, time.time() - self.since)
        ago = f"{age:.0f} s" if age < 120 else (f"{age / 60:.0f} min" if age < 7200 else f"{age / 3600:.1f} h")
        return f"{t}, {ago} ago"

    def describe(self) -> str:
        return f"`{self.command}` (pid {self.pid} on {self.host}, since {self.since_text()})"

    def alive(self) -> bool | None:
        """Whether its process still runs (None: another host, cannot tell)."""
        if self.host != socket.gethostname():
            return None
        return pid_alive(self.pid)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:       # someone else's process: alive
        return True
    except (OSError, ValueError, OverflowError):
        return False
    return True


def flock_held(lock: Path, table: str = "/proc/locks") -> bool | None:
    """Whether any process holds a flock on ``lock``, read from the kernel's lock table (Linux's
    ``/proc/locks``: ``1: FLOCK ADVISORY WRITE pid maj:min:inode 0 EOF``), taking nothing;
    None where that cannot be told (no such table, no such file)."""
    try:
        st = os.stat(lock)
        rows = Path(table).read_text().splitlines()
    except OSError:
        return None
    want = (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino)
    for row in rows:
        f = row.split()
        if len(f) < 6 or f[1] != "FLOCK":     # a waiter's row reads "N: -> FLOCK ...": not a holder
            continue
        try:
            maj, mnr, ino = f[5].split(":")
            if (int(maj, 16), int(mnr, 16), int(ino)) == want:
                return True
        except ValueError:
            continue
    return False


def lock_paths(root: str | Path) -> tuple[Path, Path]:
    work = Path(root) / "work"
    return work / LOCK_FILE, work / HOLDER_FILE


def this_command() -> str:
    """The command line of this process, as a user would type it (``gtkit run SITE``,
    ``python -m pipelines.full SITE``; the installed ``gtkit`` runs ``python -m gtkit.cli`` as a
    child, :mod:`gtkit.supervisor`, which holds the lock: its command reads ``gtkit ...``)."""
    argv = list(sys.argv) or ["python"]
    exe = Path(argv[0])
    if exe.name == "__main__.py" or exe.suffix == ".py":
        mod = exe.with_suffix("")
        parts = [p for p in mod.parts[-2:] if p != "__main__"]
        head = ["python", "-m", ".".join(parts)] if len(parts) == 2 else ["python", str(exe)]
        if head[2:] == ["gtkit.cli"]:      # the installed `gtkit` runs its command as this child
            head = ["gtkit"]
    else:
        head = [exe.name]
    return shlex.join(head + argv[1:])


def read_holder(root: str | Path) -> Holder | None:
    _, rec = lock_paths(root)
    try:
        d = json.loads(rec.read_text())
        return Holder(str(d["command"]), int(d["pid"]), str(d["host"]), float(d["since"]), bool(d.get("flock", True)))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write_holder(root: Path, h: Holder) -> None:
    """Atomically (a temporary file renamed over it), without fsync: the record only names the
    holder (the flock is the lock), and the annotator writes it at every save (0.1 ms, not 5)."""
    rec = lock_paths(root)[1]
    tmp = rec.with_name(f"{rec.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(asdict(h)) + "\n")
        os.replace(tmp, rec)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


# --- this process's locks ------------------------------------------------------------------------

_HELD: dict[str, list] = {}       # resolved root -> [fd or None, depth, owner pid]
_GUARD = threading.Lock()


def _close_in_child() -> None:
    """In a forked child (multiprocessing's workers, os.fork): close the inherited lock files, so a
    worker that outlives the run's release does not keep the project locked (the parent's own
    descriptor keeps the flock while it is open)."""
    for e in _HELD.values():
        if e[0] is not None:
            with contextlib.suppress(OSError):
                os.close(e[0])
            e[0] = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_close_in_child)


def _key(root: str | Path) -> str:
    return str(Path(root).resolve())


def held_here(root: str | Path) -> bool:
    """Whether this process holds the project's lock."""
    e = _HELD.get(_key(root))
    return e is not None and e[2] == os.getpid()


def _try_flock(lock: Path) -> tuple[int | None, bool]:
    """(fd, got): an open fd holding the flock, or (None, False) when another holds it; (None, True)
    where the file system has no flock (the record decides)."""
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    if fcntl is None:
        os.close(fd)
        return None, True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        os.close(fd)
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return None, False
        return None, True          # ENOLCK / EOPNOTSUPP ...: no flock here
    return fd, True


def _refusal(root: Path, h: Holder | None) -> ProjectLocked:
    who = h.describe() if h else "another gtkit process (it has not said which yet)"
    if h is not None and h.alive() is False:
        who += ", whose process has ended but whose worker processes still hold the lock"
    tail = f"wait for it to end, or stop it (kill {h.pid}) and run again" if h else "wait for it to end"
    return ProjectLocked(f"another writer holds this project: {who}; {tail} (a second writer would "
                         f"spoil its outputs)", root, h)


def acquire(root: str | Path, command: str | None = None, note=None) -> bool:
    """Take the project's lock for this process (re-entrant). Returns True where this call took it
    (False: already held here, depth counted up). Raises :class:`ProjectLocked` where another
    process holds it. ``note(line)`` gets the one line said when a dead holder's lock is taken over
    (default: printed to stderr)."""
    root = Path(root)
    key = _key(root)
    with _GUARD:
        e = _HELD.get(key)
        if e is not None and e[2] == os.getpid():
            e[1] += 1
            return False
        _HELD.pop(key, None)          # inherited from a parent by fork: not ours
        lock, _ = lock_paths(root)
        try:
            lock.parent.mkdir(parents=True, exist_ok=True)
            fd, got = _try_flock(lock)
        except OSError as err:
            raise GtkitError(f"cannot create the project lock ({err.strerror or err})", lock) from None
        if not got:
            fd, got = _after_dead_holder(root, lock)
        if not got:
            raise _refusal(root, _holder_settled(root))
        old = read_holder(root)
        if old is not None and not (fd is not None or old.alive() is False):
            if old.pid != os.getpid():   # no flock here and the holder may live: the record decides
                raise _refusal(root, old)
        me = Holder(command or this_command(), os.getpid(), socket.gethostname(), time.time(), fd is not None)
        try:
            _write_holder(root, me)
        except OSError as err:
            if fd is not None:
                os.close(fd)
            raise GtkitError(f"cannot write the project lock ({err.strerror or err})", lock_paths(root)[1]) from None
        _HELD[key] = [fd, 1, os.getpid()]
    if old is not None and old.pid != os.getpid():
        state = {False: "is no longer running", None: "is not running here"}.get(old.alive(), "no longer holds it")
        line = (f"gtkit: note: took over the lock of {root}: it was left by {old.describe()}, which {state} "
                f"(crashed or killed); what it finished is kept")
        (note or (lambda s: print(s, file=sys.stderr, flush=True)))(line)
    return True


def _after_dead_holder(root: Path, lock: Path, wait_s: float = 3.0) -> tuple[int | None, bool]:
    """The flock is busy but its recorded holder is dead: a killed process's worker processes
    (forked with its open lock file) keep it a moment longer; try again for ``wait_s``."""
    h = read_holder(root)
    t_end = time.time() + wait_s
    while h is not None and h.alive() is False and time.time() < t_end:
        time.sleep(0.1)
        fd, got = _try_flock(lock)
        if got:
            return fd, got
    return None, False


def _holder_settled(root: Path, wait_s: float = 1.0) -> Holder | None:
    """The holder's record, giving a holder that has just taken the lock a moment to write it (a
    record naming a dead process is the previous, killed holder's)."""
    t_end = time.time() + wait_s
    while True:
        h = read_holder(root)
        if h is not None and h.alive() is not False or time.time() > t_end:
            return h
        time.sleep(0.05)


def release(root: str | Path) -> None:
    """Give back one level of this process's lock; the last removes the record and drops the flock."""
    key = _key(root)
    with _GUARD:
        e = _HELD.get(key)
        if e is None or e[2] != os.getpid():
            return
        e[1] -= 1
        if e[1] > 0:
            return
        del _HELD[key]
        with contextlib.suppress(OSError):
            lock_paths(root)[1].unlink()
        if e[0] is not None:
            with contextlib.suppress(OSError):
                os.close(e[0])        # drops the flock


@contextlib.contextmanager
def project_lock(root: str | Path, command: str | None = None, note=None):
    """Hold the project's lock for the block (see the module doc)."""
    acquire(root, command, note)
    try:
        yield
    finally:
        release(root)


def holder(root: str | Path) -> Holder | None:
    """The other process writing this project now, or None (free, or held by this process).
    Takes nothing: its record is read, its process looked up and, on Linux, the kernel's lock table
    read (a killed holder's pid reused by another process is not a holder); only a record written on
    another host is checked against the flock (tested and dropped at once)."""
    root = Path(root)
    if held_here(root):
        return None
    h = read_holder(root)
    if h is None or h.pid == os.getpid():
        return None
    alive = h.alive()
    if alive is not None:
        # A live pid may be a killed holder's, reused by another process: the kernel's lock table
        # says whether anyone holds the flock, without taking it (None: cannot tell; the pid decides)
        if alive and h.flock and flock_held(lock_paths(root)[0]) is False:
            return None
        return h if alive else None
    try:
        fd, got = _try_flock(lock_paths(root)[0])
    except OSError:
        return h
    if fd is not None:
        os.close(fd)
        return None
    return h
