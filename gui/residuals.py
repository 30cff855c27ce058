"""Tie-point residuals after registration, for the annotator's "worst first" list.

Sources, first that exists:

1. ``work/register/tiepoint_residuals.json`` (per tie point, if a stage writes one), in one of
   the shapes ``{"tiepoints": [{"id", "residual_px", "inlier"?, "observations"?: [{"image",
   "residual_px"}]}]}``, ``{"tiepoints": {"tp1": {...} | 1.2}}`` or ``{"tp1": 1.2}``;
2. computed here from the register stage's pseudo-GT poses (``work/register/poses.txt`` +
   ``intrinsics.txt``) and the reference block's poses (``work/sfm_reference/poses.txt`` +
   ``intrinsics.txt``): each tie point is triangulated from all its clicks in posed photos
   (linear least squares), and each click's reprojection error in pixels is its residual;
   the tie point's residual is its largest click residual. Tie points that
   ``work/register/registration.json`` lists under ``bad_tiepoints`` are marked outliers.

No file = no residuals (the list then shows tie points in id order). No Qt here.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gtkit.errors import GtkitError
from gtkit.sfm import registration_record

log = logging.getLogger(__name__)

CANDIDATES = ("tiepoint_residuals.json", "tiepoints_residuals.json")
REGISTER, REFERENCE_BLOCK = "register", "sfm_reference"  # stage names of gtkit.sfm (no pycolmap import here)


@dataclass
class Residual:
    residual_px: float
    inlier: bool | None = None
    per_image: dict[str, float] = field(default_factory=dict)
    reason: str = ""


def residual_file(paths) -> Path | None:
    d = paths.stage(REGISTER)
    return next((d / n for n in CANDIDATES if (d / n).is_file()), None)


def _num(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _one(rec) -> Residual | None:
    if isinstance(rec, (int, float)):
        return Residual(float(rec))
    if not isinstance(rec, dict):
        return None
    per = {}
    for o in rec.get("observations", []) or []:
        if isinstance(o, dict) and "image" in o:
            r = _num(o.get("residual_px", o.get("residual", o.get("error_px"))))
            if r is not None:
                per[str(o["image"])] = r
    r = _num(rec.get("residual_px", rec.get("residual", rec.get("error_px", rec.get("reproj_px")))))
    if r is None and per:
        r = max(per.values())
    if r is None:
        return None
    inl = rec.get("inlier")
    return Residual(r, None if inl is None else bool(inl), per)


def _from_file(f: Path) -> dict[str, Residual]:
    try:
        d = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        log.warning("%s: unreadable tie-point residuals (%s)", f, e)
        return {}
    body = d.get("tiepoints", d) if isinstance(d, dict) else d
    out = {}
    if isinstance(body, list):
        for rec in body:
            if isinstance(rec, dict) and "id" in rec:
                r = _one(rec)
                if r is not None:
                    out[str(rec["id"])] = r
    elif isinstance(body, dict):
        for k, rec in body.items():
            r = _one(rec)
            if r is not None:
                out[str(k)] = r
    return out


def triangulate(cams: list, poses: list, uv: np.ndarray) -> np.ndarray:
    """A 3D point from >= 2 posed pixel observations (linear least squares on rays)."""
    A, b = [], []
    for cam, pose, p in zip(cams, poses, uv):
        d = pose.R.T @ cam.rays(np.asarray(p, float))
        C = pose.center
        M = np.eye(3) - np.outer(d, d)  # distance of X to the ray through C along d
        A.append(M)
        b.append(M @ C)
    return np.linalg.lstsq(np.concatenate(A), np.concatenate(b), rcond=None)[0]


class PosedResiduals:
    """Registered poses and intrinsics loaded once; the residuals of any tie point under them,
    so a click moved after registration shows its new residual at once."""

    def __init__(self, paths):
        from gtkit.io.poses import read_intrinsics, read_poses

        self.poses, self.cams = {}, {}
        self.available = (paths.stage(REGISTER) / "poses.txt").is_file()
        if not self.available:
            return
        for stage in (REFERENCE_BLOCK, REGISTER):
            d = paths.stage(stage)
            if (d / "poses.txt").is_file() and (d / "intrinsics.txt").is_file():
                try:
                    self.poses.update(read_poses(d / "poses.txt"))
                    self.cams.update(read_intrinsics(d / "intrinsics.txt"))
                except GtkitError as e:
                    log.warning("%s", e)

    def residual(self, tp) -> Residual | None:
        obs = [o for o in tp.observations if o.image in self.poses and o.image in self.cams]
        if len(obs) < 2 or not any(o.image.startswith("queries/") for o in obs):
            return None
        cs, ps = [self.cams[o.image] for o in obs], [self.poses[o.image] for o in obs]
        uv = np.array([[o.x, o.y] for o in obs])
        X = triangulate(cs, ps, uv)
        per = {}
        for o, c, p, u in zip(obs, cs, ps, uv):
            proj, front = c.project(p.transform(X[None]))
            per[o.image] = float(np.linalg.norm(proj[0] - u)) if front[0] else float("inf")
        return Residual(max(per.values()), None, per)


def computed_residuals(paths, tiepoints, model: PosedResiduals | None = None) -> dict[str, Residual]:
    """Reprojection residuals of every click under the registered poses (module docstring)."""
    model = model or PosedResiduals(paths)
    if not model.available:
        return {}
    out = {}
    for tp in tiepoints:
        r = model.residual(tp)
        if r is not None:
            out[tp.id] = r
    return out


def read_residuals(paths, tiepoints=(), model: PosedResiduals | None = None) -> dict[str, Residual]:
    """tie-point id -> residual (see the module docstring); empty when there is nothing to show."""
    f = residual_file(paths)
    out = _from_file(f) if f is not None else computed_residuals(paths, tiepoints, model)
    if out:
        bad = registration_record.bad_tiepoints(registration_record.read_registration(paths.registration))
        for tid, info in bad.items():
            if tid in out:
                out[tid].inlier = False
                out[tid].reason = str(info.get("reason", "")) if isinstance(info, dict) else ""
    return out
