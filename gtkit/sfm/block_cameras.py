"""Which calibration each block's photos start from: cameras.txt, else (query sequences) the reference
block's calibration of the same camera, else one camera per folder that the block calibrates itself.

A query sequence is a handful of photos: a self-calibration from 3-10 photos is the largest error of
its pseudo-GT (issue 55: with the calibrated K the real-truth sets' query errors dropped 5-13x), while
the reference block calibrated the same camera from many. "The same camera":
- EXIF make, model, image size and focal length equal (:func:`gtkit.io.exif.camera_key`);
- photos without EXIF camera identity (no make, model or focal: scanned or stripped photos, the
  real-truth sets) are taken for the reference camera of their size where the reference block has
  exactly one camera of that size without identity either ("same sensor"), and the block record
  says so (``calibration_from_reference``); a second camera of that size leaves them self-calibrated.
The register stage then calibrates a query camera that still had to calibrate itself from the
reference's 3D points its photos see (:mod:`gtkit.sfm.register.joint`, ``refine_query_intrinsics``).
"""
from __future__ import annotations

from pathlib import Path

from ..camera import Camera
from ..errors import GtkitError
from ..io.exif import camera_key, read_photo_meta
from ..io.poses import read_intrinsics
from ..project import Project
from .database import CameraGroup

REFERENCE_STAGE = "sfm_reference"


def _key(project: Project, name: str) -> tuple | None:
    try:
        return camera_key(read_photo_meta(project.paths.images / name, require=()))
    except GtkitError:
        return None


def reference_calibrations(project: Project, names: list[str]) -> tuple[dict[str, Camera], dict[str, str]]:
    """({photo: the reference block's calibration of the same camera}, {photo: by what rule}) for
    photos that are not reference photos (see the module doc)."""
    f = project.paths.intrinsics(REFERENCE_STAGE)
    if not f.is_file():
        return {}, {}
    ref = read_intrinsics(f)
    by_key: dict[tuple, list[Camera]] = {}
    for n, c in sorted(ref.items()):
        k = _key(project, n)
        if k is not None and c not in by_key.setdefault(k, []):
            by_key[k].append(c)
    cams, why = {}, {}
    for n in names:
        k = _key(project, n)
        if k is None or k not in by_key:
            continue
        if k[0] or k[1]:
            cams[n], why[n] = by_key[k][0], "same camera (EXIF make, model, size, focal)"
        elif k[4] is None and len(by_key[k]) == 1:
            cams[n], why[n] = by_key[k][0], "same sensor (no EXIF camera identity; the reference's one camera of this size)"
    return cams, why


def camera_groups(project: Project, names: list[str], positions: dict,
                  calibrations: dict[str, Camera] | None = None) -> list[CameraGroup]:
    """One group per distinct cameras.txt calibration (else ``calibrations``' entry, e.g. the
    reference block's calibration of the same camera); images without either: one group per folder."""
    cams: dict[str, Camera] = read_intrinsics(project.paths.cameras) if project.paths.cameras.is_file() else {}
    cams = {**(calibrations or {}), **cams}
    groups: dict[tuple, CameraGroup] = {}
    for n in names:
        c = cams.get(n)
        key = ("cam", c.model, c.width, c.height, c.params) if c else ("folder", str(Path(n).parent))
        g = groups.setdefault(key, CameraGroup([], c))
        g.names.append(n)
        if n in positions:
            g.positions[n] = positions[n]
    return list(groups.values())
