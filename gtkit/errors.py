"""gtkit's one error type: a message a user can act on, on one line, naming the file."""
from __future__ import annotations

from pathlib import Path


class GtkitError(Exception):
    """Bad input or a failed stage. ``str(err)`` is one line: ``<file>: <what is wrong>``."""

    def __init__(self, message: str, path: str | Path | None = None):
        message = " ".join(str(message).split())  # always one line
        super().__init__(f"{path}: {message}" if path is not None else message)
        self.path = None if path is None else Path(path)
