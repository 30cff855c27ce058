"""The pycolmap feature database of one block: cameras from priors, SIFT, pose priors, matches.

Image names in the database are paths relative to the project's ``images/`` folder, the same
names the tie-point and pose files use.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Camera
from ..errors import GtkitError

log = logging.getLogger(__name__)


@dataclass
class FeatureSettings:
    # px; images are downscaled for SIFT, keypoints are in full-size pixels. Measured on the fullsize
    # sample (24 MP reference, loaded): 1600 px 1.65 CPU s / 0.48 GB a photo (pseudo-GT 0.029 m vs
    # small's 0.043 m); 3200 px 5.2 s / 1.17 GB; full 6000 px 10.5 s / 3.77 GB (docs/benchmarks.md)
    max_image_size: int = 1600
    max_num_features: int = 3000    # SIFT keypoints per image (CPU time grows with it)
    # First octave of SIFT's pyramid: 0 starts at the image's own size; -1 (COLMAP's default) at twice
    # its size, which costs 3.7x the CPU and, as COLMAP keeps the largest-scale keypoints beyond
    # max_num_features, adds almost nothing kept: 94-95 % of the kept keypoints are the same within
    # 0.5 px (samples' 1024 px photos and Brighton's DJI photos at 1600 px, 3000 keypoints).
    first_octave: int = 0
    num_threads: int = 2


@dataclass
class MatchSettings:
    exhaustive_max_images: int = 25     # exhaustive pairs up to this many images, spatial above
    exhaustive_max_without_gps: int = 80  # blocks where photos lack GPS: exhaustive up to this many
    spatial_neighbors: int = 20         # spatial pairing: nearest neighbours per image
    spatial_max_distance_m: float = 250.0
    retrieval_neighbors: int = 20       # retrieval pairing (photos without GPS): most similar photos per image
    retrieval_always: bool = False      # add retrieval pairs even when every photo has a position
    # pairs matched per call at most (in locality order, see _chunks; each call reads its photos and
    # builds their search indexes once): 600 in name order -> 2,000 in locality order, medium seed 6's
    # 7,522 pairs 401 -> 336 s idle, the same matches and two-view geometries
    chunk_pairs: int = 2000
    sequential_overlap: int = 8         # query sequences: consecutive neighbours matched
    min_num_inliers: int = 15
    num_threads: int = 2


# with fewer pairs, matching on one thread in this process beats starting matching processes
LOCAL_PROCESSES_FROM_PAIRS = 400


@dataclass
class CameraGroup:
    """Images taken by one camera. ``camera`` None: pycolmap infers it (EXIF focal) and refines it."""

    names: list[str]
    camera: Camera | None = None
    positions: dict[str, np.ndarray] = field(default_factory=dict)  # local-frame pairing positions


def _extraction_options(settings: FeatureSettings) -> pycolmap.FeatureExtractionOptions:
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = settings.max_image_size
    ext.sift.max_num_features = settings.max_num_features
    ext.sift.first_octave = settings.first_octave
    ext.num_threads = settings.num_threads
    return ext


def build_database(db_path: Path, image_root: Path, groups: list[CameraGroup], settings: FeatureSettings,
                   prior_sigma_m: float = 5.0, progress=None, accuracy: dict[str, float] | None = None,
                   executor=None) -> dict[str, int]:
    """Create ``db_path`` fresh: one camera per group, SIFT features, CARTESIAN pose priors.
    ``progress(n)`` is called as each chunk of photos is extracted; ``accuracy``: {name: metres}, a
    photo's stated position accuracy (its prior's sigma; default ``prior_sigma_m``).
    Images are imported first (cameras, ids in name order, EXIF priors). ``executor``
    (:mod:`gtkit.localize.executors`): None extracts here, in this process; else each chunk's SIFT
    runs as a task on the executor (:func:`_extract_chunk`), written here: the same database.
    Returns {image name: image_id}."""
    db_path = Path(db_path)
    db_path.unlink(missing_ok=True)
    with pycolmap.Database.open(db_path):  # created empty: import_images needs it to exist
        pass
    ext = _extraction_options(settings)
    tasks = []
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
            # images imported first, in name order: ids do not depend on which extraction thread
            # finishes first (extract_features alone numbers them as they complete)
            pycolmap.import_images(db_path, image_root, camera_mode=pycolmap.CameraMode.SINGLE,
                                   image_names=chunk, options=ro)
            if executor is not None:
                tasks.append((str(image_root), chunk, dataclasses.asdict(settings)))
                continue
            pycolmap.extract_features(db_path, image_root, image_names=chunk,
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=ro,
                                      extraction_options=ext, device=pycolmap.Device.cpu)
            if progress:
                progress(len(chunk))
    if tasks:
        from ..localize.executors import iter_map

        with pycolmap.Database.open(db_path) as db:
            by_name = {im.name: im.image_id for im in db.read_all_images()}
        for res in iter_map(executor, _extract_chunk, tasks):
            with pycolmap.Database.open(db_path) as db:
                for name, kp, desc in res:
                    db.write_keypoints(by_name[name], kp)
                    db.write_descriptors(by_name[name], pycolmap.FeatureDescriptors(
                        pycolmap.FeatureExtractorType.SIFT, desc))
            if progress:
                progress(len(res))
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


EXTRACT_CHUNK = 8  # photos per extraction call (progress granularity; one executor task)


def _extract_chunk(task: tuple) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """An executor task: SIFT of a chunk of photos, as ``extract_features`` computes it (into a
    scratch database here; features do not depend on the camera). [(name, keypoints, descriptors)]."""
    import tempfile

    image_root, names, fs = task
    with tempfile.TemporaryDirectory(prefix="gtkit-sift-") as tmp:
        db_path = Path(tmp) / "chunk.db"
        ro = pycolmap.ImageReaderOptions()
        ro.camera_model = "SIMPLE_RADIAL"
        pycolmap.extract_features(db_path, image_root, image_names=list(names), camera_mode=pycolmap.CameraMode.AUTO,
                                  reader_options=ro, extraction_options=_extraction_options(FeatureSettings(**fs)),
                                  device=pycolmap.Device.cpu)
        with pycolmap.Database.open(db_path) as db:
            by_name = {im.name: im.image_id for im in db.read_all_images()}
            return [(n, np.asarray(db.read_keypoints(by_name[n])), np.asarray(db.read_descriptors(by_name[n]).data))
                    for n in names]


def read_descriptors(db_path: Path) -> dict[str, np.ndarray]:
    """{image name: uint8 SIFT descriptors} of every image in the database."""
    with pycolmap.Database.open(db_path) as db:
        return {im.name: np.asarray(db.read_descriptors(im.image_id).data) for im in db.read_all_images()}


def _matching_options(settings: MatchSettings) -> tuple:
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = settings.num_threads
    vo = pycolmap.TwoViewGeometryOptions()
    vo.min_num_inliers = settings.min_num_inliers
    vo.ransac.random_seed = 0   # verification repeatable (pycolmap's default -1 draws a new seed each run)
    return mo, vo


def match_pairs(db_path: Path, pairs: list[tuple[str, str]], settings: MatchSettings, work_dir: Path,
                progress=None, executor=None) -> None:
    """Match and verify the given name pairs, in chunks of pairs that share photos (:func:`_chunks`;
    ``progress(n)`` after each). ``executor``: each chunk is a task (:func:`_match_chunk`) on the
    executor, reading the database (read-only) and returning matches + two-view geometries, written
    here in chunk order. None: with ``settings.num_threads`` > 1 (and more than
    ``LOCAL_PROCESSES_FROM_PAIRS`` pairs) the chunks run on that many local processes (see below),
    else on one thread, here.

    COLMAP's CPU matcher is matched on one thread a process: with two matcher threads in one
    process, the same database re-matched gave a few pairs other matches in about one run in 15
    (tiny sample, 399 pairs: 2 and 11 pairs in 35 runs; on one thread 0 in 31), most likely its
    FAISS index and the bundled BLAS used by two threads at once. So the database does not depend
    on the executor or the run."""
    if executor is not None:
        # at least a chunk a worker
        parts = getattr(executor, "workers", 1)
        return _match_pairs_on(executor, db_path, _chunks(pairs, settings.chunk_pairs, parts), settings, progress)
    if settings.num_threads > 1 and len(pairs) > LOCAL_PROCESSES_FROM_PAIRS:
        from ..localize.executors import make_executor

        ex = make_executor("local", settings.num_threads)
        try:
            return _match_pairs_on(ex, db_path, _chunks(pairs, settings.chunk_pairs, settings.num_threads),
                                   settings, progress)
        finally:
            ex.close()
    mo, vo = _matching_options(dataclasses.replace(settings, num_threads=1))
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    pairs_file = work_dir / "pairs_chunk.txt"
    for chunk in _chunks(pairs, settings.chunk_pairs, 1):
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
        po = pycolmap.ImportedPairingOptions()
        po.match_list_path = pairs_file
        pycolmap.match_image_pairs(db_path, matching_options=mo, pairing_options=po,
                                   verification_options=vo, device=pycolmap.Device.cpu)
        if progress:
            progress(len(chunk))
    pairs_file.unlink(missing_ok=True)


def _chunks(pairs: list[tuple[str, str]], chunk_pairs: int, parts: int) -> list[list[tuple[str, str]]]:
    """The pairs in locality order (:func:`~gtkit.sfm.pairs.locality_order`), cut into at least
    ``parts`` runs of about equal size and at most ``chunk_pairs`` each. COLMAP's matcher reads a
    photo's descriptors and builds its search index (~70 ms) once per call, then matches a pair in
    ~57 ms (3,000 SIFT each, one thread; small seed 21): medium's 7,522 pairs in name order and
    chunks of 600 built 2,287 indexes, in locality order and 4 chunks 893. The matches do not depend
    on the chunks (``test_sfm_executor``)."""
    from .pairs import locality_order

    ordered = locality_order(pairs)
    n = min(len(ordered), max(parts, -(-len(ordered) // max(1, chunk_pairs))))
    bounds = np.linspace(0, len(ordered), n + 1).round().astype(int)
    return [ordered[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _match_pairs_on(executor, db_path: Path, chunks: list[list[tuple[str, str]]], settings: MatchSettings,
                    progress) -> None:
    from ..localize.executors import iter_map

    tasks = [(str(db_path), chunk, dataclasses.asdict(settings)) for chunk in chunks]
    results = []  # written after every task ended: no task reads the database while it is written
    for k, res in enumerate(iter_map(executor, _match_chunk, tasks)):
        results.append(res)
        if progress:
            progress(len(tasks[k][1]))
    with _open_shared(db_path) as db:
        for res in results:
            for id1, id2, matches, tvg in res:
                if db.exists_matches(id1, id2) or db.exists_two_view_geometry(id1, id2):
                    continue  # a pair listed twice: the first chunk's result stands, as in match_pairs
                if matches is not None:
                    db.write_matches(id1, id2, matches)
                if tvg is not None:
                    db.write_two_view_geometry(id1, id2, tvg)


def _open_shared(db_path, attempts: int = 30):
    """Open a database that other processes open at the same moment. COLMAP's open writes (it makes
    its tables if absent), and SQLite refuses a second writer: two local matching workers starting
    together failed with "database is locked" ("No registered database factory succeeded"). So the
    open waits and tries again (up to about two minutes) before giving up with the reason."""
    import random
    import time

    for k in range(attempts):
        try:
            return pycolmap.Database.open(db_path)
        except RuntimeError as e:
            if k == attempts - 1:
                raise GtkitError(f"could not open the database: still locked by another process after {attempts} "
                                 f"tries ({e})", db_path) from None
            time.sleep(min(4.0, 0.05 * 2 ** k) * (0.5 + random.random()))


def _match_chunk(task: tuple) -> list[tuple]:
    """An executor task: match and verify a chunk of name pairs as :func:`match_pairs` does, in a
    scratch database holding the chunk's photos (same ids, cameras, rigs, frames, features).
    [(id1, id2, matches or None, TwoViewGeometry or None)]."""
    import tempfile

    db_path, pairs, ms = task
    settings = MatchSettings(**ms)
    names = sorted({n for p in pairs for n in p})
    with tempfile.TemporaryDirectory(prefix="gtkit-match-") as tmp:
        scratch = Path(tmp) / "chunk.db"
        with _open_shared(db_path) as src, pycolmap.Database.open(scratch) as dst:
            for r in src.read_all_rigs():
                dst.write_rig(r, use_rig_id=True)
            for c in src.read_all_cameras():
                dst.write_camera(c, use_camera_id=True)
            for f in src.read_all_frames():
                dst.write_frame(f, use_frame_id=True)
            ids = {}
            for n in names:
                im = src.read_image_with_name(n)
                ids[n] = im.image_id
                dst.write_image(im, use_image_id=True)
                dst.write_keypoints(im.image_id, src.read_keypoints(im.image_id))
                dst.write_descriptors(im.image_id, src.read_descriptors(im.image_id))
        pairs_file = Path(tmp) / "pairs.txt"
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        mo, vo = _matching_options(dataclasses.replace(settings, num_threads=1))  # see match_pairs
        po = pycolmap.ImportedPairingOptions()
        po.match_list_path = pairs_file
        pycolmap.match_image_pairs(scratch, matching_options=mo, pairing_options=po, verification_options=vo,
                                   device=pycolmap.Device.cpu)
        out = []
        with pycolmap.Database.open(scratch) as db:
            for a, b in pairs:
                i, j = ids[a], ids[b]
                m = np.asarray(db.read_matches(i, j)) if db.exists_matches(i, j) else None
                g = db.read_two_view_geometry(i, j) if db.exists_two_view_geometry(i, j) else None
                out.append((i, j, m, g))
    return out


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
