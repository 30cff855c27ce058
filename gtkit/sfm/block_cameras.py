"""Which calibration each block's photos start from: cameras.txt, else (query sequences) the reference
block's calibration of the same camera, else one camera per folder that the block calibrates itself.

A query sequence is a handful of photos: a self-calibration from 3-10 photos is the largest error of
its pseudo-GT (issue 55: with the calibrated K the real-truth sets' query errors dropped 5-13x), while
the reference block calibrated the same camera from many. "The same camera":
- EXIF make, model, image size and focal length equal (:func:`gtkit.io.exif.camera_key`);
- photos without EXIF camera identity (no make, model or focal: scanned or stripped photos, the
  real-truth sets) are taken for the reference camera of their size where the reference block has
  exactly one camera of that size without identity either ("same sensor"), and the block record
  says so (``calibration_from_reference``); a second camera of that size leaves them self-calibrated
  (the rule: :func:`gtkit.queries.reference_calibrations`, which the register and localization
  stages' :func:`gtkit.queries.query_cameras` follow too).
The register stage then calibrates a query camera that still had to calibrate itself from the
reference's 3D points its photos see (:mod:`gtkit.sfm.register.joint`, ``refine_query_intrinsics``).
"""
from __future__ import annotations

from pathlib import Path

from ..camera import Camera
from ..io.poses import read_intrinsics
from ..project import Project
from .database import CameraGroup

REFERENCE_STAGE = "sfm_reference"


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
