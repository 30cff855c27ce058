"""Evaluation of the pseudo-GT against what the estimating stages never see: the sample's
``truth/`` poses, and an independent point cloud (e.g. a LAS/LAZ from other software)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..geo import GeoFrame
from ..io.poses import read_covariances, read_poses
from ..pose import Pose
from .poses import medians, pose_errors, recall


def truth_errors(estimated: dict[str, Pose], truth_poses: Path, names: list[str]) -> dict:
    """Per-image errors of ``estimated`` for ``names`` (missing ones flagged) + medians + recall."""
    truth = read_poses(truth_poses)
    names = [n for n in names if n in truth]
    errs = pose_errors(estimated, truth, names)
    return {"per_image": errs, **medians(errs), **recall(errs, ((0.05, 0.05), (0.1, 0.1), (0.5, 0.5), (1.0, 1.0)))}


def sigma_calibration(per_image: dict) -> float | None:
    """Share of registered photos whose position error vs truth is within twice their stated
    position sigma (``sigma_pos_m``, the 1-sigma radius sqrt(trace C)). For errors that follow the
    stated covariance exactly the share is 95.4 % where one axis dominates C and up to 99.3 % where C
    is round (3-D): on the small sample's photos (the camera's depth axis the tightest) a calibrated
    covariance puts 98-99 % there."""
    pairs = [(e["pos_err_m"], e["sigma_pos_m"]) for e in per_image.values()
             if e.get("pos_err_m") is not None and e.get("sigma_pos_m")]
    return float(np.mean([err <= 2 * sig for err, sig in pairs])) if pairs else None


# chi-square (3 degrees of freedom) at 95.45 %, the share of a 1-D Gaussian within 2 sigma
CHI2_3_2SIGMA = 8.0249


def sigma_calibration_ellipsoid(estimated: dict[str, Pose], truth: dict[str, Pose]) -> float | None:
    """Share of photos whose centre error lies inside the 2-sigma ellipsoid of its stated covariance
    (Mahalanobis distance squared <= 8.02): 95.4 % for a calibrated covariance whatever its shape."""
    d2 = []
    for n, p in estimated.items():
        C = p.center_covariance()
        if C is None or n not in truth:
            continue
        e = p.center - truth[n].center
        try:
            d2.append(float(e @ np.linalg.solve(C, e)))
        except np.linalg.LinAlgError:
            continue
    return float(np.mean(np.array(d2) <= CHI2_3_2SIGMA)) if d2 else None


def read_point_cloud(path: Path, frame: GeoFrame, crs: str | None = None) -> np.ndarray:
    """A LAS/LAZ/PLY cloud in the project's local frame; ``crs`` defaults to the file's own CRS,
    else the project's (:func:`gtkit.io.pointcloud.read_point_cloud`)."""
    from ..io.pointcloud import read_point_cloud as read

    return read(path, frame, crs, default_crs=frame.crs_spec).xyz


def cloud_offsets(points: np.ndarray, cloud: np.ndarray, k: int = 8, iterations: int = 15) -> dict:
    """Offsets of ``points`` (gtkit's, local frame) from an independent ``cloud`` (local frame).

    vertical: median over points of (z - median z of the cloud's k nearest neighbours in plan).
    horizontal: point-to-point ICP restricted to a translation: the vertical offset is removed
    first, then repeatedly the median of the 3D nearest-neighbour offsets (x, y) is applied;
    the accumulated (dx, dy) is the horizontal offset of gtkit's points from the cloud.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, float)
    inside = ((pts[:, 0] >= cloud[:, 0].min()) & (pts[:, 0] <= cloud[:, 0].max())
              & (pts[:, 1] >= cloud[:, 1].min()) & (pts[:, 1] <= cloud[:, 1].max()))
    pts = pts[inside]
    if len(pts) < 10:
        raise GtkitError(f"only {len(pts)} of gtkit's points lie over the point cloud's extent")
    t2 = cKDTree(cloud[:, :2])
    _, i2 = t2.query(pts[:, :2], k=k)
    dz = pts[:, 2] - np.median(cloud[i2, 2], axis=1)
    vert = float(np.median(dz))
    t3 = cKDTree(cloud)
    shift = np.array([0.0, 0.0, vert])
    for _ in range(iterations):
        d, i = t3.query(pts - shift)
        step = np.median((pts - shift) - cloud[i], axis=0)
        step[2] = 0.0
        shift[:2] += step[:2]
        if np.linalg.norm(step[:2]) < 1e-4:
            break
    d, _ = t3.query(pts - shift)
    d0, _ = t3.query(pts)
    return {"n_points": int(len(pts)), "vertical_offset_m": vert, "vertical_abs_median_m": float(np.median(np.abs(dz - vert))),
            "horizontal_offset_m": float(np.linalg.norm(shift[:2])), "horizontal_offset_xy_m": [float(shift[0]), float(shift[1])],
            "nn_distance_median_m": float(np.median(d0)), "nn_distance_after_shift_median_m": float(np.median(d)),
            "method": "vertical: median of z minus the median z of the 8 nearest cloud points in plan; horizontal: "
                      "translation-only ICP (median of nearest-neighbour offsets, vertical offset removed first)"}


COVER_SIGMAS = 3.0   # a 1-sigma claim covers an offset within 3 sigma (99 % of a 2-D, 99.7 % of a 1-D Gaussian)


def claim_covers(horizontal_m: float, vertical_m: float, claim: dict) -> dict:
    """Whether a block's measured offset (horizontal, vertical: from truth, check points or an
    independent cloud) lies within ``COVER_SIGMAS`` times the accuracy it claims (the
    georegistration's ``claimed_accuracy`` record, 1 sigma), and by what ratio."""
    rh = horizontal_m / max(claim["h_m"], 1e-9)
    rv = vertical_m / max(claim["v_m"], 1e-9)
    ok = rh <= COVER_SIGMAS and rv <= COVER_SIGMAS
    return {"covered": bool(ok), "horizontal_m": horizontal_m, "vertical_m": vertical_m,
            "ratio_h": round(rh, 2), "ratio_v": round(rv, 2),
            "line": (f"{horizontal_m:.3f} m horizontal / {vertical_m:.3f} m vertical against ~{claim['h_m']:.3g} / "
                     f"~{claim['v_m']:.3g} m claimed ({claim['source']}): "
                     + ("covered" if ok else "NOT covered") + f" ({rh:.2g} / {rv:.2g} sigma)")}


# --- ``gtkit report``: the pseudo-GT report (gtkit.sfm.report) plus the checks made here --------

@dataclass
class ReportSettings:
    point_cloud: str | None = None      # independent LAS/LAZ to compare gtkit's reference points with
    point_cloud_crs: str | None = None  # its CRS when the file does not say (default: the file's, else project's)


def run(project, settings: ReportSettings) -> dict:
    """``reports/gt_report.json`` + ``.md``: the figures of :func:`gtkit.sfm.report.collect`, plus
    errors against ``truth/`` poses (sample sites) and the offset from an independent point cloud."""
    from ..project import Project
    from ..sfm import report
    from ..sfm.blocks import REFERENCE_STAGE
    from ..sfm.guided_clicks import GUIDANCE_FILE, summary_line
    from ..sfm.register import STAGE as REGISTER_STAGE

    from ..project import settings_dict

    project = project if isinstance(project, Project) else Project.load(project)
    P = project.paths
    rep = report.collect(project)
    rep["settings"] = settings_dict(settings)     # what made it (the report stage's settings)
    checks: dict = {"rows": [], "after_table": [], "plots": [], "columns": []}
    truth = P.truth_poses
    if truth.is_file():
        reg_poses = P.poses(REGISTER_STAGE)
        est = read_poses(reg_poses) if rep.get("n_registered") and reg_poses.is_file() else {}
        te = truth_errors(est, truth, sorted(rep["per_image"]))
        rep["median_pos_err_m"], rep["median_rot_err_deg"] = te["median_pos_err_m"], te["median_rot_err_deg"]
        rep["truth_recall"] = {k: v for k, v in te.items() if k.startswith("recall")}
        for n, e in te["per_image"].items():
            rep["per_image"][n].update(e)
        checks["rows"] += [f"| median position error vs truth | {_fmt(rep['median_pos_err_m'])} m |",
                           f"| median rotation error vs truth | {_fmt(rep['median_rot_err_deg'])} ° |"]
        within = sigma_calibration(rep["per_image"])
        if within is not None:
            rep["share_within_2sigma"] = within
            checks["rows"].append(f"| position errors within 2 sigma (calibrated: 95-99 %) | {100 * within:.0f} % |")
        cov_file = P.stage(REGISTER_STAGE) / "covariances.txt"
        if est and cov_file.is_file():
            covs = read_covariances(cov_file)
            ell = sigma_calibration_ellipsoid({n: Pose(p.R, p.t, covs[n]) for n, p in est.items() if n in covs},
                                              read_poses(truth))
            if ell is not None:
                rep["share_within_2sigma_ellipsoid"] = ell
                checks["rows"].append(f"| position errors inside the 2-sigma ellipsoid (calibrated: 95 %) | {100 * ell:.0f} % |")
        if rep.get("reference_block") is not None:
            rp = read_poses(P.poses(REFERENCE_STAGE))
            rt = truth_errors(rp, truth, sorted(rp))
            rep["reference_median_pos_err_m"], rep["reference_median_rot_err_deg"] = rt["median_pos_err_m"], rt["median_rot_err_deg"]
            checks["rows"].append(f"| reference block vs truth | {_fmt(rep['reference_median_pos_err_m'])} m, "
                                  f"{_fmt(rep['reference_median_rot_err_deg'])} ° |")
            claim = ((rep["reference_block"].get("georegistration") or {}).get("claimed_accuracy"))
            if claim:
                from .poses import block_frame_errors

                fe = block_frame_errors(rp, read_poses(truth))
                if fe:
                    cov = rep["claim_vs_truth"] = claim_covers(fe["horizontal_m"], fe["vertical_m"], claim)
                    checks["rows"].append(f"| reference block's offset from truth vs the accuracy it claims | {cov['line']} |")
        checks["plots"].append(("position error vs truth per query photo", "pos_err_m", "gt_pos_err.svg", 0.10))
        checks["columns"] += [("pos_err_m", "pos err m"), ("rot_err_deg", "rot err °")]
    guide = P.stage(REGISTER_STAGE) / GUIDANCE_FILE
    if guide.is_file():
        g = json.loads(guide.read_text())["sequences"]
        rep["guided_clicks"] = {q: {k: v for k, v in s.items() if k != "suggestions"}
                                | {"photos": [x["photo"] for x in s["suggestions"]]} for q, s in g.items()}
        checks["after_table"] += ["", "**Guided clicks** (the clicks expected to cut each sequence's position sigma "
                                  "most; the annotator shows them one by one, `work/register/guided_clicks.json`):", ""]
        checks["after_table"] += [f"- {summary_line(q, s)}" for q, s in sorted(g.items())]
    if settings.point_cloud and rep.get("reference_block") is not None:
        import pycolmap

        rec = pycolmap.Reconstruction(P.stage(REFERENCE_STAGE) / "model")
        pts = np.array([p.xyz for p in rec.points3D.values()])
        cloud = read_point_cloud(Path(settings.point_cloud), project.frame, settings.point_cloud_crs)
        pc = rep["point_cloud_comparison"] = {"cloud": str(settings.point_cloud), **cloud_offsets(pts, cloud)}
        name = Path(pc["cloud"]).name
        checks["rows"] += [f"| vertical offset from {name} | {pc['vertical_offset_m']:+.3f} m (median) |",
                           f"| horizontal offset from {name} | {pc['horizontal_offset_m']:.3f} m "
                           f"(dx {pc['horizontal_offset_xy_m'][0]:+.3f}, dy {pc['horizontal_offset_xy_m'][1]:+.3f}) |"]
        claim = ((rep["reference_block"].get("georegistration") or {}).get("claimed_accuracy"))
        if claim:
            cov = pc["claim"] = claim_covers(pc["horizontal_offset_m"], abs(pc["vertical_offset_m"]), claim)
            checks["rows"].append(f"| offset from {name} vs the accuracy the block claims | {cov['line']} |")
        checks["after_table"] += ["", f"Method: {pc['method']}."]
    return report.write(project, rep, checks)


def _fmt(v, nd=3):
    return "–" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))
