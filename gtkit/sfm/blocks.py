"""The two kinds of SfM block: the reference block (oblique photos, georegistered by RTK GPS
and/or GCPs) and one block per query sequence (wide photos; sequential + spatial pairs).

Outputs (``work/sfm_reference/``, ``work/sfm_queries/<seq>/``): ``database.db``, ``model/``
(pycolmap reconstruction), ``poses.txt`` + ``intrinsics.txt`` (gtkit.io.poses formats, project
world frame), ``block.json`` (georegistration, GCP residuals, unregistered images and why).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Camera
from ..errors import GtkitError
from ..io.atomic import write_json, write_text
from ..io.exif import read_photo_meta
from ..io.odm import read_gcp_list, read_geo_txt
from ..io.poses import read_intrinsics, write_intrinsics, write_poses
from ..project import Project, file_fingerprint, mark_stage_done, settings_dict, settings_key, stage_done
from . import quiet_colmap
from .database import (CameraGroup, FeatureSettings, MatchSettings, build_database, failure_reason,
                       image_diagnostics, match)
from .geometry import RegistrationError, model_cameras, model_poses
from .georegister import GeoregisterSettings, georegister

log = logging.getLogger(__name__)

IMAGE_EXT = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
REFERENCE_STAGE = "sfm_reference"
QUERIES_STAGE = "sfm_queries"


@dataclass
class SfmSettings:
    features: FeatureSettings = field(default_factory=FeatureSettings)
    matching: MatchSettings = field(default_factory=MatchSettings)
    georegister: GeoregisterSettings = field(default_factory=GeoregisterSettings)
    # auto: cameras.txt calibrations stay fixed; cameras without one (EXIF focal) get their distortion
    # refined but keep the EXIF focal length (a flat, nadir-only block cannot tell focal length from
    # flying height: the focal drifts and the ground moves up or down); yes: refine all; no: none
    refine_intrinsics: str = "auto"
    query_pattern: str = "*_W.*"      # which photos of a query sequence form its block
    pair_by_footprint: bool = True    # spatial pairs by where photos look (gimbal), not where they were taken
    gps_prior_sigma_m: float = 5.0    # written with the CARTESIAN pose priors (used only for pairing)
    init_min_tri_angle_deg: float = 4.0  # mapper's initial pair (COLMAP: 16; short UAV baselines need less)
    min_tri_angle_deg: float = 1.0       # triangulation/filtering (COLMAP: 1.5)
    num_threads: int = 2


def list_images(folder: Path, root: Path, pattern: str = "*") -> list[str]:
    if not folder.is_dir():
        return []
    return sorted(p.relative_to(root).as_posix() for p in folder.glob(pattern)
                  if p.is_file() and p.suffix.lower() in IMAGE_EXT)


def gps_positions(project: Project, names: list[str]) -> dict[str, np.ndarray]:
    """Local-frame camera positions: from geo.txt where present, else EXIF GPS + DJI altitude."""
    P = project.paths
    geo = read_geo_txt(P.geo_txt, project.frame) if P.geo_txt.is_file() else {}
    out = {}
    for n in names:
        g = geo.get(n) or geo.get(Path(n).name)
        if g is not None and np.all(np.isfinite(g.xyz)):
            out[n] = g.xyz
            continue
        m = read_photo_meta(P.images / n, require=())
        if m.has_gps and m.altitude is not None:
            out[n] = project.frame.wgs84_to_local(m.lon, m.lat, m.altitude)
    return out


def pairing_positions(project: Project, names: list[str], centres: dict[str, np.ndarray],
                      max_range_factor: float = 3.0) -> dict[str, np.ndarray]:
    """Where each photo looks: the camera centre moved along the optical axis (DJI gimbal angles)
    to the ground (height above ground from DJI RelativeAltitude). Oblique photos that see the
    same ground are then neighbours for spatial pairing even when taken far apart. Photos without
    gimbal angles or relative altitude keep their camera centre."""
    from ..conventions import dji_to_rotation

    out = dict(centres)
    for n in names:
        if n not in centres:
            continue
        m = read_photo_meta(project.paths.images / n, require=())
        if not m.has_gimbal or m.rel_alt is None or m.rel_alt <= 0:
            continue
        d = dji_to_rotation(m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll).T @ np.array([0.0, 0.0, 1.0])
        r = m.rel_alt / max(-d[2], 1.0 / max_range_factor)
        out[n] = centres[n] + d * r
    return out


def camera_groups(project: Project, names: list[str], positions: dict) -> list[CameraGroup]:
    """One group per distinct cameras.txt calibration; images without one: one group per folder."""
    cams: dict[str, Camera] = read_intrinsics(project.paths.cameras) if project.paths.cameras.is_file() else {}
    groups: dict[tuple, CameraGroup] = {}
    for n in names:
        c = cams.get(n)
        key = ("cam", c.model, c.width, c.height, c.params) if c else ("folder", str(Path(n).parent))
        g = groups.setdefault(key, CameraGroup([], c))
        g.names.append(n)
        if n in positions:
            g.positions[n] = positions[n]
    return list(groups.values())


def _inputs(project: Project, names: list[str]) -> dict:
    P = project.paths
    return {"images": {n: file_fingerprint(P.images / n) for n in names},
            "cameras": file_fingerprint(P.cameras), "gcp_list": file_fingerprint(P.gcp_list),
            "geo_txt": file_fingerprint(P.geo_txt), "crs": [project.frame.crs_spec, list(project.frame.origin)]}


def _map(db: Path, image_root: Path, out: Path, settings: SfmSettings, refine: bool,
         refine_focal: bool) -> pycolmap.Reconstruction | None:
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = settings.num_threads
    opts.random_seed = 0
    opts.ba_refine_focal_length = refine_focal
    opts.ba_refine_extra_params = refine
    opts.ba_refine_principal_point = False
    opts.mapper.abs_pose_refine_focal_length = refine_focal
    opts.mapper.abs_pose_refine_extra_params = refine
    opts.min_model_size = 3
    opts.mapper.init_min_tri_angle = settings.init_min_tri_angle_deg
    opts.mapper.filter_min_tri_angle = settings.min_tri_angle_deg
    opts.triangulation.min_angle = settings.min_tri_angle_deg
    out.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(db, image_root, out, options=opts)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


@dataclass
class BlockResult:
    rec: pycolmap.Reconstruction | None
    summary: dict


def build_block(project: Project, names: list[str], out: Path, pairings: list[str], settings: SfmSettings,
                georegister_block: bool, label: str) -> BlockResult:
    """Features, pairs, mapping, optional georegistration; writes the block's files to ``out``."""
    P = project.paths
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    positions = gps_positions(project, names)
    look = pairing_positions(project, names, positions) if settings.pair_by_footprint else positions
    groups = camera_groups(project, names, look)
    db = out / "database.db"
    # features + matches are reused when nothing that made them changed (mapping settings may)
    db_key = settings_key({"features": settings_dict(settings.features), "matching": settings_dict(settings.matching),
                           "pairings": pairings, "sigma": settings.gps_prior_sigma_m,
                           "images": {n: file_fingerprint(P.images / n) for n in names},
                           "groups": [[g.names, g.camera.to_line() if g.camera else None,
                                       {n: [round(float(v), 3) for v in x] for n, x in g.positions.items()}]
                                      for g in groups]})
    key_file = out / "database.key"
    reuse = db.is_file() and key_file.is_file() and key_file.read_text().strip() == db_key
    if not reuse:
        key_file.unlink(missing_ok=True)
        build_database(db, P.images, groups, settings.features, settings.gps_prior_sigma_m)
    t_feat = time.time()
    if not reuse:
        for p in pairings:
            if p == "spatial" and len(positions) < 2:
                continue
            match(db, p, settings.matching)
        write_text(key_file, db_key + "\n")
    t_match = time.time()
    refine = {"yes": True, "no": False}.get(settings.refine_intrinsics, any(g.camera is None for g in groups))
    refine_focal = settings.refine_intrinsics == "yes"
    rec = _map(db, P.images, out / "mapper", settings, refine, refine_focal)
    t_map = time.time()
    diag = image_diagnostics(db)
    registered = {im.name for im in rec.images.values() if im.has_pose} if rec else set()
    unregistered = {n: failure_reason(diag.get(n, {"keypoints": 0, "verified_pairs": 0, "best_inliers": 0}),
                                      settings.matching.min_num_inliers) for n in names if n not in registered}
    summary = {"block": label, "reused_database": reuse, "n_images": len(names), "n_registered": len(registered),
               "unregistered": unregistered, "pairings": pairings, "refined_distortion": refine, "refined_focal": refine_focal,
               "n_cameras": len(groups), "n_gps": len(positions)}
    if rec is None:
        summary["error"] = "the mapper reconstructed nothing (no initial pair found)"
        write_json(out / "block.json", summary)
        return BlockResult(None, summary)
    summary.update({"n_points3D": rec.num_points3D(), "mean_reproj_px": float(rec.compute_mean_reprojection_error())})
    if georegister_block:
        gcps = read_gcp_list(P.gcp_list, project.frame) if P.gcp_list.is_file() else []
        for g in gcps:  # ODM names photos by file name; gtkit by path under images/
            for c in g.clicks:
                if "/" not in c.image:
                    c.image = next((n for n in names if Path(n).name == c.image), c.image)
        try:
            summary["georegistration"] = georegister(rec, positions, gcps, settings.georegister)
            summary["frame"] = "project world frame"
        except RegistrationError as e:
            summary["georegistration"] = {"error": str(e)}
            summary["frame"] = "arbitrary SfM frame (georegistration failed)"
    else:
        summary["frame"] = "arbitrary SfM frame"
    t_geo = time.time()
    (out / "model").mkdir(exist_ok=True)
    rec.write(out / "model")
    write_poses(out / "poses.txt", model_poses(rec), header=f"{label}: {summary['frame']}")
    write_intrinsics(out / "intrinsics.txt", model_cameras(rec))
    summary["seconds"] = {"features": t_feat - t0, "matching": t_match - t_feat, "mapping": t_map - t_match,
                          "georegistration": t_geo - t_map}
    write_json(out / "block.json", summary)
    return BlockResult(rec, summary)


def run_reference(project: Project | str | Path, settings: SfmSettings | None = None, force: bool = False) -> dict:
    """``gtkit sfm DIR --block reference``."""
    quiet_colmap()
    project = project if isinstance(project, Project) else Project.load(project)
    settings = settings or SfmSettings()
    P = project.paths
    names = list_images(P.reference_images, P.images)
    if not names:
        raise GtkitError("no reference photos found", P.reference_images)
    out = P.stage(REFERENCE_STAGE)
    inputs = _inputs(project, names)
    if not force and stage_done(out, settings, inputs):
        import json
        return json.loads((out / "block.json").read_text())
    pairings = ["exhaustive"] if len(names) <= settings.matching.exhaustive_max_images else ["spatial"]
    res = build_block(project, names, out, pairings, settings, georegister_block=True, label="reference block")
    if res.rec is None:
        raise GtkitError(res.summary["error"], out)
    if "error" in res.summary.get("georegistration", {}):
        raise GtkitError(f"georegistration failed: {res.summary['georegistration']['error']}", out)
    mark_stage_done(out, settings, inputs, n_registered=res.summary["n_registered"])
    return res.summary


def run_queries(project: Project | str | Path, settings: SfmSettings | None = None, force: bool = False,
                sequences: list[str] | None = None) -> dict:
    """``gtkit sfm DIR --block queries``: one model per sequence. A failed sequence is reported
    with its reason; the others still finish."""
    import json

    quiet_colmap()
    project = project if isinstance(project, Project) else Project.load(project)
    settings = settings or SfmSettings()
    P = project.paths
    seqs = sequences or P.query_sequences()
    if not seqs:
        raise GtkitError("no query sequences found", P.query_images)
    root = P.stage(QUERIES_STAGE)
    result = {}
    for seq in seqs:
        names = list_images(P.query_images / seq, P.images, settings.query_pattern)
        out = root / seq
        if not names:
            result[seq] = {"block": seq, "error": f"no photos matching {settings.query_pattern}", "n_images": 0}
            continue
        inputs = _inputs(project, names)
        if not force and stage_done(out, settings, inputs):
            result[seq] = json.loads((out / "block.json").read_text())
            continue
        log.info("query sequence %s: %d photos", seq, len(names))
        pairings = ["sequential", "spatial"] if len(names) > settings.matching.exhaustive_max_images else ["exhaustive"]
        res = build_block(project, names, out, pairings, settings, georegister_block=True, label=f"query sequence {seq}")
        result[seq] = res.summary
        if res.rec is not None:
            mark_stage_done(out, settings, inputs, n_registered=res.summary["n_registered"])
    write_json(root / "summary.json", result)
    return result
