"""COLMAP sparse models (text or binary) <-> gtkit poses and intrinsics, through pycolmap.

COLMAP and gtkit share every convention that matters here: ``cam_from_world`` is gtkit's
world-to-camera pose, camera axes are OpenCV's, and the pixel convention is the same (top-left
pixel centre at (0.5, 0.5)), so parameters and poses are copied unchanged. Coordinates are the
project's world frame (CRS minus the local origin); :func:`write_colmap_model` records that
frame in ``gtkit_frame.json`` beside the model (COLMAP ignores the file), and
:func:`read_colmap_model` refuses a model whose recorded frame differs from the project's.
Only posed (registered) images are read; 3D points are not needed for poses and are not written.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..camera import MODELS, Camera
from ..errors import GtkitError
from ..pose import Pose
from .atomic import write_json

FRAME_FILE = "gtkit_frame.json"


def is_colmap_model(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and any((path / f"cameras.{e}").is_file() and (path / f"images.{e}").is_file()
                                 for e in ("bin", "txt"))


def read_colmap_model(path: str | Path, frame=None) -> tuple[dict[str, Pose], dict[str, Camera]]:
    """Poses and cameras of the registered images of a COLMAP model folder."""
    import pycolmap

    path = Path(path)
    if not is_colmap_model(path):
        raise GtkitError("not a COLMAP model folder (cameras.bin/txt and images.bin/txt missing)", path)
    side = path / FRAME_FILE
    if frame is not None and side.is_file():
        d = json.loads(side.read_text())
        from ..geo import parse_crs

        if not parse_crs(d["crs"], side).equals(frame.crs) or not np.allclose(d["origin"], frame.origin, atol=1e-9):
            raise GtkitError(f"model frame {d['crs']} {d['origin']} differs from the project's "
                             f"{frame.crs_spec} {list(frame.origin)}", side)
    rec = pycolmap.Reconstruction()
    try:
        rec.read(str(path))
    except Exception as e:  # noqa: BLE001 - pycolmap raises plain RuntimeErrors for bad files
        raise GtkitError(f"pycolmap cannot read the model ({str(e).splitlines()[0][:160]})", path) from None
    poses, cams = {}, {}
    for img in rec.images.values():
        if not img.has_pose:
            continue
        rig = img.cam_from_world()
        R, t = rig.rotation.matrix(), np.asarray(rig.translation)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise GtkitError(f"image {img.name}: pose has NaN or infinite values", path)
        cam = rec.cameras[img.camera_id]
        if cam.model.name not in MODELS:
            raise GtkitError(f"image {img.name}: camera model {cam.model.name} is not supported "
                             f"({', '.join(MODELS)})", path)
        try:
            poses[img.name] = Pose(R, t)
        except GtkitError as e:
            raise GtkitError(f"image {img.name}: {e}", path) from None
        cams[img.name] = Camera.from_pycolmap(cam)
    if not poses:
        raise GtkitError("model has no registered images", path)
    return poses, cams


def to_reconstruction(poses: dict[str, Pose], cameras: dict[str, Camera]):
    """A pycolmap.Reconstruction holding one camera per distinct intrinsics and every posed image."""
    import pycolmap

    missing = sorted(set(poses) - set(cameras))
    if missing:
        raise GtkitError(f"no intrinsics for {len(missing)} posed images (e.g. {missing[0]})")
    rec = pycolmap.Reconstruction()
    ids: dict[Camera, int] = {}
    for image_id, name in enumerate(sorted(poses), 1):
        cam = cameras[name]
        if cam not in ids:
            c = cam.to_pycolmap()
            c.camera_id = len(ids) + 1
            rec.add_camera_with_trivial_rig(c)
            ids[cam] = c.camera_id
        img = pycolmap.Image(name=name, camera_id=ids[cam], image_id=image_id)
        rec.add_image_with_trivial_frame(img, poses[name].to_pycolmap())
    return rec


def write_colmap_model(path: str | Path, poses: dict[str, Pose], cameras: dict[str, Camera], frame=None,
                       binary: bool = True) -> Path:
    """Write a COLMAP model folder (binary, or text) that pycolmap and COLMAP's GUI open."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    rec = to_reconstruction(poses, cameras)
    (rec.write_binary if binary else rec.write_text)(str(path))
    if frame is not None:
        write_json(path / FRAME_FILE, {"crs": frame.crs_spec, "origin": list(frame.origin),
                                       "note": "model coordinates = CRS coordinates minus origin (metres)"})
    return path
