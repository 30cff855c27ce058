"""gtkit's one error type: a message a user can act on, on one line, naming the file."""
from __future__ import annotations

from pathlib import Path


class GtkitError(Exception):
    """Bad input or a failed stage. ``str(err)`` is one line: ``<file>: <what is wrong>``."""

    def __init__(self, message: str, path: str | Path | None = None):
        message = " ".join(str(message).split())  # always one line
        super().__init__(f"{path}: {message}" if path is not None else message)
        self.path = None if path is None else Path(path)


class Problems:
    """Every problem of one input file, collected, then raised as one :class:`GtkitError` that
    counts them and names each (``line 4: ...; line 9: ...``), so a user fixes them in one go."""

    SHOWN = 20

    def __init__(self, path: str | Path, what: str = "line"):
        self.path, self.what, self.items = path, what, []

    def add(self, where, why) -> None:
        self.items.append(f"{where}: {why}" if where is not None else str(why))

    def __bool__(self) -> bool:
        return bool(self.items)

    def message(self) -> str:
        n, more = len(self.items), len(self.items) - self.SHOWN
        return (f"{n} bad {self.what}{'s' if n != 1 else ''}: " + "; ".join(self.items[:self.SHOWN])
                + (f"; ... and {more} more" if more > 0 else ""))

    def raise_if_any(self) -> None:
        if self.items:
            raise GtkitError(self.message(), self.path)
