"""The two kinds of SfM block: the reference block (oblique photos, georegistered by RTK GPS
and/or GCPs) and one block per query sequence (wide photos; sequential + spatial pairs).

Outputs (``work/sfm_reference/``, ``work/sfm_queries/<seq>/``): ``database.db``, ``model/``
(pycolmap reconstruction), ``poses.txt`` + ``intrinsics.txt`` (gtkit.io.poses formats, project
world frame), ``block.json`` (georegistration, GCP residuals, unregistered images and why); the
reference block also keeps its unplaced mapped models in ``mapped/`` (gtkit.sfm.georeg_step).

A block is two steps: :func:`map_block` (features, pairs, mapper, the final intrinsics BA) and
:func:`place_block` (georegistration, merged models, the hold by positions, the block's files).
The reference block runs them with a fingerprint each (:func:`run_reference`): a GCP click or a
geo.txt edit re-runs only the second (issue 57).

Size: one module for both kinds of block and their settings (``SfmSettings``, read by every stage
that lists photos); its steps live beside it (database, pairs, seeded, georegister, georeg_step,
prior_ba), and ``map_block`` / ``place_block`` tie them.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..determinism import ba_threads, single_thread_mapper
from ..errors import GtkitError
from ..io.atomic import write_json, write_text
from ..io.exif import read_photo_meta
from ..io.poses import INTRINSICS, POSES, write_intrinsics, write_poses
from ..io.gcp_points import points_path
from ..photo_positions import positions_and_accuracy
from ..project import (IMAGE_EXT, Project, cpu_seconds, file_fingerprint, mark_stage_done, settings_dict, settings_key,
                       stage_done, start_stage_clock)
from . import quiet_colmap
from ..progress import progress_bar
from ..queries import QUERY_PATTERN, reference_calibrations
from .block_cameras import REFERENCE_STAGE, camera_groups
from .database import (CameraGroup, FeatureSettings, MatchSettings, build_database, failure_reason,
                       image_diagnostics, match_pairs, read_descriptors)
from .geometry import model_cameras, model_poses
from .georegister import GeoregisterSettings
from .georeg_step import (MappedBlock, block_gcps, georegister_models, load_mapped, mapping_inputs, mapping_key,
                          positions_moved, reusable, save_mapped, stated_gcp_accuracy)
from .prior_ba import hold_by_positions, moved_off_positions
from .pairs import block_pairs
from .reference_report import write_reference_report

log = logging.getLogger(__name__)

QUERIES_STAGE = "sfm_queries"


@dataclass
class SfmSettings:
    features: FeatureSettings = field(default_factory=FeatureSettings)
    matching: MatchSettings = field(default_factory=MatchSettings)
    georegister: GeoregisterSettings = field(default_factory=GeoregisterSettings)
    # auto: cameras.txt calibrations stay fixed; cameras with an EXIF focal get distortion refined,
    # and their focal only where the block's geometry determines it (a flat nadir block cannot tell
    # focal length from flying height); cameras with no focal at all are self-calibrated (focal,
    # distortion, principal point); yes: refine all; no: none (see intrinsics_policy)
    refine_intrinsics: str = "auto"
    gps_priors_in_ba: bool = True     # GPS positions as weak pose priors in the mapper's BA (refined cameras only)
    query_pattern: str = QUERY_PATTERN  # which photos of a query sequence form its block ("*_W.*")
    pair_by_footprint: bool = True    # spatial pairs by where photos look (gimbal), not where they were taken
    gps_prior_sigma_m: float = 5.0    # sigma of the CARTESIAN pose priors (geo.txt accuracy where stated)
    init_min_tri_angle_deg: float = 4.0  # mapper's initial pair (COLMAP: 16; short UAV baselines need less)
    min_tri_angle_deg: float = 1.0       # triangulation/filtering (COLMAP: 1.5)
    # incremental (COLMAP) | global (GLOMAP: rotation averaging + global positioning + BA) | seeded
    # (reference block: each photo starts at its RTK position + gimbal attitude, gtkit.sfm.seeded) | auto:
    # seeded where the reference photos allow it (choose_mapper), else global from
    # GLOBAL_MAPPER_MIN_PHOTOS photos up (see there: never measured to win yet), else incremental
    mapper: str = "auto"
    # the incremental mapper's BA schedule. COLMAP's defaults (global BA each time the model grew by
    # 1.1x in photos or points, 5 rounds of BA + filtering + retriangulation in each, 2 in the local
    # BA after each new photo, every point in the global BA) spent most of a large block's time in
    # BA, which the position-held BA after georegistration (prior_ba) redoes anyway. Medium seed 6
    # (650 photos, idle, same database): mapping 667 -> 362 s, camera centres vs truth after the
    # whole stage 0.0264 / 0.0524 m (median / p95) -> 0.0265 / 0.0546 m (README, Scale)
    mapper_global_ba_ratio: float = 1.5
    mapper_global_ba_refinements: int = 2
    mapper_local_ba_refinements: int = 1
    mapper_ignore_redundant_points: bool = True   # global BA over the points that add coverage (COLMAP option)
    # photos in the local BA after each new photo (COLMAP: 6); the local BA is most of the mapping's time
    # (its set-up checks the whole model each time). Medium seed 6, same database, idle: mapping 571 ->
    # 518 s, camera centres vs truth 0.0264 / 0.0546 / 0.0723 -> 0.0266 / 0.0548 / 0.0731 m (median /
    # p95 / max); small seed 21: 0.0179 / 0.0344 / 0.0419 -> 0.0180 / 0.0339 / 0.0418 m
    mapper_local_ba_images: int = 4
    # a mapper BA with fewer residuals runs on one thread (COLMAP: 50,000; 2,000 on medium: 7 s less
    # a stage, 9 % more CPU)
    mapper_ba_threads_from_residuals: int = 50000
    num_threads: int = 2
    # the mapper and every bundle adjustment of the block on one thread (feature extraction and matching
    # keep num_threads): the same photos and settings give the same block bit for bit (gtkit.determinism:
    # on two threads Ceres sums in the order its threads finish and the mapper's RANSACs race; tiny seeds
    # 0 / 2: blocks 30 mm / 0.8 m apart run to run, pseudo-GT 0.22 / 0.12 m at worst). Its cost:
    # docs/benchmarks.md, "Reproducible poses (issue 49)"
    reproducible: bool = True
    hold_by_positions: bool = True       # reference block: its positions as priors in a BA after georegistration (prior_ba)


def list_images(folder: Path, root: Path, pattern: str = "*") -> list[str]:
    if not folder.is_dir():
        return []
    return sorted(p.relative_to(root).as_posix() for p in folder.glob(pattern)
                  if p.is_file() and p.suffix.lower() in IMAGE_EXT)


def gps_positions(project: Project, names: list[str]) -> dict[str, np.ndarray]:
    """Local-frame camera positions: from geo.txt where present, else EXIF GPS + DJI altitude."""
    return gps_positions_and_accuracy(project, names)[0]


def gps_positions_and_accuracy(project: Project, names: list[str], metas: dict | None = None
                               ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Camera positions (geo.txt first, else EXIF GPS + DJI altitude) and, where geo.txt states
    one, each position's accuracy: :func:`gtkit.photo_positions.positions_and_accuracy`, the one reader."""
    return positions_and_accuracy(project, names, metas)


def _meta(project: Project, name: str, metas: dict | None):
    """A photo's metadata from ``metas`` where read already, else read now (an unreadable photo: GtkitError)."""
    m = (metas or {}).get(name)
    return m if m is not None else read_photo_meta(project.paths.images / name, require=())


def photo_metas(project: Project, names: list[str]) -> dict:
    """{photo: PhotoMeta} (gimbal attitude, capture time, relative altitude) of the readable photos."""
    out = {}
    for n in names:
        try:
            out[n] = read_photo_meta(project.paths.images / n, require=())
        except GtkitError:
            continue
    return out


def pairing_positions(project: Project, names: list[str], centres: dict[str, np.ndarray],
                      max_range_factor: float = 3.0, metas: dict | None = None) -> dict[str, np.ndarray]:
    """Where each photo looks: the camera centre moved along the optical axis (DJI gimbal angles)
    to the ground (height above ground from DJI RelativeAltitude). Oblique photos that see the
    same ground are then neighbours for spatial pairing even when taken far apart. Photos without
    gimbal angles or relative altitude keep their camera centre."""
    from ..conventions import dji_to_rotation

    out = dict(centres)
    for n in names:
        if n not in centres:
            continue
        m = _meta(project, n, metas)
        if not m.has_gimbal or m.rel_alt is None or m.rel_alt <= 0:
            continue
        d = dji_to_rotation(m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll).T @ np.array([0.0, 0.0, 1.0])
        r = m.rel_alt / max(-d[2], 1.0 / max_range_factor)
        out[n] = centres[n] + d * r
    return out


def _inputs(project: Project, names: list[str]) -> dict:
    P = project.paths
    return {"images": {n: file_fingerprint(P.images / n) for n in names},
            "cameras": file_fingerprint(P.cameras), "gcp_list": file_fingerprint(P.gcp_list),
            "geo_txt": file_fingerprint(P.geo_txt), "crs": [project.frame.crs_spec, list(project.frame.origin)]}


def _gcp_clicks_in(project: Project, names: list[str]) -> list:
    """The GCP clicks in ``names`` (a query sequence's photos): all a sequence's block reads of
    gcp_list.txt, so a click in a reference photo does not re-run the sequences' SfM."""
    gcps = block_gcps(project, names)
    return sorted([g.name, c.image, round(c.x, 3), round(c.y, 3), [round(float(v), 4) for v in g.xyz]]
                  for g in gcps for c in g.clicks if c.image in set(names))


def _camera_ids(db: Path, groups: list[CameraGroup]) -> tuple[set[int], set[int], set[int]]:
    """(every camera id, those from cameras.txt, those with neither cameras.txt nor an EXIF focal)."""
    calibrated, no_prior = set(), set()
    with pycolmap.Database.open(db) as d:
        by_name = {im.name: im.camera_id for im in d.read_all_images()}
        cams = {c.camera_id: c for c in d.read_all_cameras()}
    for g in groups:
        ids = {by_name[n] for n in g.names if n in by_name}
        if g.camera is not None:
            calibrated |= ids
        else:
            no_prior |= {i for i in ids if not cams[i].has_prior_focal_length}
    return set(cams), calibrated, no_prior


MAPPERS = ("incremental", "global", "seeded", "auto")
# ``mapper = "auto"`` uses GLOMAP from this many photos up; None: never. Measured (README, "Scale"),
# same feature database per seed, small preset (120 photos), seeds 1 and 2: both registered 120/120;
# mapping CPU 104 / 103 s global vs 54 / 68 s incremental; camera centres vs truth median 0.020 /
# 0.020 m global vs 0.022 / 0.026 m incremental, worst 0.098 / 0.055 vs 0.051 / 0.067 m. Medium
# (650 photos, seed 5): global 903 CPU s of mapping, 0.041 / 0.433 m (median / worst); incremental
# 0.051 / 0.169 m in at most 878 CPU s (439 s wall idle, 2 threads). Never cheaper, worst camera
# worse at size: auto = incremental until global is measured to win (large not measured).
GLOBAL_MAPPER_MIN_PHOTOS: int | None = None


def choose_mapper(mapper: str, n_images: int, seedable: tuple[bool, str] | None = None) -> tuple[str, str]:
    """(the mapper a block of ``n_images`` photos gets, why: one line). ``seedable``: what
    :func:`gtkit.sfm.seeded.seeding_check` says of a reference block (None: not a candidate).
    ``auto``: seeded where every photo carries an RTK-grade position and a gimbal attitude (the seeding
    measures the rest and may still hand the block to the incremental mapper), else incremental."""
    if mapper not in MAPPERS:
        raise GtkitError(f"unknown sfm.mapper {mapper!r} (choose from {', '.join(MAPPERS)})")
    if mapper != "auto":
        if mapper == "seeded" and seedable is None:
            return "incremental", "sfm.mapper = seeded, but only the reference block is seeded"
        if mapper == "seeded" and not seedable[0]:
            return "incremental", f"sfm.mapper = seeded, but the photos cannot seed the block: {seedable[1]}"
        return mapper, "set by sfm.mapper"
    if seedable is not None and seedable[0]:
        return "seeded", f"auto: {seedable[1]}"
    if GLOBAL_MAPPER_MIN_PHOTOS is not None and n_images >= GLOBAL_MAPPER_MIN_PHOTOS:
        return "global", f"auto: {n_images} photos (global from {GLOBAL_MAPPER_MIN_PHOTOS})"
    return "incremental", "auto: " + (f"not seeded: {seedable[1]}" if seedable is not None else "not a seedable block")


def incremental_options(settings: SfmSettings, policy: dict) -> pycolmap.IncrementalPipelineOptions:
    """The incremental mapper's options (also the seeded mapper's triangulation, filtering and absolute pose)."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = settings.num_threads
    opts.random_seed = 0
    opts.ba_refine_focal_length = policy["refine_focal"]
    opts.ba_refine_extra_params = policy["refine_distortion"]
    opts.ba_refine_principal_point = False
    opts.mapper.abs_pose_refine_focal_length = policy["refine_focal"]
    opts.mapper.abs_pose_refine_extra_params = policy["refine_distortion"]
    if policy["constant_cameras"]:
        opts.constant_cameras = set(policy["constant_cameras"])
    if policy["gps_priors_in_ba"]:
        opts.use_prior_position = True
        opts.use_robust_loss_on_prior_position = True
    opts.min_model_size = 3
    opts.ba_global_frames_ratio = opts.ba_global_points_ratio = settings.mapper_global_ba_ratio
    opts.mapper.ba_global_ignore_redundant_points3D = settings.mapper_ignore_redundant_points
    opts.ba_global_max_refinements = settings.mapper_global_ba_refinements
    opts.ba_local_max_refinements = settings.mapper_local_ba_refinements
    opts.mapper.ba_local_num_images = settings.mapper_local_ba_images
    opts.ba_min_num_residuals_for_cpu_multi_threading = settings.mapper_ba_threads_from_residuals
    opts.mapper.init_min_tri_angle = settings.init_min_tri_angle_deg
    opts.mapper.filter_min_tri_angle = settings.min_tri_angle_deg
    opts.triangulation.min_angle = settings.min_tri_angle_deg
    return single_thread_mapper(opts, settings.reproducible)


def _map(db: Path, image_root: Path, out: Path, settings: SfmSettings, policy: dict, n_images: int,
         label: str, priors: dict | None = None) -> tuple[list[pycolmap.Reconstruction], dict]:
    """Incremental, global or seeded mapping (``settings.mapper``, :func:`choose_mapper`); every model
    found, largest first, and what ran and why (block.json's ``mapper``). ``priors``: the reference
    block's {"names", "positions", "accuracy", "metas"} (seeded candidates only). Progress: photos
    registered so far (the global and seeded mappers report once, at the end)."""
    from .seeded import seeded_mapping, seeding_check

    seedable = (seeding_check(priors["names"], priors["positions"], priors["accuracy"], priors["metas"])
                if priors is not None else None)
    if seedable is not None and seedable[0] and (policy["refine_focal"] or policy["refine_distortion"]):
        # measured (tiny seed 0 without cameras.txt, EXIF focal 4 % off): the positions and the fixed wrong
        # focal length disagree, the seeded block bends (0.30 / 0.65 m), and refining the focal length
        # afterwards does not mend it
        seedable = (False, "its cameras are calibrated while mapping (no cameras.txt calibration for every "
                           "reference camera): seeding needs known intrinsics")
    name, why = choose_mapper(settings.mapper, n_images, seedable)
    record = {"name": name, "why": why}
    if name == "global":
        return _map_global(db, image_root, out, settings, policy, n_images, label), record
    opts = incremental_options(settings, policy)
    if name == "seeded":
        s = seeded_mapping(db, priors["names"], priors["positions"], priors["accuracy"], priors["metas"], opts,
                           num_threads=ba_threads(settings.num_threads, settings.reproducible))
        record["seeded"] = s.record
        if s.rec is not None:
            record["prior_outliers"] = sorted(s.outliers)
            return [s.rec], record
        record.update(name="incremental", why=f"seeding refused: {s.record['fallback']}")
    out.mkdir(parents=True, exist_ok=True)
    bar = progress_bar(n_images, f"{label}: photos registered")
    models = pycolmap.incremental_mapping(db, image_root, out, options=opts,
                                          initial_image_pair_callback=lambda: bar.update(2),
                                          next_image_callback=lambda: bar.update(1))
    bar.close()
    return sorted(models.values(), key=lambda r: -r.num_reg_images()), record


def _map_global(db: Path, image_root: Path, out: Path, settings: SfmSettings, policy: dict, n_images: int,
                label: str) -> list[pycolmap.Reconstruction]:
    """GLOMAP (``pycolmap.global_mapping``). Its BA refines intrinsics of every camera or of none
    (no per-camera constants): with any fixed camera (cameras.txt) none is refined here; the final
    BA of :func:`build_block` still refines the free ones. GPS priors do not enter its BA."""
    opts = pycolmap.GlobalPipelineOptions()
    # reproducible: on one thread (rotation averaging, positioning and BA all run Ceres); not measured
    opts.num_threads = ba_threads(settings.num_threads, settings.reproducible)
    opts.random_seed = 0
    opts.min_num_matches = settings.matching.min_num_inliers
    opts.min_model_size = 3
    opts.mapper.num_threads = opts.num_threads
    opts.mapper.random_seed = 0
    opts.mapper.min_tri_angle_deg = settings.min_tri_angle_deg
    opts.mapper.retriangulation.min_angle = settings.min_tri_angle_deg
    ba = opts.mapper.bundle_adjustment
    free = not policy["constant_cameras"]
    ba.refine_focal_length = bool(policy["refine_focal"]) and free
    ba.refine_extra_params = bool(policy["refine_distortion"]) and free
    ba.refine_principal_point = False
    ba.ceres.use_gpu = False
    opts.mapper.global_positioning.use_gpu = False
    out.mkdir(parents=True, exist_ok=True)
    bar = progress_bar(n_images, f"{label}: photos registered (global mapper)")
    models = pycolmap.global_mapping(db, image_root, out, options=opts)
    bar.update(sum(r.num_reg_images() for r in models.values()))
    bar.close()
    return sorted(models.values(), key=lambda r: -r.num_reg_images())


def _final_bundle_adjustment(rec: pycolmap.Reconstruction, free: set[int], principal_point: set[int],
                             num_threads: int = -1) -> None:
    """One global BA refining focal + distortion of the cameras in ``free`` (and the principal point
    of those in ``principal_point``, which had no calibration prior at all); the others constant."""
    for cams, pp in ((free - principal_point, False), (principal_point, True)):
        if not cams:
            continue
        opts = pycolmap.BundleAdjustmentOptions()
        opts.refine_focal_length = True
        opts.refine_principal_point = pp
        opts.refine_extra_params = True
        opts.ceres.solver_options.num_threads = num_threads
        config = pycolmap.BundleAdjustmentConfig()
        for iid in rec.reg_image_ids():
            config.add_image(iid)
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
        for cid in rec.cameras:
            if cid not in cams:
                config.set_constant_cam_intrinsics(cid)
        pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()


def focal_observable(rec: pycolmap.Reconstruction, min_spread_deg: float = 20.0, min_relief: float = 0.25) -> dict:
    """Whether the block's geometry tells focal length from distance: views in several directions
    (largest angle between optical axes) or relief (depth range over median depth in a photo).
    A flat, nadir-only block does not: a longer focal length and a higher flight fit it equally."""
    axes, relief = [], []
    for im in rec.images.values():
        if not im.has_pose:
            continue
        T = im.cam_from_world()
        R = T.rotation.matrix()
        axes.append(R.T @ np.array([0.0, 0.0, 1.0]))
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()]
        if len(ids) >= 20:
            X = np.array([rec.points3D[i].xyz for i in ids[:2000]])
            z = (X @ R.T + T.translation)[:, 2]
            med = float(np.median(z))
            if med > 0:
                relief.append(float((np.percentile(z, 90) - np.percentile(z, 10)) / med))
    A = np.array(axes)
    spread = float(np.degrees(np.arccos(np.clip((A @ A.T).min(), -1, 1)))) if len(A) > 1 else 0.0
    rel = float(np.median(relief)) if relief else 0.0
    return {"observable": spread >= min_spread_deg or rel >= min_relief, "axis_spread_deg": spread, "relief": rel}


def merge_models(models: list[pycolmap.Reconstruction]) -> pycolmap.Reconstruction:
    """Models already in one frame (georegistered) joined into the first: cameras, posed images,
    3D points with their tracks. Cameras shared by two models keep the first model's intrinsics."""
    base = models[0]
    for m in models[1:]:
        for cid, cam in m.cameras.items():
            if not base.exists_camera(cid):
                base.add_camera_with_trivial_rig(cam)
        added = set()
        for iid, im in m.images.items():
            if not im.has_pose or base.exists_image(iid):  # models may share a few photos: keep the first's
                continue
            kp = np.array([p.xy for p in im.points2D]).reshape(-1, 2)
            base.add_image_with_trivial_frame(pycolmap.Image(name=im.name, keypoints=kp, camera_id=im.camera_id,
                                                             image_id=iid), im.cam_from_world())
            added.add(iid)
        for p in m.points3D.values():
            els = [el for el in p.track.elements if el.image_id in added]
            if len(els) < 2:
                continue
            track = pycolmap.Track()
            for el in els:
                track.add_element(el.image_id, el.point2D_idx)
            base.add_point3D(p.xyz, track, p.color)
    return base


def intrinsics_policy(settings: SfmSettings, calibrated: set[int], no_prior: set[int], all_ids: set[int],
                      n_gps: int) -> dict:
    """What the bundle adjustments refine.

    ``auto``: cameras.txt calibrations stay fixed. Cameras with no focal at all are self-calibrated:
    focal and distortion while mapping, then the principal point in a final BA. Cameras with an EXIF
    focal get distortion refined while mapping; their focal is refined in a final BA only where the
    block's geometry determines it (:func:`focal_observable`: a flat nadir block keeps the EXIF focal).
    GPS positions are weak pose priors in the mapper's BA whenever intrinsics are refined.
    ``yes``: refine focal + distortion of every camera; ``no``: refine none."""
    mode = settings.refine_intrinsics
    refined = set() if mode == "no" else (set(all_ids) if mode == "yes" else set(all_ids) - calibrated)
    self_cal = (no_prior & refined) if mode == "auto" else set()
    return {"mode": mode, "refine_focal": bool(self_cal) or (mode == "yes" and bool(refined)),
            "refine_distortion": bool(refined), "constant_cameras": set(all_ids) - refined,
            "exif_focal": (refined - self_cal) if mode == "auto" else set(),
            "gps_priors_in_ba": bool(refined) and n_gps >= 3 and settings.gps_priors_in_ba,
            "self_calibrate": self_cal}


def _refined_parts(cid: int, policy: dict, focal_check: dict | None) -> list[str]:
    if cid in policy["constant_cameras"]:
        return []
    if cid in policy["self_calibrate"]:
        return ["focal", "principal point", "distortion"]
    if cid in policy["exif_focal"]:
        return (["focal"] if focal_check and focal_check["observable"] else []) + ["distortion"]
    return ["focal", "distortion"] if policy["refine_focal"] else ["distortion"]


@dataclass
class BlockResult:
    rec: pycolmap.Reconstruction | None
    summary: dict


def _step(label: str, what: str, t0: float) -> float:
    t = time.time()
    log.info("%s: %s in %.1f s", label, what, t - t0)
    return t


def _feature_database(project: Project, names: list[str], out: Path, kind: str, settings: SfmSettings, label: str,
                      executor, groups, look: dict, accuracy: dict, t0: float):
    """The block's features and verified matches in ``out/database.db``, reused when nothing that made
    them changed (``database.key``). Returns (reused, pair strategies, number of pairs, (time, CPU)
    after the features)."""
    P = project.paths
    db = out / "database.db"
    m = settings.matching
    # features + matches are reused when nothing that made them changed (mapping settings may)
    db_key = settings_key({"features": settings_dict(settings.features), "matching": settings_dict(m), "kind": kind,
                           "sigma": settings.gps_prior_sigma_m, "accuracy": accuracy, "pairs_version": 2,
                           "look": {n: [round(float(v), 3) for v in x] for n, x in look.items()},
                           "images": {n: file_fingerprint(P.images / n) for n in names},
                           "groups": [[g.names, g.camera.to_line() if g.camera else None,
                                       {n: [round(float(v), 3) for v in x] for n, x in g.positions.items()}]
                                      for g in groups]})
    key_file = out / "database.key"
    reuse = db.is_file() and key_file.is_file() and key_file.read_text().strip() == db_key
    pairs_used = ["reused"]
    n_pairs = None
    if not reuse:
        key_file.unlink(missing_ok=True)
        from ..localize.executors import make_executor

        ex = make_executor(executor) if executor is not None else None
        try:
            bar = progress_bar(len(names), f"{label}: features")
            build_database(db, P.images, groups, settings.features, settings.gps_prior_sigma_m,
                           progress=bar.update, accuracy=accuracy, executor=ex)
            bar.close()
        except BaseException:
            if ex is not None:
                ex.close()
            raise
    t_feat, c_feat = _step(label, f"features of {len(names)} photos", t0), cpu_seconds()
    if not reuse:
        try:
            pairs, pairs_used = block_pairs(
                names, look, lambda: read_descriptors(db), kind=kind, exhaustive_max=m.exhaustive_max_images,
                exhaustive_max_without_gps=m.exhaustive_max_without_gps, spatial_k=m.spatial_neighbors,
                spatial_max_m=m.spatial_max_distance_m, retrieval_k=m.retrieval_neighbors,
                retrieval_always=m.retrieval_always, sequential_overlap=m.sequential_overlap if kind == "sequence" else 0)
            n_pairs = len(pairs)
            bar = progress_bar(len(pairs), f"{label}: pairs matched ({'+'.join(pairs_used)})")
            match_pairs(db, pairs, m, out, progress=bar.update, executor=ex)
            bar.close()
        finally:
            if ex is not None:
                ex.close()
        write_text(key_file, db_key + "\n")
        write_json(out / "pairs.json", {"strategies": pairs_used, "n_pairs": n_pairs})
    elif (out / "pairs.json").is_file():
        import json
        pj = json.loads((out / "pairs.json").read_text())
        pairs_used, n_pairs = pj["strategies"], pj["n_pairs"]
    return reuse, pairs_used, n_pairs, (t_feat, c_feat)


def _duplicate_models(models_info: list[dict]) -> dict[int, int]:
    """The mapper may rebuild part of the block as another model (up to 20 shared photos): a model
    whose photos are all in a larger one adds nothing. {model: the model holding all its photos}."""
    duplicate = {}
    for k, info in enumerate(models_info):
        for j in range(k):
            if j not in duplicate and set(info["photos"]) <= set(models_info[j]["photos"]):
                duplicate[k] = j
                break
    return duplicate


def _hold_by_positions(rec, kind: str, settings: SfmSettings, summary: dict, positions: dict, accuracy: dict,
                       mapper_record: dict):
    """The reference block held by its positions in a pose-prior BA where they can hold its shape (see
    :mod:`gtkit.sfm.prior_ba`); a BA that moves it off them is undone. Returns the block."""
    geo = summary.get("georegistration", {})
    if (kind == "reference" and settings.hold_by_positions and "error" not in geo and geo.get("n_gps", 0) >= 3
            and (geo.get("fit", {}).get("mode") == "gravity-held"
                 or (geo.get("fit", {}).get("mode") == "combined" and (geo.get("gps_quality") or {}).get("bias_assumed")))):
        summary["held_by_positions"] = {"applied": False, "reason": "positions too coarse to hold the block's shape "
                                        "(its tilt is held by gravity)"}
    elif kind == "reference" and settings.hold_by_positions and "error" not in geo and geo.get("n_gps", 0) >= 3:
        # a photo the seeded mapper found off its prior stays out of the priors, even inside the Sim(3)'s threshold
        before_ba = pycolmap.Reconstruction(rec)
        held = hold_by_positions(rec, positions, set(geo.get("outliers", []))
                                 | set(mapper_record.get("prior_outliers", [])), accuracy,
                                 num_threads=ba_threads(settings.num_threads, settings.reproducible))
        if moved_off_positions(held):   # keep the georegistered block as it was, and say so
            res = held["residual_median_m"]
            rec = before_ba
            held = {**held, "applied": False, "reverted": True,
                    "reason": f"the pose-prior BA moved the block off its positions (residual median "
                              f"{res['before']:.3f} -> {res['after']:.3f} m): the georegistered block kept"}
            log.warning("reference block: %s", held["reason"])
        summary["held_by_positions"] = held
    return rec


def _unregistered_reasons(diag: dict, names: list[str], registered: set, models_info: list[dict], summary: dict,
                          min_num_inliers: int) -> dict[str, str]:
    """Why each photo not in the block is not: in another model (and why that one was not kept), off its
    seeded prior, or its matches (``diag``: :func:`~gtkit.sfm.database.image_diagnostics`)."""
    in_other = {n: info for info in models_info if not info["kept"] for n in info["photos"]}
    unregistered = {}
    for n in names:
        if n in registered:
            continue
        if n in in_other:
            i = in_other[n]
            # the model's own reason is stated once, with the models; its photos point to it
            unregistered[n] = (f"in model {i['model']} ({i['n_registered']} photos), "
                               + ("not placed in the world (why: see model " + str(i["model"]) + ")"
                                  if i["reason"].startswith("not placed in the world") else i["reason"]))
        elif n in summary.get("seeded", {}).get("not_registered", {}):
            unregistered[n] = "its prior pose does not fit the block: " + summary["seeded"]["not_registered"][n]
        else:
            unregistered[n] = failure_reason(diag.get(n, {"keypoints": 0, "verified_pairs": 0, "best_inliers": 0}),
                                             min_num_inliers)
    return unregistered


def _write_block_model(out: Path, rec, kind: str, summary: dict, label: str) -> None:
    """The block's model, poses and intrinsics; a reference block not placed in the world is kept apart
    (``unplaced_model/``, for inspection) so that no later stage builds on it."""
    if kind == "reference" and "error" in summary.get("georegistration", {}):
        import shutil

        for f in (POSES, INTRINSICS):
            (out / f).unlink(missing_ok=True)
        shutil.rmtree(out / "model", ignore_errors=True)
        (out / "unplaced_model").mkdir(exist_ok=True)
        rec.write(out / "unplaced_model")
    else:
        (out / "model").mkdir(exist_ok=True)
        rec.write(out / "model")
        write_poses(out / POSES, model_poses(rec), header=f"{label}: {summary['frame']}")
        write_intrinsics(out / INTRINSICS, model_cameras(rec))


def _block_priors(project: Project, names: list[str], kind: str, settings: SfmSettings, metas: dict | None = None):
    """(metas, positions, accuracy, the reference block's seeding verdict or None): what the photos'
    headers and geo.txt say, read once for the mapping and the georegistration."""
    from .seeded import seeding_check

    metas = photo_metas(project, names) if metas is None else metas
    positions, accuracy = gps_positions_and_accuracy(project, names, metas)
    seedable = seeding_check(names, positions, accuracy, metas) if kind == "reference" else None
    return metas, positions, accuracy, seedable


def map_block(project: Project, names: list[str], out: Path, kind: str, settings: SfmSettings, label: str,
              executor=None, priors: tuple | None = None) -> MappedBlock:
    """The mapping step: features, pairs, the mapper and the final intrinsics BA; the models unplaced,
    largest first, with their record (:class:`~gtkit.sfm.georeg_step.MappedBlock`). ``priors``: what
    :func:`_block_priors` read (None: read now)."""
    P = project.paths
    out.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.time(), cpu_seconds()
    metas, positions, accuracy, _ = priors or _block_priors(project, names, kind, settings)
    look = pairing_positions(project, names, positions, metas=metas) if settings.pair_by_footprint else positions
    from_ref, from_ref_why = reference_calibrations(project, names) if kind == "sequence" else ({}, {})
    groups = camera_groups(project, names, positions, from_ref)
    db = out / "database.db"
    reuse, pairs_used, n_pairs, (t_feat, c_feat) = _feature_database(
        project, names, out, kind, settings, label, executor, groups, look, accuracy, t0)
    t_match, c_match = _step(label, f"matching ({n_pairs} pairs)", t_feat), cpu_seconds()
    all_ids, calibrated, no_prior = _camera_ids(db, groups)
    policy = intrinsics_policy(settings, calibrated, no_prior, all_ids, len(positions))
    map_priors = ({"names": names, "positions": positions, "accuracy": accuracy, "metas": metas}
                  if kind == "reference" else None)
    models, mapper_record = _map(db, P.images, out / "mapper", settings, policy, len(names), label, map_priors)
    t_map = _step(label, f"mapping ({sum(r.num_reg_images() for r in models)} photos in {len(models)} models)", t_match)
    c_map = cpu_seconds()
    summary = {"block": label, "reused_database": reuse, "n_images": len(names), "pairings": pairs_used,
               "n_pairs": n_pairs, "n_cameras": len(groups), "n_gps": len(positions),
               "intrinsics_policy": {"mode": policy["mode"], "refined_focal": policy["refine_focal"],
                                     "refined_distortion": policy["refine_distortion"],
                                     "refined_principal_point": bool(policy["self_calibrate"]),
                                     "gps_priors_in_ba": policy["gps_priors_in_ba"],
                                     "fixed_cameras": sorted(policy["constant_cameras"]),
                                     "self_calibrated_cameras": sorted(policy["self_calibrate"])}}
    if from_ref_why:   # photos that start from the reference block's calibration, and by what rule
        summary["calibration_from_reference"] = {r: sorted(n for n, w in from_ref_why.items() if w == r)
                                                 for r in sorted(set(from_ref_why.values()))}
    summary["mapper"] = mapper_record["name"]
    summary["mapper_why"] = mapper_record["why"]
    if "seeded" in mapper_record:
        summary["seeded"] = mapper_record["seeded"]
    focal_check = None
    for k, r in enumerate(models):
        free = set(policy["self_calibrate"])
        if policy["exif_focal"]:
            fo = focal_observable(r)
            if k == 0:
                focal_check = fo
            if fo["observable"]:
                free |= policy["exif_focal"]
        if free:
            _final_bundle_adjustment(r, free & set(r.cameras), policy["self_calibrate"],
                                     ba_threads(settings.num_threads, settings.reproducible))
    if focal_check is not None:
        summary["intrinsics_policy"]["exif_focal_check"] = focal_check
        summary["intrinsics_policy"]["exif_focal_refined"] = focal_check["observable"]
    models_info = [{"model": k, "n_registered": r.num_reg_images(), "n_points3D": r.num_points3D(),
                    "photos": sorted(im.name for im in r.images.values() if im.has_pose)} for k, r in enumerate(models)]
    record = {"summary": summary, "models_info": models_info, "duplicate": _duplicate_models(models_info),
              "policy": policy, "focal_check": focal_check, "mapper_record": mapper_record,
              "diagnostics": image_diagnostics(db),
              # the positions the mapping was seeded / paired with (a later geo.txt edit is measured against them)
              "positions": {n: [round(float(v), 4) for v in x] for n, x in positions.items()},
              "seconds": {"features": t_feat - t0, "matching": t_match - t_feat, "mapping": t_map - t_match},
              "cpu_seconds": {"features": round(c_feat - c0, 1), "matching": round(c_match - c_feat, 1),
                              "mapping": round(c_map - c_match, 1)}}
    return MappedBlock(models, record)


def place_block(project: Project, names: list[str], out: Path, kind: str, settings: SfmSettings, mapped: MappedBlock,
                georegister_block: bool, label: str, priors: tuple | None = None) -> BlockResult:
    """The georegistration step over ``mapped`` (its models are moved in place): the Sim(3) by GPS and
    GCPs of each model, the kept ones merged, the reference block held by its positions, why each photo
    is not in it; writes the block's model, poses, intrinsics and ``block.json`` to ``out``.
    ``priors``: what :func:`_block_priors` read (None: read now, geo.txt as it is now)."""
    import copy

    t0, c0 = time.time(), cpu_seconds()
    metas, positions, accuracy, _ = priors or _block_priors(project, names, kind, settings)
    rec0 = mapped.record
    models, policy, focal_check = mapped.models, rec0["policy"], rec0["focal_check"]
    summary = copy.deepcopy(rec0["summary"])
    models_info = copy.deepcopy(rec0["models_info"])
    duplicate = {int(k): v for k, v in rec0["duplicate"].items()}
    min_inliers = settings.matching.min_num_inliers
    diag = rec0["diagnostics"]
    if mapped.reused:
        summary["mapping"] = {"reused": True, "made": rec0.get("made", ""),
                              "why": "photos, cameras.txt and SfM settings unchanged (gtkit.sfm.georeg_step)",
                              **positions_moved(rec0.get("positions") or {}, positions)}
    if not models:
        summary.update(n_registered=0, n_models=0, models=[], unregistered={
            n: failure_reason(diag.get(n, {"keypoints": 0, "verified_pairs": 0, "best_inliers": 0}), min_inliers)
            for n in names})
        summary["error"] = "the mapper reconstructed nothing (no initial pair found)"
        write_json(out / "block.json", summary)
        return BlockResult(None, summary)
    kept = [0]
    if georegister_block:
        gcps = block_gcps(project, names)
        kept = georegister_models(gcps, names, kind, settings.georegister, models, models_info, duplicate,
                                  positions, accuracy, metas, summary,
                                  stated_gcp_accuracy(project) if kind == "reference" else None)
    else:
        summary["frame"] = "arbitrary SfM frame"
    rec = merge_models([models[k] for k in kept]) if len(kept) > 1 else models[kept[0]]
    if len(kept) > 1:  # each model was georegistered on its own; the figures above are model 0's
        summary["georegistration"]["merged_models"] = kept
    rec = _hold_by_positions(rec, kind, settings, summary, positions, accuracy, rec0["mapper_record"])
    for k, info in enumerate(models_info):
        info["kept"] = k in kept
        if k in duplicate:
            info["reason"] = f"its photos are all in model {duplicate[k]}"
        elif k not in kept:
            info["reason"] = ("not placed in the world: " + info.get("georegistration", {}).get("error", "")
                              if georegister_block else "not the largest model of an unregistered block")
    t_geo, c_geo = time.time(), cpu_seconds()
    registered = {im.name for im in rec.images.values() if im.has_pose}
    unregistered = _unregistered_reasons(diag, names, registered, models_info, summary, min_inliers)
    summary.update({"n_registered": len(registered), "unregistered": unregistered, "n_models": len(models),
                    "models": models_info, "n_points3D": rec.num_points3D(),
                    "mean_reproj_px": float(rec.compute_mean_reprojection_error()),
                    "intrinsics": {str(cid): {"model": c.model.name, "width": c.width, "height": c.height,
                                              "params": [float(v) for v in c.params],
                                              "fixed": cid in policy["constant_cameras"],
                                              "refined": _refined_parts(cid, policy, focal_check)}
                                   for cid, c in rec.cameras.items()}})
    _write_block_model(out, rec, kind, summary, label)
    # a reused mapping cost nothing now: its own seconds stay in mapped/mapped.json
    done = {k: (0.0 if mapped.reused else v) for k, v in rec0["seconds"].items()}
    summary["seconds"] = {**done, "georegistration": t_geo - t0}
    summary["cpu_seconds"] = {**{k: (0.0 if mapped.reused else v) for k, v in rec0["cpu_seconds"].items()},
                              "georegistration": round(c_geo - c0, 1)}
    write_json(out / "block.json", summary)
    return BlockResult(rec, summary)


def build_block(project: Project, names: list[str], out: Path, kind: str, settings: SfmSettings,
                georegister_block: bool, label: str, executor=None) -> BlockResult:
    """Features, pairs, mapping, optional georegistration; writes the block's files to ``out``
    (:func:`map_block` then :func:`place_block`). ``kind``: 'reference' or 'sequence' (adds sequential
    pairs). ``executor``: None extracts and matches in this process; an
    :class:`~gtkit.localize.executors.ExecutorSettings` runs feature extraction and matching as tasks
    on that executor (same database)."""
    priors = _block_priors(project, names, kind, settings)
    mapped = map_block(project, names, out, kind, settings, label, executor, priors)
    return place_block(project, names, out, kind, settings, mapped, georegister_block, label, priors)


# a reference block of at most this many photos, all larger than the default feature size, finds its
# features at FINE_FEATURES (long side, keypoints) where the user set neither, and its query sequences
# with it (issue 55: on the real-truth sets' 3072-px photos the 1600-px features left the blocks' cameras
# 2-3x worse than plain COLMAP's 3200 / 8192; finer features on the reference block alone, the queries
# at 1600 px, made entry worse: 21.6 mm against 15.8). A larger block keeps the default (its time).
FINE_FEATURES_MAX_PHOTOS = 40
FINE_FEATURES = (3200, 8192)


def _photo_long_side(path: Path) -> int | None:
    """The photo's long side (px) from the one metadata reader; None where it cannot be read (the
    features' own reader then names the file)."""
    try:
        m = read_photo_meta(path, require=())
    except GtkitError:
        return None
    return max(m.width, m.height) or None


def block_feature_settings(project: Project, names: list[str], settings: SfmSettings,
                           reference_names: list[str] | None = None) -> SfmSettings:
    """``settings`` with finer features (:data:`FINE_FEATURES`) where the reference block
    (``reference_names``, default ``names``) has at most :data:`FINE_FEATURES_MAX_PHOTOS` photos and
    they, and ``names``, are all larger than the default feature size, and the user set neither
    ``[sfm] features.max_image_size`` nor ``max_num_features`` (project.toml, or a flag giving another
    value than the default). A query sequence passes its own ``names`` and the reference block's: it
    takes the reference block's size, so both blocks' features agree. The stage's record holds the
    size used (the sigma reads it: ``register.real_photo_terms.feature_side_of``)."""
    import dataclasses

    ref = names if reference_names is None else reference_names
    f, d = settings.features, FeatureSettings()
    table = (project.config.get("sfm", {}) or {}).get("features", {}) or {}
    if ("max_image_size" in table or "max_num_features" in table or f.max_image_size != d.max_image_size
            or f.max_num_features != d.max_num_features or not 0 < len(ref) <= FINE_FEATURES_MAX_PHOTOS
            or not names):
        return settings
    sides = [_photo_long_side(project.paths.images / n) for n in dict.fromkeys([*ref, *names])]
    if any(s is None or s <= d.max_image_size for s in sides):
        return settings
    size, n_feat = FINE_FEATURES
    log.info("%d photos of %d-%d px in a reference block of %d: features at %d px / %d keypoints (default %d / %d)",
             len(names), min(sides), max(sides), len(ref), size, n_feat, d.max_image_size, d.max_num_features)
    return dataclasses.replace(settings, features=dataclasses.replace(f, max_image_size=size, max_num_features=n_feat))


def run_reference(project: Project | str | Path, settings: SfmSettings, force: bool = False,
                  executor=None) -> dict:
    """``gtkit sfm DIR --block reference``: the mapping step, reused when its own inputs are unchanged
    (``work/sfm_reference/mapped/``, :mod:`gtkit.sfm.georeg_step`), then the georegistration step.
    ``force``: both re-run. ``executor``: see :func:`build_block`."""
    quiet_colmap()
    project = project if isinstance(project, Project) else Project.load(project)
    P = project.paths
    names = list_images(P.reference_images, P.images)
    if not names:
        raise GtkitError("no reference photos found", P.reference_images)
    settings = block_feature_settings(project, names, settings)
    out = P.stage(REFERENCE_STAGE)
    inputs = _inputs(project, names)
    if points_path(P).is_file():   # the GCPs' stated accuracy (gcp/points.txt) enters the claimed accuracy
        inputs["gcp_points"] = file_fingerprint(points_path(P))
    if not force and stage_done(out, settings, inputs):
        import json
        return json.loads((out / "block.json").read_text())
    start_stage_clock(out)
    choose_mapper(settings.mapper, len(names))  # a bad mapper name fails before the features
    label = "reference block"
    priors = _block_priors(project, names, "reference", settings)
    key = mapping_key(settings, mapping_inputs(project, names, priors[1], priors[3]))
    mapped = None if force else load_mapped(out, key)
    if mapped is not None:
        ok, why = reusable(mapped, priors[1])
        if not ok:
            log.info("%s: %s", label, why)
            mapped = None
    if mapped is None:
        mapped = map_block(project, names, out, "reference", settings, label, executor, priors)
        mapped.record["made"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        save_mapped(out, mapped, key)
        # the georegistration works on the models as saved, so that a later run of it alone
        # (a GCP click, a geo.txt edit) starts from the very same models
        mapped = load_mapped(out, key) or mapped
        mapped.reused = False
    else:
        log.info("%s: mapping reused (photos, cameras.txt and SfM settings unchanged); georegistration only", label)
    res = place_block(project, names, out, "reference", settings, mapped, True, label, priors)
    write_reference_report(P, res.summary)
    if res.rec is None:
        raise GtkitError(res.summary["error"], out)
    if "error" in res.summary.get("georegistration", {}):
        raise GtkitError(f"georegistration failed: {res.summary['georegistration']['error']}", out)
    mark_stage_done(out, settings, inputs, n_registered=res.summary["n_registered"],
                    mapping_reused=mapped.reused)
    return res.summary


def run_queries(project: Project | str | Path, settings: SfmSettings, force: bool = False,
                sequences: list[str] | None = None, executor=None) -> dict:
    """``gtkit sfm DIR --block queries``: one model per sequence. A failed sequence is reported
    with its reason; the others still finish."""
    import json

    quiet_colmap()
    project = project if isinstance(project, Project) else Project.load(project)
    P = project.paths
    seqs = sequences or P.query_sequences()
    if not seqs:
        raise GtkitError("no query sequences found", P.query_images)
    root = P.stage(QUERIES_STAGE)
    result = {}
    ref_names = list_images(P.reference_images, P.images)
    base = settings
    for seq in seqs:
        names = list_images(P.query_images / seq, P.images, settings.query_pattern)  # the same list as gtkit.queries.query_photos
        settings = block_feature_settings(project, names, base, ref_names)   # the reference block's feature size
        out = root / seq
        if not names:
            result[seq] = {"block": seq, "error": f"no photos matching {settings.query_pattern}", "n_images": 0}
            continue
        inputs = _inputs(project, names)
        inputs["gcp_list"] = _gcp_clicks_in(project, names)
        # a sequence shot with a reference camera starts from its calibration (reference_calibrations)
        inputs["reference_intrinsics"] = file_fingerprint(P.intrinsics(REFERENCE_STAGE))
        if not force and stage_done(out, settings, inputs):
            result[seq] = json.loads((out / "block.json").read_text())
            continue
        log.info("query sequence %s: %d photos", seq, len(names))
        start_stage_clock(out)
        res = build_block(project, names, out, "sequence", settings, georegister_block=True, label=f"query sequence {seq}",
                          executor=executor)
        result[seq] = res.summary
        if res.rec is not None:
            mark_stage_done(out, settings, inputs, n_registered=res.summary["n_registered"])
    write_json(root / "summary.json", result)
    return result
