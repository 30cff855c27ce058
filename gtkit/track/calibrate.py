"""The rig calibration stage: every query sequence's simultaneous wide/zoom photo pairs ->
``work/rig/rig.json`` (see :mod:`gtkit.track.rig` for the model and the method).

Inputs: the photos, ``cameras.txt`` (the wide camera's calibration, taken as known, and the
zoom camera's nominal one; without a zoom line the nominal focal comes from the EXIF 35 mm
equivalent focal length), and the spec offset of the zoom lens from ``project.toml``
``[rig] offset_m = [x, y, z]`` (wide camera frame, metres; default 0 -- it is not observable
from the photos, see the module docs).
"""
from __future__ import annotations

import logging
from pathlib import Path


from ..camera import Camera
from ..errors import GtkitError
from ..io.exif import read_photo_meta
from ..io.photo import read_photo
from ..io.poses import read_intrinsics
from ..project import IMAGE_EXT, Project, file_fingerprint, mark_stage_done, stage_done, start_stage_clock
from .rig import Rig, RigCalibrationSettings, ZoomSetting, calibrate_pairs

log = logging.getLogger(__name__)

WIDE_SUFFIX, ZOOM_SUFFIX = "_W", "_Z"


def wide_name_for(zoom_name: str) -> str | None:
    """``queries/s1/0003_Z.jpg`` -> ``queries/s1/0003_W.jpg`` (None if not a zoom photo name)."""
    stem, dot, ext = zoom_name.rpartition(".")
    if not stem.endswith(ZOOM_SUFFIX):
        return None
    return stem[: -len(ZOOM_SUFFIX)] + WIDE_SUFFIX + dot + ext


def query_photos(project: Project) -> list[str]:
    P = project.paths
    out = []
    for seq in P.query_sequences():
        for f in sorted((P.query_images / seq).iterdir()):
            if f.suffix.lower() in IMAGE_EXT:
                out.append(f.relative_to(P.images).as_posix())
    return out


def photo_pairs(project: Project) -> list[tuple[str, str]]:
    names = set(query_photos(project))
    return [(wide_name_for(z), z) for z in sorted(names)
            if wide_name_for(z) is not None and wide_name_for(z) in names]


def nominal_zoom(name: str, meta, cams: dict[str, Camera], path: Path) -> Camera:
    if name in cams:
        return cams[name]
    if meta.focal_35mm:
        f = meta.width * meta.focal_35mm / 36.0
        return Camera.pinhole(meta.width, meta.height, f)
    raise GtkitError(f"no nominal calibration for zoom photo {name}: add it to cameras.txt "
                     "(or give the photo an EXIF FocalLengthIn35mmFilm)", path)


def run(project: Project | str | Path, settings: RigCalibrationSettings, force: bool = False) -> Rig:
    project = project if isinstance(project, Project) else Project.load(project)
    P = project.paths
    if len(settings.offset_m) != 3:
        raise GtkitError("[rig] offset_m must be three numbers (metres, wide camera frame)", P.project_toml)
    pairs = photo_pairs(project)
    if not pairs:
        raise GtkitError(f"no wide/zoom photo pairs (<idx>{WIDE_SUFFIX}.jpg + <idx>{ZOOM_SUFFIX}.jpg) "
                         "under images/queries/", P.query_images)
    stage_dir = P.rig.parent
    inputs = {"pairs": len(pairs), "cameras": file_fingerprint(P.cameras),
              "first": pairs[0][1], "last": pairs[-1][1]}
    if not force and P.rig.is_file() and stage_done(stage_dir, settings, inputs):
        log.info("rig: up to date (%s)", P.rig)
        return Rig.load(P.rig)
    start_stage_clock(stage_dir)   # the record's cost (the check above starts it only without a record)
    cams = read_intrinsics(P.cameras) if P.cameras.is_file() else {}
    wide_cams, zoom_group, groups = {}, {}, {}
    init: list[ZoomSetting] = []
    for w, z in pairs:
        if w not in cams:
            raise GtkitError(f"the wide photo {w} has no calibration line (the rig calibration takes the "
                             "wide camera as known)", P.cameras)
        wide_cams[w] = cams[w]
        meta = read_photo_meta(P.images / z)
        key = (meta.width, meta.height, None if meta.focal_mm is None else round(meta.focal_mm, 2))
        if key not in groups:
            groups[key] = len(init)
            init.append(ZoomSetting(nominal_zoom(z, meta, cams, P.cameras), key[2]))
        zoom_group[z] = groups[key]
    rig = calibrate_pairs(pairs, wide_cams, init, zoom_group, settings, lambda n: read_photo(P.images / n))
    rig.info["nominal"] = [s.camera.to_line() for s in init]
    rig.save(P.rig)
    mark_stage_done(stage_dir, settings, inputs, n_pairs=rig.info["n_pairs"], median_px=rig.info["median_px"])
    log.info("rig: %d pairs, %d points, median %.2f px -> %s", rig.info["n_pairs"], rig.info["n_points"],
             rig.info["median_px"], P.rig)
    return rig
