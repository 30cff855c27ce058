"""Poses and intrinsics out of a kapture folder, read by the ``kapture`` package's own loader.

A photo's pose is its ``trajectories`` entry (world-to-device, as gtkit's; a rig's pose is turned
into its cameras' by the rig, ``kapture.rigs_remove_inplace``), found through ``records_camera``
(timestamp, camera) -> image path, which becomes the photo's name. Cameras of the COLMAP models
gtkit knows become :class:`gtkit.camera.Camera`; a photo whose camera is of another model has a pose
but no intrinsics. Kapture and gtkit share the pose direction, the quaternion order (w, x, y, z)
and COLMAP's camera models and pixel convention, so values are copied unchanged.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import MODELS, Camera
from ..conventions import quat_to_rotmat
from ..errors import GtkitError
from ..pose import Pose


def kapture_folder(path: str | Path) -> Path | None:
    """The kapture folder at ``path`` (one holding ``sensors/sensors.txt``), else None."""
    p = Path(path)
    return p if (p / "sensors" / "sensors.txt").is_file() else None


def read_kapture_poses(path: str | Path) -> tuple[dict[str, Pose], dict[str, Camera]]:
    """(poses, cameras) by image name of a kapture folder; every photo with a trajectory."""
    import kapture
    import kapture.io.csv as kcsv

    path = Path(path)
    if kapture_folder(path) is None:
        raise GtkitError("not a kapture folder (sensors/sensors.txt missing)", path)
    try:
        k = kcsv.kapture_from_dir(str(path), skip_list=[kapture.Keypoints, kapture.Descriptors, kapture.GlobalFeatures,
                                                        kapture.Matches, kapture.Points3d, kapture.Observations])
    except Exception as e:  # noqa: BLE001 - kapture raises plain errors (ValueError, FileNotFoundError ...) for bad files
        raise GtkitError(f"kapture cannot read the folder ({str(e).splitlines()[0][:160] if str(e) else type(e).__name__})",
                         path) from None
    if not k.trajectories:
        raise GtkitError("the kapture folder has no trajectories (sensors/trajectories.txt)", path)
    if not k.records_camera:
        raise GtkitError("the kapture folder has no records_camera (sensors/records_camera.txt): no image names", path)
    traj = k.trajectories
    if k.rigs and any(dev in k.rigs for _ts, dev, _p in kapture.flatten(traj)):
        traj = kapture.rigs_remove(traj, k.rigs)
    poses, cams = {}, {}
    for ts, sid, name in kapture.flatten(k.records_camera, is_sorted=True):
        p = traj.get(ts, {}).get(sid)
        if p is None or p.r is None or p.t is None:
            continue
        q = np.asarray(p.r_raw, dtype=np.float64)
        try:
            poses[name] = Pose(quat_to_rotmat(q / np.linalg.norm(q)), np.asarray(p.t_raw, dtype=np.float64))
        except GtkitError as e:
            raise GtkitError(f"{name} (timestamp {ts}, {sid}): {e}", path / "sensors" / "trajectories.txt") from None
        s = k.sensors.get(sid)
        if s is not None and getattr(s, "camera_type", None) is not None and s.camera_type.name in MODELS:
            w, h, *params = s.camera_params
            cams[name] = Camera(s.camera_type.name, int(w), int(h), tuple(params))
    if not poses:
        raise GtkitError("no photo of records_camera has a trajectory", path)
    return poses, cams
