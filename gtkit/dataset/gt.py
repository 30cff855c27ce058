"""Which pseudo-GT poses a dataset publishes, with their uncertainty, and which it keeps out and why.

A query photo's pseudo-GT pose (``work/register/poses.txt``) is **published** when it has a usable
6x6 covariance (``work/register/covariances.txt``: finite, symmetric, positive semi-definite), no
record marks it unverified, and no annotator refused it (``review.json``: ``reject`` or
``needs-work``). Every other query photo is **kept out** and listed with its reason:

- ``unverified``: registered, but no covariance (a pose without sigma cannot say how far to trust
  it), or the registration record or the GT report flags it unverified;
- ``refused``: an annotator marked it ``reject`` or ``needs-work``;
- ``not registered``: the registration left it out (the reason is the record's).

Sigma, the one definition (as ``registration.json``'s ``sigma_pos_m`` / ``sigma_rot_deg``):
``sigma_pos_m = sqrt(trace(C_centre))`` with ``C_centre`` the camera centre's 3x3 covariance
(:meth:`gtkit.pose.Pose.center_covariance`), the 1-sigma radius; ``sigma_rot_deg =
degrees(sqrt(trace(C[:3, :3])))``. Only files are read here; nothing under ``truth/``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.atomic import read_json_object
from ..io.poses import COVARIANCES, read_covariances, read_intrinsics, read_poses
from ..pose import Pose
from ..project import Project

REGISTER = "register"
UNVERIFIED, REFUSED, NOT_REGISTERED = "unverified", "refused", "not registered"
REFUSING_VERDICTS = ("reject", "needs-work")


@dataclass
class PublishedGT:
    poses: dict[str, Pose]                      # published: world-to-camera, each with its covariance
    cameras: dict[str, Camera]                  # their intrinsics (the joint BA's)
    sigma: dict[str, tuple[float, float]]       # name -> (sigma_pos_m, sigma_rot_deg)
    kept_out: dict[str, tuple[str, str]] = field(default_factory=dict)   # name -> (kind, reason)
    sequences: dict[str, str] = field(default_factory=dict)              # name -> sequence

    def covariance(self, name: str) -> np.ndarray:
        return self.poses[name].covariance


def sigmas(pose: Pose) -> tuple[float, float]:
    """(sigma_pos_m, sigma_rot_deg) of a pose with a covariance (see the module doc)."""
    return (float(np.sqrt(np.trace(pose.center_covariance()))),
            float(np.degrees(np.sqrt(np.trace(pose.covariance[:3, :3])))))


def usable_covariance(c) -> bool:
    c = np.asarray(c, dtype=np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)) or np.abs(c - c.T).max() > 1e-9 * max(np.abs(c).max(), 1e-300):
        return False
    return bool(np.linalg.eigvalsh(0.5 * (c + c.T)).min() >= -1e-12 * max(np.abs(c).max(), 1e-300))


def _flagged_unverified(info: dict | None) -> str | None:
    """The registration record's word that a photo's pose is unverified (``unverified``: its reason,
    written by gtkit register where the BA gave it no covariance, issue 55), or None."""
    why = (info or {}).get("unverified")
    return f"flagged unverified by the registration ({why})" if why else None


def load_json(path: Path) -> dict:
    """A JSON object file, or {} where it is missing, unreadable or not an object."""
    return read_json_object(path) or {}


def collect(project: Project) -> PublishedGT:
    """The published pseudo-GT of ``project`` and the photos kept out (see the module doc)."""
    from ..queries import query_photos
    from ..review import read_review
    from ..sfm import registration_record as record

    P = project.paths
    poses_file = P.pseudo_gt_poses
    if not poses_file.is_file():
        raise GtkitError("the project has no pseudo-GT (run 'gtkit register DIR' or 'gtkit run DIR' first)", poses_file)
    poses = read_poses(poses_file)
    if not poses:
        raise GtkitError("the pseudo-GT pose file holds no pose (no query photo was registered)", poses_file)
    intr_file = P.intrinsics(REGISTER)
    cams = read_intrinsics(intr_file)
    missing = sorted(set(poses) - set(cams))
    if missing:
        raise GtkitError(f"no intrinsics for {len(missing)} pseudo-GT poses (e.g. {missing[0]})", intr_file)
    cov_file = P.stage(REGISTER) / COVARIANCES
    covs = read_covariances(cov_file) if cov_file.is_file() else {}
    reg = record.read_registration(P.registration) or {}
    images = reg.get("images") or {}
    review = read_review(P.review)
    gt = PublishedGT({}, {}, {})
    for name in sorted(poses):
        gt.sequences[name] = (images.get(name) or {}).get("sequence") or _sequence_of(name)
        verdict = (review.get(name) or {}).get("status")
        flag = _flagged_unverified(images.get(name))
        if verdict in REFUSING_VERDICTS:
            gt.kept_out[name] = (REFUSED, f"marked '{verdict}' in review.json")
        elif flag:
            gt.kept_out[name] = (UNVERIFIED, flag)
        elif name not in covs:
            gt.kept_out[name] = (UNVERIFIED, f"no covariance in {cov_file.relative_to(P.root)}")
        elif not usable_covariance(covs[name]):
            gt.kept_out[name] = (UNVERIFIED, "its covariance is not finite, symmetric, positive semi-definite")
        else:
            p = Pose(poses[name].R, poses[name].t, covs[name])
            gt.poses[name], gt.cameras[name], gt.sigma[name] = p, cams[name], sigmas(p)
    seq_reasons = {q: record.describe(s) for q, s in record.sequences(reg).items() if not record.is_registered(s)}
    for name in query_photos(project):
        if name not in poses:
            seq = _sequence_of(name)
            gt.sequences[name] = seq
            gt.kept_out[name] = (NOT_REGISTERED, seq_reasons.get(seq) or _left_out_reason(reg, name))
    if not gt.poses:
        kinds = sorted({k for k, _ in gt.kept_out.values()})
        raise GtkitError(f"no pseudo-GT pose can be published: all {len(poses)} are kept out ({', '.join(kinds)}; "
                         f"e.g. {next(iter(gt.kept_out))}: {next(iter(gt.kept_out.values()))[1]})", poses_file)
    return gt


def _sequence_of(name: str) -> str:
    parts = Path(name).parts
    return parts[1] if len(parts) > 2 and parts[0] == "queries" else ""


def _left_out_reason(reg: dict, name: str) -> str:
    for s in (reg.get("sequences") or {}).values():
        r = (s.get("left_out_by_sfm") or {}).get(name)
        if r:
            return f"left out by its sequence's SfM and not placed ({r.get('auto_reason') or r.get('reason') or 'no reason recorded'})"
    return "no pseudo-GT pose (not in work/register/poses.txt)"
