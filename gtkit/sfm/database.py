"""The pycolmap feature database of one block: cameras from priors, SIFT, pose priors, matches.

Image names in the database are paths relative to the project's ``images/`` folder, the same
names the tie-point and pose files use.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Camera

log = logging.getLogger(__name__)


@dataclass
class FeatureSettings:
    max_image_size: int = 1600      # px; images are downscaled for SIFT, keypoints are in full-size pixels
    max_num_features: int = 3000    # SIFT keypoints per image (CPU time grows with it)
    num_threads: int = 2


@dataclass
class MatchSettings:
    exhaustive_max_images: int = 25     # exhaustive pairs up to this many images, spatial above
    exhaustive_max_without_gps: int = 80  # blocks where photos lack GPS: exhaustive up to this many
    spatial_neighbors: int = 20         # spatial pairing: nearest neighbours per image
    spatial_max_distance_m: float = 250.0
    retrieval_neighbors: int = 20       # retrieval pairing (photos without GPS): most similar photos per image
    retrieval_always: bool = False      # add retrieval pairs even when every photo has a position
    chunk_pairs: int = 300              # pairs matched per call (progress granularity)
    sequential_overlap: int = 8         # query sequences: consecutive neighbours matched
    min_num_inliers: int = 15
    num_threads: int = 2


@dataclass
class CameraGroup:
    """Images taken by one camera. ``camera`` None: pycolmap infers it (EXIF focal) and refines it."""

    names: list[str]
    camera: Camera | None = None
    positions: dict[str, np.ndarray] = field(default_factory=dict)  # local-frame pairing positions


def build_database(db_path: Path, image_root: Path, groups: list[CameraGroup], settings: FeatureSettings,
                   prior_sigma_m: float = 5.0, progress=None, accuracy: dict[str, float] | None = None) -> dict[str, int]:
    """Create ``db_path`` fresh: one camera per group, SIFT features, CARTESIAN pose priors.
    ``progress(n)`` is called as each chunk of photos is extracted; ``accuracy``: {name: metres}, a
    photo's stated position accuracy (its prior's sigma; default ``prior_sigma_m``).
    Returns {image name: image_id}."""
    db_path = Path(db_path)
    db_path.unlink(missing_ok=True)
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = settings.max_image_size
    ext.sift.max_num_features = settings.max_num_features
    ext.num_threads = settings.num_threads
    for g in groups:
        ro = pycolmap.ImageReaderOptions()
        if g.camera is not None:
            cam = g.camera.to_pycolmap()
            cam.has_prior_focal_length = True
            with pycolmap.Database.open(db_path) as db:
                ro.existing_camera_id = db.write_camera(cam)
        else:
            ro.camera_model = "SIMPLE_RADIAL"
        for k in range(0, len(g.names), EXTRACT_CHUNK):
            chunk = list(g.names[k:k + EXTRACT_CHUNK])
            if k:  # later chunks join the group's camera made by the first one
                with pycolmap.Database.open(db_path) as db:
                    first = next(im for im in db.read_all_images() if im.name == g.names[0])
                ro.existing_camera_id = first.camera_id
            pycolmap.extract_features(db_path, image_root, image_names=chunk,
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=ro,
                                      extraction_options=ext, device=pycolmap.Device.cpu)
            if progress:
                progress(len(chunk))
    ids = {}
    with pycolmap.Database.open(db_path) as db:
        by_name = {im.name: im for im in db.read_all_images()}
        accuracy = accuracy or {}
        # pycolmap writes WGS84 priors from EXIF itself; replace them by CARTESIAN local ones
        existing = {pp.corr_data_id.id: pp for pp in db.read_all_pose_priors()}
        for g in groups:
            for name, xyz in g.positions.items():
                im = by_name.get(name)
                if im is None or not np.all(np.isfinite(xyz)):
                    continue
                prior = existing.get(im.image_id)
                if prior is None:
                    prior = pycolmap.PosePrior(corr_data_id=pycolmap.data_t(
                        pycolmap.sensor_t(pycolmap.SensorType.CAMERA, im.camera_id), im.image_id))
                prior.position = np.asarray(xyz, float)
                prior.position_covariance = np.eye(3) * accuracy.get(name, prior_sigma_m) ** 2
                prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
                if im.image_id in existing:
                    db.update_pose_prior(prior)
                else:
                    db.write_pose_prior(prior)
        ids = {n: im.image_id for n, im in by_name.items()}
    return ids


EXTRACT_CHUNK = 8  # photos per extraction call (progress granularity)


def read_descriptors(db_path: Path) -> dict[str, np.ndarray]:
    """{image name: uint8 SIFT descriptors} of every image in the database."""
    with pycolmap.Database.open(db_path) as db:
        return {im.name: np.asarray(db.read_descriptors(im.image_id).data) for im in db.read_all_images()}


def match_pairs(db_path: Path, pairs: list[tuple[str, str]], settings: MatchSettings, work_dir: Path,
                progress=None) -> None:
    """Match and verify the given name pairs, in chunks (``progress(n)`` after each)."""
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = settings.num_threads
    vo = pycolmap.TwoViewGeometryOptions()
    vo.min_num_inliers = settings.min_num_inliers
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    pairs_file = work_dir / "pairs_chunk.txt"
    for k in range(0, len(pairs), settings.chunk_pairs):
        chunk = pairs[k:k + settings.chunk_pairs]
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
        po = pycolmap.ImportedPairingOptions()
        po.match_list_path = pairs_file
        pycolmap.match_image_pairs(db_path, matching_options=mo, pairing_options=po,
                                   verification_options=vo, device=pycolmap.Device.cpu)
        if progress:
            progress(len(chunk))
    pairs_file.unlink(missing_ok=True)


def image_diagnostics(db_path: Path) -> dict[str, dict]:
    """Per image: keypoints, verified pairs and the best pair's inlier count (why it may fail)."""
    out = {}
    with pycolmap.Database.open(db_path) as db:
        images = {im.image_id: im.name for im in db.read_all_images()}
        for iid, name in images.items():
            out[name] = {"keypoints": int(db.num_keypoints_for_image(iid)), "verified_pairs": 0, "best_inliers": 0}
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
        for pid, n in zip(pair_ids, counts):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            for i in (a, b):
                d = out[images[i]]
                if n > 0:
                    d["verified_pairs"] += 1
                d["best_inliers"] = max(d["best_inliers"], int(n))
    return out


def failure_reason(diag: dict, min_inliers: int) -> str:
    if diag["keypoints"] < 50:
        return f"too few features ({diag['keypoints']} keypoints)"
    if diag["verified_pairs"] == 0:
        return "no verified matches with any other image"
    if diag["best_inliers"] < 2 * min_inliers:
        return f"weak matches (best pair {diag['best_inliers']} inliers, {diag['verified_pairs']} verified pairs)"
    return (f"not registered by the mapper ({diag['verified_pairs']} verified pairs, best "
            f"{diag['best_inliers']} inliers; disconnected or degenerate geometry)")
