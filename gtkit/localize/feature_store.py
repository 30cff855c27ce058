"""Crash-safe database feature file: HDF5 written only whole, chunks kept as whole files.

An HDF5 file appended to in place is not safe against a killed process: a SIGKILL in the middle of
a metadata write leaves a file that opens but fails on a later lookup ("addr overflow"), and all
its views are lost. So the feature file (``features.h5``, one group per view, read by
:func:`.features.read_features`) is only ever replaced whole (:func:`..io.atomic.atomic_path`),
and while it is being extracted each chunk of views goes to its own small file in
``features.h5.parts/``, also written whole. A killed run leaves the finished chunks; the next run
extracts only the views in none of them, then merges the chunks into a new feature file.

Listing a file's views means visiting every group (about 1 ms a view: 26 s at 26k views), so the
list is kept beside it (``features.h5.views.json``), stamped with the file's size, mtime and inode:
it is used only while it describes the file as it is; otherwise the file is scanned once more.
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

from ..io.atomic import atomic_path, write_json
from .features import Features, write_features

log = logging.getLogger(__name__)


def parts_dir(path: Path) -> Path:
    return path.with_name(path.name + ".parts")


def views_index(path: Path) -> Path:
    return path.with_name(path.name + ".views.json")


def _stamp(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns, st.st_ino]


def _file_views(path: Path) -> set[str] | None:
    """The feature file's views: from its index when the index describes this file, else scanned
    (and the index written); None if the file cannot be read."""
    idx = views_index(path)
    try:
        rec = json.loads(idx.read_text())
        if rec.get("stamp") == _stamp(path):
            return set(rec["views"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    views = _complete_views(path)
    if views is not None:
        _write_index(path, views)
    return views


def _write_index(path: Path, views: set[str]) -> None:
    write_json(views_index(path), {"stamp": _stamp(path), "views": sorted(views)}, indent=None)


def _complete_views(path: Path) -> set[str] | None:
    """Views whose descriptors (written last) are in the file; None if it cannot be read."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            return _views_in(h5)
    except (OSError, RuntimeError, KeyError, ValueError):
        return None


def _views_in(h5) -> set[str]:
    """The complete views of an open feature file."""
    import h5py

    views: set[str] = set()
    h5.visititems(lambda name, obj: views.add(name) if isinstance(obj, h5py.Group) and "desc" in obj else None)
    return views


def stored_views(path: Path) -> set[str]:
    """Views already extracted, in the feature file or in finished chunks of a killed run.

    An unreadable file (only a gtkit from before the chunk files could leave one) is removed and
    its views counted as missing.
    """
    done: set[str] = set()
    for f in ([path] if path.is_file() else []) + sorted(parts_dir(path).glob("*.h5")):
        views = _file_views(f) if f == path else _complete_views(f)
        if views is None:
            log.warning("%s: unreadable feature file (a run killed mid-write?), its views are extracted again", f)
            f.unlink()
        else:
            done |= views
    return done


def write_part(path: Path, features: dict[str, Features]) -> Path:
    """One chunk of views as a whole file beside the feature file."""
    import h5py

    d = parts_dir(path)
    d.mkdir(parents=True, exist_ok=True)
    n = 1 + max((int(p.stem) for p in d.glob("*.h5") if p.stem.isdigit()), default=-1)
    part = d / f"{n:06d}.h5"
    with atomic_path(part) as tmp, h5py.File(tmp, "w") as h5:
        for name, f in features.items():
            write_features(h5, name, f)
    return part


def merge_parts(path: Path) -> None:
    """Fold the chunk files into the feature file (a new file, replacing the old one whole)."""
    import h5py

    d = parts_dir(path)
    parts = sorted(d.glob("*.h5")) if d.is_dir() else []
    if not parts:
        return
    merged = (_file_views(path) or set()) if path.is_file() else set()
    with atomic_path(path) as tmp:
        if path.is_file():
            shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as out:
            for part in parts:
                with h5py.File(part, "r") as h5:
                    views = _views_in(h5)
                    merged |= views
                    for name in sorted(views):
                        if name in out:
                            del out[name]
                        parent, _, leaf = name.rpartition("/")
                        h5.copy(h5[name], out.require_group(parent) if parent else out, leaf)
    _write_index(path, merged)
    shutil.rmtree(d)
