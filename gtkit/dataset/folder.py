"""The dataset folder as one atomic unit: built whole beside ``OUT`` and swapped in, so ``OUT`` is
either the previous export or the new one, never half-written; a folder that holds anything but a
dataset gtkit wrote is refused before anything is written; an export whose inputs and settings are
those ``OUT/dataset.json`` records is a no-op."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
from pathlib import Path

from ..errors import GtkitError
from ..project import Project, file_fingerprint, settings_dict

FORMAT = "gtkit-dataset"
SHEET_JSON = "dataset.json"


def read_sheet(folder: str | Path) -> dict | None:
    """``folder``'s ``dataset.json`` where it is one this package wrote, else None."""
    try:
        d = json.loads((Path(folder) / SHEET_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) and d.get("format") == FORMAT else None


def previous_export(out: Path) -> dict | None:
    """The ``dataset.json`` of the dataset already in ``out``; None where ``out`` is absent or empty.
    A file, or a folder holding anything else, is refused in one line."""
    out = Path(out)
    if not out.exists():
        return None
    if not out.is_dir():
        raise GtkitError("the output exists and is not a folder", out)
    if not any(out.iterdir()):
        return None
    d = read_sheet(out)
    if d is None:
        raise GtkitError("the output folder holds something else (no dataset.json written by gtkit export dataset): "
                         "give a new or empty folder", out)
    return d


def _photo_stamp(p: Path) -> str:
    st = p.stat()
    return f"{st.st_size}-{st.st_mtime_ns}"


def input_fingerprints(project: Project, photos: list[str], extra: list[Path]) -> dict[str, str]:
    """What the export reads, each file by :func:`gtkit.project.file_fingerprint` (photos by size
    and modification time), keyed by its path inside the project."""
    P = project.paths
    files = [P.project_toml, P.pseudo_gt_poses, P.intrinsics("register"), P.stage("register") / "covariances.txt",
             P.registration, P.reports / "gt_report.json", P.review, P.reference_poses, P.reference_intrinsics,
             P.stage("sfm_reference") / "block.json", P.stage("render_db") / "stage.json",
             P.stage("render_db") / "views.json", P.rig, P.geo_txt, P.ortho, *extra]
    out = {str(f.relative_to(P.root)): file_fingerprint(f) for f in files}
    out.update({f"images/{n}": _photo_stamp(P.images / n) for n in sorted(photos) if (P.images / n).is_file()})
    return out


def export_key(settings, inputs: dict, version: str) -> str:
    blob = json.dumps({"settings": settings_dict(settings), "inputs": inputs, "gtkit": version}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def up_to_date(out: Path, previous: dict | None, key: str) -> bool:
    if not previous or previous.get("export", {}).get("key") != key:
        return False
    return all((Path(out) / f).exists() or (Path(out) / f).is_symlink() for f in previous.get("files", []))


@contextlib.contextmanager
def staged(out: Path):
    """A fresh folder beside ``out`` to build the dataset in; on success it replaces ``out`` (the
    previous export is removed only once the new one is in place); on failure it is removed."""
    out = Path(out).absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        if out.exists():
            os.rename(out, old)
        os.rename(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def listing(root: Path) -> list[str]:
    """Every file under ``root`` (symbolic links included), relative, sorted."""
    root = Path(root)
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() or p.is_symlink())
