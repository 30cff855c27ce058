"""The reference block held by its camera positions (RTK / GPS, geo.txt) in its own bundle adjustment.

Georegistration moves the mapper's block onto the positions with one Sim(3); the block's shape stays
what the mapper made of it, and a large block bends by centimetres (medium sample, seed 5: camera
centres 5.1 cm from the truth after the best Sim(3)). Here pycolmap's pose-prior bundle adjustment
refines every pose and point again with each photo's position as a prior:

- only photos whose position was a georegistration inlier (an RTK fix lost for a photo stays out);
- per-axis sigma: the position's stated accuracy (geo.txt) where there is one, else the robust
  scatter (1.4826 x MAD) of the block's horizontal and vertical residuals to the positions, never under
  ``min_sigma_m``: centimetre RTK holds the block, metre-grade consumer GPS barely pulls it;
- intrinsics as the mapper left them (the camera model decisions are the mapper's);
- without the points the block cannot place (:func:`drop_unplaceable_points`): a point a metre
  from the cameras of one station (a false match between the photos of a multi-camera rig) or seen
  under a tiny angle made the solver's Schur complement indefinite, so that Ceres failed every other
  step (dense Cholesky) and stopped wherever that left it. Tiny seed 0: 4 such points of 5,876; with
  them, inputs 0.05 mm apart (geo.txt rounded to 0.1 mm) gave blocks 30 mm apart (1.9 mm median),
  51 iterations, 25 failed; without them 0.06 mm (0.02 mm median), 5 iterations, none failed, camera
  error vs the truth 34.0 -> 34.5 mm median, 73.3 -> 73.7 mm worst (docs/benchmarks.md, issue 57).

``hold_by_positions(rec, positions, ...)`` changes ``rec`` in place and returns its report.
"""
from __future__ import annotations

import logging
import time

import numpy as np
import pycolmap

log = logging.getLogger(__name__)


def _residuals(rec: pycolmap.Reconstruction, positions: dict[str, np.ndarray], names: list[str]) -> np.ndarray:
    c = {im.name: im.projection_center() for im in rec.images.values() if im.has_pose}
    return np.array([c[n] - positions[n] for n in names])


def _aligns(rec: pycolmap.Reconstruction, positions: dict[str, np.ndarray], names: list[str],
            ransac: pycolmap.RANSACOptions) -> bool:
    """Whether pycolmap's alignment of the block to the positions of ``names`` succeeds with ``ransac``:
    the similarity its pose-prior BA fits before it adds the priors (none of them where this fails)."""
    return pycolmap.align_reconstruction_to_locations(rec, names, np.array([positions[n] for n in names], np.float64),
                                                      3, ransac) is not None


def _iterations(summary) -> dict:
    """{'steps', 'failed'} of the solve (failed: steps Ceres rejected, e.g. a linear solver failure)."""
    c = getattr(summary, "ceres_summary", None)
    if c is None:
        return {}
    return {"steps": int(c.num_successful_steps + c.num_unsuccessful_steps), "failed": int(c.num_unsuccessful_steps)}


def _scatter(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


# a point nearer its nearest camera than this share of the block's median point-to-nearest-camera
# distance (the flying height for an aerial block): not ground seen from the air (tiny seed 0: 4 points
# 1.2 m from the three photos of one station flying 110 m up, ratio 0.013)
MIN_DEPTH_RATIO = 0.1
# a point whose rays meet under less than this: its depth is barely determined (COLMAP's mapper filters
# at 1.5 deg; small seed 0: 6 points under 2 deg of 40,810 made 12 of 18 steps fail)
MIN_TRI_ANGLE_DEG = 2.0
FUNCTION_TOLERANCE = 1e-7   # the BA's stop (see hold_by_positions)
# ... for blocks of more photos than this; smaller blocks run to COLMAP's own stop (a 1e-4 gradient), which costs
# them under a second: entry-P10 held out every 3rd (7 photos, self-calibrated) stopped at 1e-7 after 7 steps, its
# query photos 16.1 mm off the truth; converged (10 steps) 14.7 mm (docs/benchmarks.md, stop 63)
FULL_CONVERGENCE_UP_TO_PHOTOS = 40
DENSE_UP_TO_PHOTOS = 700    # the BA's linear solver dense up to this many photos (see hold_by_positions)


def _near_points(rec: pycolmap.Reconstruction, min_depth_ratio: float) -> list[int]:
    """Points nearer their nearest camera than ``min_depth_ratio`` x the block's median distance from a
    point to its nearest camera."""
    from scipy.spatial import cKDTree

    centres = np.array([im.projection_center() for im in rec.images.values() if im.has_pose])
    ids = np.fromiter(rec.points3D.keys(), np.int64, rec.num_points3D())
    if len(ids) == 0 or len(centres) == 0:
        return []
    xyz = np.array([rec.points3D[int(i)].xyz for i in ids])
    d, _ = cKDTree(centres).query(xyz)
    return [int(i) for i in ids[d < min_depth_ratio * float(np.median(d))]]


def drop_unplaceable_points(rec: pycolmap.Reconstruction, min_depth_ratio: float = MIN_DEPTH_RATIO,
                            min_tri_angle_deg: float = MIN_TRI_ANGLE_DEG) -> dict:
    """Deletes from ``rec`` the points its cameras cannot place (see the module docstring); returns how
    many, by reason."""
    near = _near_points(rec, min_depth_ratio)
    for pid in near:
        rec.delete_point3D(pid)
    n = rec.num_points3D()
    pycolmap.ObservationManager(rec).filter_points3D_with_small_triangulation_angle(
        min_tri_angle_deg, set(rec.point3D_ids()))
    return {"near_a_photo": len(near), "small_angle": n - rec.num_points3D()}


def moved_off_positions(report: dict) -> bool:
    """Whether :func:`hold_by_positions` moved the block off the positions it was fitted to (its residual
    median more than doubled and up by 5 cm or more): pycolmap's prior alignment with its RANSAC threshold
    left at 0 did so on surveyed blocks (0.069 -> 5.46 m). The block before the BA is then kept."""
    res = report.get("residual_median_m") or {}
    return bool(report.get("applied") and res and res["after"] > max(2.0 * res["before"], res["before"] + 0.05))


def options_refining(refined: dict[int, list[str]]) -> pycolmap.BundleAdjustmentOptions:
    """BA options (no summary printed) refining the lens parameters named in ``refined`` ({camera id:
    "focal", "principal point", "distortion"}) of any camera; the cameras not in it are to be held by the
    BA's config (``set_constant_cam_intrinsics``)."""
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    parts = {p for v in refined.values() for p in v}
    opts.refine_focal_length = "focal" in parts
    opts.refine_principal_point = "principal point" in parts
    opts.refine_extra_params = "distortion" in parts
    return opts


def hold_by_positions(rec: pycolmap.Reconstruction, positions: dict[str, np.ndarray], outliers: set[str],
                      accuracy: dict[str, float] | None = None, min_sigma_m: float = 0.005,
                      max_iterations: int = 50, num_threads: int = -1, seeding: bool = False,
                      sigma_hv: tuple[float, float] | None = None,
                      free_intrinsics: dict[int, list[str]] | None = None) -> dict:
    """Pose-prior BA of a georegistered block (see the module docstring); returns its report.
    ``seeding``: the seeded mapper's seeding BA (gtkit.sfm.seeded), as COLMAP runs it: every point kept
    (they are triangulated from the priors and filtered by the mapper after it), its stop and its choice
    of linear solver (the mapping unchanged by what is tuned here for the georegistration).
    ``sigma_hv``: the priors' horizontal and vertical sigma where a position states no accuracy (default:
    the block's scatter about its positions, as above). ``free_intrinsics``: {camera id: the parts this
    BA refines, "focal", "principal point", "distortion"}; every other camera's intrinsics held (default:
    all held)."""
    accuracy = accuracy or {}
    free_intrinsics = {c: p for c, p in (free_intrinsics or {}).items() if p and c in rec.cameras}
    names = sorted(im.name for im in rec.images.values()
                   if im.has_pose and im.name in positions and im.name not in outliers
                   and np.all(np.isfinite(positions[im.name])))
    if len(names) < 3:
        return {"applied": False, "reason": f"only {len(names)} photos with a usable position"}
    t0 = time.time()
    r0 = _residuals(rec, positions, names)
    sig_h, sig_v = sigma_hv or (max(min_sigma_m, _scatter(r0[:, :2].ravel())), max(min_sigma_m, _scatter(r0[:, 2])))
    # pycolmap's alignment RANSAC: seeded (pycolmap's -1 draws from the calling thread's generator, whose
    # state depends on what ran before in the process: tiny seed 0, three reference SfMs in one process
    # gave three blocks, each separate process the same one; issue 49, gtkit.determinism), its inlier
    # threshold from the positions' own accuracy (3 sigma). Left at 0, pycolmap aligned a surveyed facade
    # block (5 photos a station, 5 mm positions) 5.46 m off them (residual median 0.069 m before; the
    # suite's one xfail until issue 55); with a threshold it is placed where its positions agree: 0.0004 m
    prior_opts = pycolmap.PosePriorBundleAdjustmentOptions()
    ransac = prior_opts.alignment_ransac   # (pycolmap's RANSACOptions() has other defaults)
    ransac.random_seed = 0
    ransac.max_error = 3.0 * max([sig_h, sig_v] + [accuracy[n] for n in names if accuracy.get(n)])
    alignment = {"threshold_m": round(ransac.max_error, 4)}
    if not seeding and not _aligns(rec, positions, names, ransac):
        # where that alignment fails, pycolmap adds none of the priors and the BA runs free. The block is
        # georegistered to these very photos' positions: the alignment keeps every one of them instead
        # (entry-P10's every 2nd photo, K known: a 3-photo block 10-25 mm from its positions at 7.9 mm left
        # 2 of 3 inside 3 sigma; the block was recorded as held while nothing held it)
        inside = int((np.linalg.norm(r0, axis=1) <= ransac.max_error).sum())
        wider = 2.0 * float(np.linalg.norm(r0, axis=1).max())
        ransac.max_error = max(wider, ransac.max_error)
        if not _aligns(rec, positions, names, ransac):
            return {"applied": False, "reason": f"pycolmap could not align the block to its {len(names)} positions "
                                                f"(within {alignment['threshold_m']:.3f} m nor {wider:.3f} m): "
                                                "its pose-prior BA would use none of them"}
        alignment.update(threshold_m=round(ransac.max_error, 4), widened_from_m=alignment["threshold_m"],
                         why=f"pycolmap's alignment failed within 3 sigma ({inside} of {len(names)} photos "
                             f"within it of their positions)")
    dropped = {} if seeding else drop_unplaceable_points(rec)
    priors = []
    by_name = {im.name: im for im in rec.images.values()}
    for n in names:
        sh, sv = (accuracy[n], accuracy[n]) if accuracy.get(n) else (sig_h, sig_v)
        priors.append(pycolmap.PosePrior(
            position=np.asarray(positions[n], np.float64), position_covariance=np.diag([sh ** 2, sh ** 2, sv ** 2]),
            coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN, corr_data_id=by_name[n].data_id))
    opts = options_refining(free_intrinsics)
    opts.ceres.solver_options.max_num_iterations = max_iterations
    # stop once a step changes the cost by less than 1e-7 of itself (COLMAP sets 0: it went on until the
    # gradient was 1e-4): small seed 0 converged in 3 steps instead of 6, 2.8 -> 2.1 CPU s, cameras within
    # 0.064 mm of the full run (tiny: 0.008 mm); at 1e-6 (Ceres' default) up to 1.06 mm
    if not seeding:
        if rec.num_reg_images() > FULL_CONVERGENCE_UP_TO_PHOTOS:
            opts.ceres.solver_options.function_tolerance = FUNCTION_TOLERANCE
        # the reduced camera system solved dense up to DENSE_UP_TO_PHOTOS photos (COLMAP: 50, then sparse):
        # the same blocks (0.0 mm), small seed 0 (120 photos) BA 2.9 -> 2.3 CPU s, medium (650) 29.9 -> 26.7
        opts.ceres.max_num_images_direct_dense_cpu_solver = DENSE_UP_TO_PHOTOS
    opts.ceres.solver_options.num_threads = num_threads
    cfg = pycolmap.BundleAdjustmentConfig()
    for iid in rec.reg_image_ids():
        cfg.add_image(iid)
    for cid in rec.cameras:
        if cid not in free_intrinsics:
            cfg.set_constant_cam_intrinsics(cid)
    summary = pycolmap.create_pose_prior_bundle_adjuster(opts, prior_opts, cfg, priors, rec).solve()
    r1 = _residuals(rec, positions, names)
    rep = {"applied": True, "n_priors": len(names), "n_stated_accuracy": sum(1 for n in names if accuracy.get(n)),
           # the photos with a position left out of the priors (the georegistration's or the mapper's outliers)
           "not_held": sorted(im.name for im in rec.images.values() if im.has_pose and im.name in positions
                              and im.name not in names),
           "sigma_h_m": round(sig_h, 4), "sigma_v_m": round(sig_v, 4), "alignment": alignment,
           "residual_median_m": {"before": round(float(np.median(np.linalg.norm(r0, axis=1))), 4),
                                 "after": round(float(np.median(np.linalg.norm(r1, axis=1))), 4)},
           "points_dropped": dropped, "converged": summary.termination_type == pycolmap.BundleAdjustmentTerminationType.CONVERGENCE,
           "iterations": _iterations(summary), "seconds": round(time.time() - t0, 1)}
    log.info("reference block held by %d positions (sigma %.3f m horizontal, %.3f m vertical): residual median "
             "%.3f -> %.3f m in %.0f s", len(names), sig_h, sig_v, rep["residual_median_m"]["before"],
             rep["residual_median_m"]["after"], rep["seconds"])
    return rep
