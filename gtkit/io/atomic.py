"""Atomic writes: a file is either its old self or its complete new self, never half-written."""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

from ..errors import GtkitError


_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` atomically.

    For writers that want a file name (cv2.imwrite, rasterio, trimesh ...). The temporary
    name keeps the suffix so format detection by extension still works.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        if not os.path.exists(tmp):   # a library writer that failed and cleaned up (cv2 under a full disk)
            raise GtkitError("could not be written (the writer left no file: a full disk, a file-size limit "
                             "or a read-only folder?)", path)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes files owner-only; give them the usual mode
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def write_bytes(path: str | Path, data: bytes) -> Path:
    try:
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(data)
    except OSError as e:
        if e.filename is None:   # a failed write() names no file: name the one being written
            raise OSError(e.errno, e.strerror, str(path)) from None
        raise
    return Path(path)


def write_image(path: str | Path, rgb, params: list[int] | None = None) -> Path:
    """An RGB image encoded by OpenCV in memory (format by ``path``'s suffix) and written whole, so
    a failed write raises the system's own error naming the file (cv2.imwrite only returns False)."""
    import cv2
    import numpy as np

    ok, buf = cv2.imencode(Path(path).suffix, cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), params or [])
    if not ok:
        raise GtkitError(f"OpenCV cannot encode a {Path(path).suffix} image", path)
    return write_bytes(path, buf.tobytes())


def write_text(path: str | Path, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj, indent: int = 2) -> Path:
    return write_text(path, json.dumps(obj, indent=indent, sort_keys=False, default=_json_default) + "\n")


def read_json_object(path: str | Path) -> dict | None:
    """A JSON object file as a dict, or None where it is missing, unreadable or not an object (for
    readers of other stages' records, where a missing record means "not run")."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
