"""``gtkit export dataset SITE OUT``: the stage (see :mod:`gtkit.dataset`)."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from ..errors import GtkitError
from ..project import Project, settings_dict
from . import datasheet, folder, formats, kapture_tree
from .gt import collect

log = logging.getLogger(__name__)

FORMATS = ("kapture", "colmap", "hloc")


@dataclass
class DatasetSettings:
    formats: tuple[str, ...] = FORMATS   # which of kapture, colmap, hloc to write (the sidecar, kept-out list and datasheet always)
    copy: bool = False                   # copy the photos (and model files) instead of linking them (absolute symbolic links)
    with_model: bool = False             # add the reference model (exports/mesh/, else model/) and exports/dsm.tif
    depth: bool = True                   # the render-db views' depth maps in kapture/mapping (float32: 1.2 MB a 640x480 view)


def check_formats(formats) -> tuple[str, ...]:
    got = tuple(dict.fromkeys(f.strip().lower() for f in formats if f.strip()))
    bad = [f for f in got if f not in FORMATS]
    if bad or not got:
        raise GtkitError(f"unknown dataset format {', '.join(bad) or '(none given)'!s} (choose from {', '.join(FORMATS)})")
    return got


def _version() -> str:
    from .. import __version__

    return __version__


def _model_files(project: Project) -> list[tuple[Path, str]]:
    P = project.paths
    src = P.mesh_export if P.mesh_export.is_dir() and any(P.mesh_export.iterdir()) else P.model
    files = [(f, f"model/{f.relative_to(src)}") for f in sorted(src.rglob("*")) if f.is_file()] if src.is_dir() else []
    if not files:
        raise GtkitError("--with-model: the project has no reference model (exports/mesh/ or model/)", P.root)
    if P.dsm.is_file():
        files.append((P.dsm, "model/dsm.tif"))
    return files


def run(project: Project | str | Path, out: str | Path, settings: DatasetSettings | None = None) -> dict:
    """Write the dataset into ``out`` (atomically; a no-op where ``out`` already holds this export)."""
    from ..io.exif import read_photo_meta
    from ..queries import query_photos

    project = project if isinstance(project, Project) else Project.load(project)
    settings = settings or DatasetSettings()
    settings.formats = check_formats(settings.formats)
    out = Path(out).absolute()
    root = project.paths.root.absolute()
    if out == root or root.is_relative_to(out):
        raise GtkitError("the output folder is the project or holds it: give a folder of its own", out)
    previous = folder.previous_export(out)            # refuses a folder that holds something else, first
    gt = collect(project)
    extra = [f for f, _ in _model_files(project)] if settings.with_model else []
    photos = sorted(set(query_photos(project)) | set(gt.poses))
    version = _version()
    inputs = folder.input_fingerprints(project, photos, extra)
    key = folder.export_key(settings, inputs, version)
    if folder.up_to_date(out, previous, key):
        log.debug("dataset %s is up to date", out)
        return {"out": str(out), "status": "up to date", "n_published": len(gt.poses), "n_kept_out": len(gt.kept_out)}
    metas = {n: read_photo_meta(project.paths.images / n) for n in sorted(gt.poses)}
    header = (f"pseudo-GT poses of the query photos (gtkit {version}); world frame: {project.frame.crs_spec} "
              f"minus origin {list(project.frame.origin)}")
    with folder.staged(out) as tmp:
        parts: dict = {}
        if "kapture" in settings.formats:
            parts["kapture_query"] = kapture_tree.write_query(tmp, project, gt, metas, settings.copy)
            parts["kapture_mapping"] = kapture_tree.write_mapping(tmp, project, settings.copy, settings.depth)
        if "colmap" in settings.formats:
            parts["colmap"] = str(formats.write_colmap(tmp, gt, project.frame).relative_to(tmp))
        if "hloc" in settings.formats:
            parts["hloc"] = {k: str(v.relative_to(tmp)) for k, v in formats.write_hloc(tmp, gt, header).items()}
        if "kapture" in settings.formats:
            parts["image_root"] = str(kapture_tree.image_root(tmp).relative_to(tmp))
        else:                                    # the photos come with the dataset all the same
            parts["image_root"] = "images"
            kapture_tree.transfer([(project.paths.images / n, tmp / "images" / n) for n in gt.poses], settings.copy)
        formats.write_uncertainty(tmp, gt)
        formats.write_kept_out(tmp, gt)
        if settings.with_model:
            kapture_tree.transfer([(f, tmp / rel) for f, rel in _model_files(project)], settings.copy)
            parts["model"] = "model/"
        datasheet.plots(tmp, project, gt)
        sheet = datasheet.sheet(project, gt, parts, settings_dict(settings), version)
        sheet["export"].update(key=key, inputs=inputs)
        sheet["files"] = [f for f in folder.listing(tmp) if "records_data" not in Path(f).parts] + [folder.SHEET_JSON,
                                                                                                     datasheet.SHEET_MD]
        datasheet.write(tmp, sheet, gt)
    log.debug("dataset written to %s: %d poses published, %d kept out", out, len(gt.poses), len(gt.kept_out))
    return {"out": str(out), "status": "written", "n_published": len(gt.poses), "n_kept_out": len(gt.kept_out),
            "formats": list(settings.formats), "kept_out_by_kind": sheet["pseudo_gt"]["kept_out_by_kind"]}
