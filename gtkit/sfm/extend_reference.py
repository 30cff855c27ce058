"""Photos placed on their own, tied to the reference block as an SfM of all the photos would tie them.

A query photo its sequence's SfM left out (held-out photos of a flight, too far apart to match each
other) is first resected from the automatic matches to the reference block's 3D points
(:mod:`gtkit.sfm.resect`). Those are only the points the reference SfM triangulated: on a weakly
textured real site (Brighton beach: 1,684 points over 14 photos) 34-110 matches a photo, and the
pose they give is 0.10-0.22 m from an SfM of all the photos. Here each such photo is matched, keypoint
to keypoint, with the reference photos that see what it sees, and COLMAP's mapper registers it into
the reference block with the reference poses held (``fix_existing_frames``), triangulating the new
points the photo shares with the reference photos. Every point of that extended block that a
resected photo and at least one reference photo observe becomes an automatic tie point
``auto:ext<n>`` (the photo's and the reference photos' pixels), so the joint adjustment holds the
photo by all of them.

Inputs: the reference database and block (their image ids agree), the photos' resected poses,
cameras and sequence databases (features as the sequence's SfM extracted them: nothing is extracted
again). Work is done on a copy of the reference database in ``work``.
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Camera
from ..determinism import single_thread_mapper
from ..pose import Pose
from .crossmatch import AUTO_PREFIX
from .database import MatchSettings, match_pairs

log = logging.getLogger(__name__)
EXT_PREFIX = f"{AUTO_PREFIX}ext"   # ids of tie points from the extended block: auto:ext<n>


@dataclass
class ExtendSettings:
    enabled: bool = True     # tie photos placed on their own to the reference by keypoint matches
    neighbours: int = 8      # reference photos each such photo is matched with (nearest views)
    max_ties_per_photo: int = 1500  # at most this many tie points a photo (spread: random)


def _ground_point(pose: Pose, ground_z: float) -> np.ndarray:
    """Where the photo's optical axis meets the plane z = ground_z (its centre if it looks up)."""
    c = pose.center
    axis = pose.R[2]                      # camera z axis in the world (world-to-camera rotation rows)
    if axis[2] >= -1e-3:
        return c
    return c + axis * (ground_z - c[2]) / axis[2]


def neighbour_views(pose: Pose, ref_rec: pycolmap.Reconstruction, k: int, ground_z: float) -> list[str]:
    """The ``k`` reference photos whose view is closest to the photo's: nearest optical-axis ground
    points, then nearest camera centres (union, closest first)."""
    ims = [im for im in ref_rec.images.values() if im.has_pose]
    if not ims:
        return []
    g = _ground_point(pose, ground_z)
    ref_poses = [Pose.from_pycolmap(im.cam_from_world()) for im in ims]
    dg = np.array([np.linalg.norm(_ground_point(p, ground_z)[:2] - g[:2]) for p in ref_poses])
    dc = np.array([np.linalg.norm(p.center - pose.center) for p in ref_poses])
    out = []
    for i in list(np.argsort(dg)[:k]) + list(np.argsort(dc)[:k // 2]):
        if ims[i].name not in out:
            out.append(ims[i].name)
    return out


def photo_pairs(ref_rec: pycolmap.Reconstruction, poses: dict[str, Pose], neighbours: int) -> list[tuple[str, str]]:
    """The pairs to match for photos at ``poses`` joining the reference block: each with its
    ``neighbours`` nearest reference views (:func:`neighbour_views`), and the photos of one sequence
    with each other."""
    ground_z = float(np.median([p.xyz[2] for p in ref_rec.points3D.values()]))
    names = sorted(poses)
    pairs = []
    for n in names:
        pairs += [(n, r) for r in neighbour_views(poses[n], ref_rec, neighbours, ground_z)]
    pairs += [(a, b) for i, a in enumerate(names) for b in names[i + 1:]
              if a.split("/")[:2] == b.split("/")[:2]]   # photos of one sequence with each other
    return pairs


def _copy_features(src: Path, names: list[str], dst: pycolmap.Database, ids: dict[str, int]) -> None:
    with pycolmap.Database.open(src) as db:
        for n in names:
            im = db.read_image_with_name(n)
            dst.write_keypoints(ids[n], db.read_keypoints(im.image_id))
            dst.write_descriptors(ids[n], db.read_descriptors(im.image_id))


def extended_database(ref_db: Path, photos: dict[str, tuple[Camera, Path]], pairs: list[tuple[str, str]],
                      image_root: Path, work: Path, match: MatchSettings | None = None, num_threads: int = 2,
                      shared: dict[int, Camera] | None = None) -> Path:
    """A copy of the reference database in ``work`` (emptied first) with ``photos`` ({name: (camera, its
    sequence's feature database)}) added, their features copied (not extracted again), and the name
    ``pairs`` matched keypoint to keypoint. ``shared``: reference cameras ({id: calibration}) a photo
    whose camera is that very calibration takes as its own (one camera for both, not a copy). Returns
    its path."""
    work = Path(work)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    db_path = work / "database.db"
    shutil.copy(ref_db, db_path)
    names = sorted(photos)

    def key_of(cam: Camera) -> tuple:
        return cam.model, cam.width, cam.height, tuple(np.round(cam.params, 6))

    with pycolmap.Database.open(db_path) as db:
        cam_ids: dict[tuple, int] = {key_of(c): cid for cid, c in sorted((shared or {}).items(), reverse=True)}
        for n in names:
            key = key_of(photos[n][0])
            if key not in cam_ids:
                cam = photos[n][0]
                pc = cam.to_pycolmap()
                pc.has_prior_focal_length = True
                cam_ids[key] = db.write_camera(pc)
    by_cam: dict[int, list[str]] = {}
    for n in names:
        by_cam.setdefault(cam_ids[key_of(photos[n][0])], []).append(n)
    for cid, group in by_cam.items():
        ro = pycolmap.ImageReaderOptions()
        ro.existing_camera_id = cid
        pycolmap.import_images(db_path, image_root, camera_mode=pycolmap.CameraMode.SINGLE, image_names=group,
                               options=ro)
    with pycolmap.Database.open(db_path) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        by_db: dict[Path, list[str]] = {}
        for n in names:
            by_db.setdefault(Path(photos[n][1]), []).append(n)
        for src, group in by_db.items():
            _copy_features(src, group, db, ids)
    match_pairs(db_path, pairs, match or MatchSettings(num_threads=num_threads), work)
    return db_path


def register_into_reference(ref_rec: pycolmap.Reconstruction, ref_db: Path, photos: dict[str, tuple[Camera, Path]],
                            pairs: list[tuple[str, str]], image_root: Path, work: Path, match: MatchSettings | None = None,
                            num_threads: int = 2, seed: int = 0, reproducible: bool = True
                            ) -> pycolmap.Reconstruction | None:
    """The reference block with ``photos`` ({name: (camera, its sequence's feature database)}) registered
    into it by COLMAP's mapper, the reference poses held (``fix_existing_frames``), after matching the
    name ``pairs`` (:func:`extended_database`); None where the mapper made nothing."""
    work = Path(work)
    db_path = extended_database(ref_db, photos, pairs, image_root, work, match, num_threads)
    model_in = work / "reference"
    model_in.mkdir()
    ref_rec.write(model_in)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.fix_existing_frames = True
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.ba_refine_focal_length = opts.ba_refine_extra_params = opts.ba_refine_principal_point = False
    opts.mapper.abs_pose_refine_focal_length = opts.mapper.abs_pose_refine_extra_params = False
    opts.min_model_size = 1
    single_thread_mapper(opts, reproducible)     # its RANSACs and BAs on one thread: gtkit.determinism
    models = pycolmap.incremental_mapping(db_path, image_root, work / "mapper", options=opts, input_path=model_in)
    return max(models.values(), key=lambda r: r.num_reg_images()) if models else None


def extension_ties(ref_rec: pycolmap.Reconstruction, ref_db: Path, photos: dict[str, tuple[Pose, Camera, Path]],
                   image_root: Path, work: Path, settings: ExtendSettings, match: MatchSettings | None = None,
                   num_threads: int = 2, seed: int = 0, reproducible: bool = True
                   ) -> tuple[dict[str, dict[str, tuple[float, float]]], dict]:
    """({tie id: {image: (x, y)}}, {photo: record}) for ``photos`` ({name: (resected pose, camera,
    its sequence's feature database)}); see the module doc. A photo the mapper does not register
    into the reference block gets no tie points here (its record says so) and keeps the ones it had."""
    photos = {n: v for n, v in photos.items() if Path(v[2]).is_file()}
    if not photos or not Path(ref_db).is_file() or ref_rec.num_points3D() == 0:
        return {}, {}
    names = sorted(photos)
    pairs = photo_pairs(ref_rec, {n: v[0] for n, v in photos.items()}, settings.neighbours)
    rec = register_into_reference(ref_rec, ref_db, {n: (v[1], v[2]) for n, v in photos.items()}, pairs, image_root,
                                  work, match, num_threads, seed, reproducible)
    records = {n: {"registered": False, "n_ties": 0} for n in names}
    if rec is None:
        return {}, records
    wanted = set(names)
    rng = np.random.default_rng(seed)
    per_photo: dict[str, list[int]] = {}
    for pid, p in rec.points3D.items():
        els = [rec.images[e.image_id] for e in p.track.elements]
        if any(im.name in wanted for im in els) and any(im.name.startswith("reference/") for im in els):
            for im in els:
                if im.name in wanted:
                    per_photo.setdefault(im.name, []).append(pid)
    keep: set[int] = set()
    for n, pids in per_photo.items():
        if len(pids) > settings.max_ties_per_photo:
            pids = list(rng.choice(pids, settings.max_ties_per_photo, replace=False))
        keep.update(pids)
    ties: dict[str, dict[str, tuple[float, float]]] = {}
    for k, pid in enumerate(sorted(keep)):
        obs = {}
        for e in rec.points3D[pid].track.elements:
            im = rec.images[e.image_id]
            obs.setdefault(im.name, tuple(float(v) for v in im.points2D[e.point2D_idx].xy))
        ties[f"{EXT_PREFIX}{k}"] = obs
    for n in names:
        im = rec.find_image_with_name(n)
        if im is not None and im.has_pose:
            moved = float(np.linalg.norm(im.projection_center() - photos[n][0].center))
            records[n] = {"registered": True, "n_ties": sum(1 for t in ties.values() if n in t),
                          "moved_from_resection_m": moved}
    log.info("reference block extended: %d of %d photos placed on their own registered into it, %d tie points",
             sum(r["registered"] for r in records.values()), len(names), len(ties))
    return ties, records
