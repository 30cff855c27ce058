"""The dataset's plain-text parts: the hloc lists, the COLMAP text model of the queries (pycolmap writes
it), the uncertainty sidecar and the list of photos kept out; and the readers of the sidecar.

Every pose is world-to-camera in the project's world frame (CRS coordinates minus the origin that
``dataset.json`` states), OpenCV camera axes, quaternions ``qw qx qy qz``; intrinsics are COLMAP
camera models with the top-left pixel centre at (0.5, 0.5) (:mod:`gtkit.conventions`). Image names
are paths relative to the image root ``kapture/query/sensors/records_data/``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_text
from ..io.poses import write_intrinsics, write_poses
from ..pose import Pose
from .gt import PublishedGT

HLOC = "hloc"
HLOC_POSES = "pseudo_gt_poses.txt"                  # name qw qx qy qz tx ty tz
HLOC_QUERIES = "queries_with_intrinsics.txt"        # name MODEL W H params...
COLMAP = "colmap"
UNCERTAINTY = "pseudo_gt_uncertainty.txt"           # the sidecar (the formats above have no slot for it)
KEPT_OUT = "kept_out.txt"

UNCERTAINTY_HEADER = """\
# gtkit pseudo-GT uncertainty: one line per published pose (the same photos as hloc/pseudo_gt_poses.txt,
# kapture/query's trajectories and colmap/queries), the same world frame (dataset.json: crs, origin).
# name sigma_pos_m sigma_rot_deg c00 c01 ... c55
#   c: the 6x6 covariance, row-major, of (rotation vector [rad], translation [m]) of the world-to-camera
#      pose x_cam = R x_world + t, for the perturbation R' = exp([dr]_x) R, t' = t + dt
#   sigma_pos_m = sqrt(trace(J C J^T)), J = R^T [-[t]_x, -I]: the camera centre's 1-sigma radius (metres)
#   sigma_rot_deg = degrees(sqrt(trace(C[0:3, 0:3]))): the rotation's 1-sigma angle
"""


def write_hloc(out: Path, gt: PublishedGT, header: str) -> dict[str, Path]:
    d = out / HLOC
    return {"poses": write_poses(d / HLOC_POSES, gt.poses, header=header),
            "queries_with_intrinsics": write_intrinsics(d / HLOC_QUERIES, gt.cameras)}


def write_colmap(out: Path, gt: PublishedGT, frame) -> Path:
    from ..io.colmap_model import write_colmap_model

    return write_colmap_model(out / COLMAP / "queries", {n: Pose(p.R, p.t) for n, p in gt.poses.items()},
                              gt.cameras, frame, binary=False)


def write_uncertainty(out: Path, gt: PublishedGT) -> Path:
    lines = [UNCERTAINTY_HEADER.rstrip("\n")]
    for name in sorted(gt.poses):
        sp, sr = gt.sigma[name]
        lines.append(" ".join([name, repr(sp), repr(sr)] + [repr(float(v)) for v in gt.covariance(name).reshape(-1)]))
    return write_text(out / UNCERTAINTY, "\n".join(lines) + "\n")


def write_kept_out(out: Path, gt: PublishedGT) -> Path:
    lines = ["# query photos kept out of the published pseudo-GT: name<TAB>kind<TAB>reason",
             "# kind: unverified (no usable covariance, or flagged), refused (review.json), not registered"]
    lines += [f"{n}\t{k}\t{why}" for n, (k, why) in sorted(gt.kept_out.items())]
    return write_text(out / KEPT_OUT, "\n".join(lines) + "\n")


def read_uncertainty(path: str | Path) -> dict[str, tuple[float, float, np.ndarray]]:
    """name -> (sigma_pos_m, sigma_rot_deg, 6x6 covariance) from a sidecar this module wrote."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("file not found", path)
    out = {}
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        if len(f) != 39:
            raise GtkitError(f"line {n}: expected 'name sigma_pos_m sigma_rot_deg' and 36 covariance values, "
                             f"got {len(f)} fields", path)
        try:
            v = np.array([float(x) for x in f[1:]])
        except ValueError:
            raise GtkitError(f"line {n} ({f[0]}): not a number", path) from None
        out[f[0]] = (float(v[0]), float(v[1]), v[2:].reshape(6, 6))
    return out


def read_kept_out(path: str | Path) -> dict[str, tuple[str, str]]:
    path = Path(path)
    if not path.is_file():
        return {}
    out = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line and not line.startswith("#"):
            name, kind, why = (line.split("\t") + ["", ""])[:3]
            out[name] = (kind, why)
    return out
