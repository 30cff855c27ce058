"""The reference block seeded by what its photos already know (issue 34).

UAVD4L-style reference flights carry an RTK position (centimetres) and the DJI gimbal attitude in
every photo. Instead of growing the block photo by photo (``pycolmap.incremental_mapping``), each
photo starts at its prior pose, the database's matches are triangulated with those poses, and a
bundle adjustment with the positions as priors (gtkit.sfm.prior_ba) refines poses and points:

1. **eligible** (:func:`seeding_check`): nearly every photo has a position and a gimbal attitude,
   and no position's stated accuracy (geo.txt) is worse than ``MAX_PRIOR_ACCURACY_M``; and (checked
   by gtkit.sfm.blocks) every camera is calibrated (cameras.txt): with only an EXIF focal length the
   positions and a focal length a few % off disagree and the seeded block bends;
2. **seed**: position from GPS / geo.txt in the project frame (the same positions the
   georegistration uses), rotation from the gimbal angles (gtkit.conventions.dji_to_rotation);
3. **triangulate** every match with the poses held, then a pose-prior BA with a loose position
   sigma (``SEED_SIGMA_M``: the images set the block's shape, the positions its place). A heading
   error common to every photo (a gimbal's compass, the meridian convergence of a projected CRS)
   leaves the loosely held block turned about its positions: a Sim(3) onto the positions turns it
   back, and where the photos were turned alike by more than ``SEED_RESEED_DEG`` the block is
   seeded again with that turn taken out of every attitude (measured on tiny seed 0: 1.5, 3 and
   5 deg of added heading error seeded as well as none);
4. **misfits**: a photo whose prior may not fit (moved by the BA beyond ``MISFIT_SHIFT_M`` /
   ``MISFIT_ROTATION_DEG``, too few of its points seen by 3+ photos) is taken out and registered as
   the incremental mapper registers a photo (absolute pose from its matches to the block's points,
   ``IncrementalMapper.register_next_image``); where that pose is as far from its prior, the photo
   misfits and its position leaves the priors (here and in gtkit.sfm.blocks' position-held BA): it
   is never left at a prior that does not fit. A photo without a prior is registered the same way;
5. **measured**: where more than ``MAX_MISFIT_SHARE`` of the photos misfit, or the positions
   scatter about the block by more than ``MAX_PRIOR_ACCURACY_M`` (metre-grade GPS that states
   nothing), or the attitudes are off by more than a heading error, the whole block goes back to
   the incremental mapper, with that reason (the real DJI consumer block of tests/test_sfm.py, its
   cameras taken as calibrated: the seeding BA turned its photos 46 deg in common; tiny seed 0 with
   a 1 m wandering GPS error added: 20 of 45 photos off their priors);
6. **final BA**: the tracks merged and filtered at the mapper's thresholds, the photos placed again
   in, one more pose-prior BA to convergence (the seeding BA of step 3 stops after
   ``SEED_BA_FIRST_ITERATIONS``: its job is the block's turn and the misfits, not the last millimetre).

The result is a block in the project frame; gtkit.sfm.blocks georegisters it (a Sim(3) near the
identity), checks it for plausibility and holds it by its positions as it does any mapper's block.
"""
from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..conventions import dji_to_rotation, rotation_angle_deg, translation_from_center
from .geometry import RegistrationError, robust_sim3
from .prior_ba import hold_by_positions

log = logging.getLogger(__name__)

# seeded only where the positions are this good (stated in geo.txt, or measured in step 5), metres
MAX_PRIOR_ACCURACY_M = 0.5
MIN_SEEDED_SHARE = 0.95        # of the block's photos with a position and a gimbal attitude
SEED_SIGMA_M = 0.25            # position sigma in the seeding BA (a stated accuracy, where smaller)
# iterations of the final BA. Medium seed 6 (same database, loaded), when it was the only BA: 8 -> 30: mapping
# 50 -> 99 CPU s, but the position-held BA after georegistration 187 -> 66 CPU s (it started further off),
# worst camera 0.089 -> 0.081 m (incremental: 0.073 m)
SEED_BA_ITERATIONS = 30
# the seeding BA before the tracks are merged and filtered stops after this many: the final BA (above's
# iterations, on the merged, filtered tracks, the photos placed by their matches in) does the rest. Medium
# seed 7, same database, idle: 30 + 30 -> 10 + 30: mapping 102 -> 63 s (142 -> 79 CPU s), cameras equal
SEED_BA_FIRST_ITERATIONS = 10
SEED_BA_ROUNDS = 4             # seeding BA + Sim(3) onto the positions, until the Sim(3) turns less than
SEED_TURN_DONE_DEG = 0.3       # this many degrees (small 14: a 0.14 deg turn cost a second BA, for nothing)
SEED_ATTEMPTS = 3              # seedings at most (each with the common turn the last one found taken out)
SEED_RESEED_DEG = 0.5          # a common turn larger than this: seeded again with the attitude turned by it
SEED_MAX_HEADING_DEG = 10.0    # a larger common turn: the priors do not fit (no heading error is that large)
SEED_MERGE_PX = 10.0           # tracks joined before the seeding BA within this reprojection error
MISFIT_SHIFT_M = 1.0           # a photo the seeding BA moves farther than this from its prior is checked ...
MISFIT_ROTATION_DEG = 3.0      # ... or turns farther than this from its gimbal attitude (the turn common to all taken out)
MISFIT_MIN_OBSERVATIONS = 30   # ... or whose points seen by 3+ photos are fewer (or under a quarter of the
                               # median, or half its points)
MAX_MISFIT_SHARE = 0.2         # more misfits than this: the whole block is mapped incrementally


@dataclass
class Seeded:
    rec: pycolmap.Reconstruction | None
    record: dict = field(default_factory=dict)   # block.json's "seeded": photos seeded, misfits, fallback, seconds
    outliers: set[str] = field(default_factory=set)   # photos whose position left the priors


def seeding_check(names: list[str], positions: dict[str, np.ndarray], accuracy: dict[str, float],
                  metas: dict) -> tuple[bool, str]:
    """Whether the block can be seeded by its photos' priors, and why (one line)."""
    n = len(names)
    with_pose = [x for x in names if x in positions and metas.get(x) is not None and metas[x].has_gimbal]
    if not n or len(with_pose) < MIN_SEEDED_SHARE * n:
        n_att = sum(1 for x in names if metas.get(x) is not None and metas[x].has_gimbal)
        return False, (f"{len(with_pose)} of {n} photos have both a position and a gimbal attitude "
                       f"({sum(1 for x in names if x in positions)} positions, {n_att} attitudes; "
                       f"{100 * MIN_SEEDED_SHARE:.0f} % needed to seed)")
    coarse = sorted(x for x in with_pose if accuracy.get(x, 0.0) > MAX_PRIOR_ACCURACY_M)
    if coarse:
        return False, (f"{len(coarse)} positions state an accuracy worse than {MAX_PRIOR_ACCURACY_M} m "
                       f"(geo.txt; e.g. {coarse[0]}: {accuracy[coarse[0]]} m)")
    stated = sum(1 for x in with_pose if x in accuracy)
    return True, (f"{len(with_pose)} of {n} photos have a position and a gimbal attitude"
                  + (f" ({stated} with a stated accuracy <= {MAX_PRIOR_ACCURACY_M} m)" if stated else
                     f" (accuracy stated nowhere: measured while seeding, <= {MAX_PRIOR_ACCURACY_M} m needed)"))


def prior_pose(position: np.ndarray, meta, turn: np.ndarray | None = None) -> pycolmap.Rigid3d:
    """cam_from_world of a photo at ``position`` (project frame) with its gimbal attitude (turned by
    ``turn``, a world-frame rotation: a heading correction common to the block)."""
    R = dji_to_rotation(meta.gimbal_yaw, meta.gimbal_pitch, meta.gimbal_roll)
    if turn is not None:
        R = R @ turn
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R), translation_from_center(R, np.asarray(position, float)))


def _support(rec: pycolmap.Reconstruction) -> dict[int, tuple[int, int]]:
    """{image id: (its observations, those of points seen by 3 or more photos)}. A point seen by two
    photos fits any two poses that share its epipolar plane (a prior moved along the flight line);
    one seen by three or more holds each of them. (Observations over the filter's reprojection error
    are gone already: a photo whose prior does not fit loses its points.)"""
    n_obs: dict[int, int] = {}
    n_multi: dict[int, int] = {}
    for p in rec.points3D.values():
        ids = [el.image_id for el in p.track.elements]
        for i in ids:
            n_obs[i] = n_obs.get(i, 0) + 1
            if len(ids) >= 3:
                n_multi[i] = n_multi.get(i, 0) + 1
    return {i: (n_obs.get(i, 0), n_multi.get(i, 0)) for i, im in rec.images.items() if im.has_pose}


def _common_turn(rec, seeds: dict[int, pycolmap.Rigid3d]) -> np.ndarray:
    """The rotation (world frame) the seeding BA gave every photo alike: a gimbal's heading bias (its
    compass, the meridian convergence of a projected CRS) that the block's shape does not depend on."""
    from scipy.spatial.transform import Rotation

    turns = [seeds[i].rotation.matrix().T @ rec.images[i].cam_from_world().rotation.matrix() for i in seeds]
    return Rotation.from_matrix(turns).mean().as_matrix() if turns else np.eye(3)


def _off_prior(T: pycolmap.Rigid3d, prior: pycolmap.Rigid3d, common: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) a pose is from its prior, the common turn taken out of the rotation."""
    shift = float(np.linalg.norm(T.inverse().translation - prior.inverse().translation))
    return shift, rotation_angle_deg(prior.rotation.matrix().T @ T.rotation.matrix(), common)


def _suspects(rec, seeds: dict[int, pycolmap.Rigid3d], common: np.ndarray) -> dict[int, str]:
    """{image id: why its prior may not fit} after the seeding BA (checked then by its matches)."""
    sup = _support(rec)
    n_med = float(np.median([f[1] for f in sup.values()])) if sup else 0.0
    out = {}
    for iid, prior in seeds.items():
        n_obs, n_multi = sup.get(iid, (0, 0))
        shift, turn = _off_prior(rec.images[iid].cam_from_world(), prior, common)
        if shift > MISFIT_SHIFT_M or turn > MISFIT_ROTATION_DEG:
            out[iid] = f"moved {shift:.2f} m / turned {turn:.1f} deg from its prior by the seeding BA"
        elif n_multi < max(MISFIT_MIN_OBSERVATIONS, 0.25 * n_med, 0.5 * n_obs):
            out[iid] = (f"{n_multi} of its {n_obs} points at its prior are seen by 3 or more photos "
                        f"(median photo: {n_med:.0f})")
    return out


def _onto_priors(rec: pycolmap.Reconstruction, names: list[str], positions: dict[str, np.ndarray]) -> float | None:
    """``rec`` moved by the robust Sim(3) that takes its camera centres onto ``positions``; its angle
    (degrees), None where no Sim(3) is found (too few photos, all on a line)."""
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    names = [n for n in names if n in by_name]
    try:
        fit = robust_sim3(np.array([by_name[n].projection_center() for n in names]),
                          np.array([positions[n] for n in names]), MISFIT_SHIFT_M, what="seeded camera centres")
    except RegistrationError:
        return None
    rec.transform(fit.tgt_from_src)
    return round(rotation_angle_deg(fit.tgt_from_src.rotation.matrix(), np.eye(3)), 3)


def _prior_ba(rec, positions, outliers, accuracy, num_threads, max_iterations) -> dict:
    """The seeding BA: positions as loose priors (a stated accuracy where tighter), every pose and point free."""
    loose = {n: min(SEED_SIGMA_M, a) for n, a in accuracy.items()}
    return hold_by_positions(rec, positions, outliers, loose, min_sigma_m=SEED_SIGMA_M, max_iterations=max_iterations,
                             num_threads=num_threads, seeding=True)


def _seed(cache: pycolmap.DatabaseCache, names: list[str], positions: dict, metas: dict,
          tri: pycolmap.IncrementalTriangulatorOptions, turn: np.ndarray):
    """(mapper, reconstruction, {image id: prior pose}): every photo with a prior at its prior pose
    (rotation turned by ``turn``, world frame), the matches triangulated."""
    mapper = pycolmap.IncrementalMapper(cache)
    rec = pycolmap.Reconstruction()
    mapper.begin_reconstruction(rec)
    by_name = {im.name: iid for iid, im in rec.images.items()}
    seeds = {}
    for n in names:
        iid, m = by_name.get(n), metas.get(n)
        if iid is None or n not in positions or m is None or not m.has_gimbal:
            continue
        seeds[iid] = prior_pose(positions[n], m, turn)
        im = rec.images[iid]
        rec.frame(im.frame_id).set_cam_from_world(im.camera_id, seeds[iid])
        mapper.observation_manager.register_frame(im.frame_id)
    for iid in seeds:
        mapper.triangulate_image(tri, iid)
    # the gimbal's rotation error splits tracks that are one point (a few px apart): joined before the BA
    # (fewer, longer tracks: a cheaper and stiffer BA), checked at the usual threshold after it
    loose = copy.copy(tri)
    loose.merge_max_reproj_error = loose.complete_max_reproj_error = SEED_MERGE_PX
    mapper.complete_and_merge_tracks(loose)
    return mapper, rec, seeds


def seeded_mapping(db: Path, names: list[str], positions: dict[str, np.ndarray], accuracy: dict[str, float],
                   metas: dict, options: pycolmap.IncrementalPipelineOptions, num_threads: int = -1) -> Seeded:
    """The block seeded by its priors (module docstring); ``Seeded.rec`` None: map it incrementally
    (``record["fallback"]`` says why). ``options``: the incremental mapper's (triangulation, filtering,
    absolute pose), so that photos registered from their matches are registered as it would. The
    cameras' intrinsics are held (gtkit.sfm.blocks seeds only blocks whose cameras are calibrated)."""
    t0 = time.time()
    with pycolmap.Database.open(db) as d:
        copts = pycolmap.DatabaseCacheOptions()
        copts.min_num_matches = options.min_num_matches
        cache = pycolmap.DatabaseCache.create(d, copts)
    # the pipeline's own copies: they carry its random_seed (0) and threads. options.triangulation and
    # options.mapper as set hold random_seed -1 (a new seed each run): the block differed run to run
    tri, mopts = options.get_triangulation(), options.get_mapper()
    clock, last = {}, [t0]

    def lap(step):
        clock[step], last[0] = round(time.time() - last[0], 1), time.time()

    record = {"seconds": clock}
    turn = np.eye(3)
    for attempt in range(SEED_ATTEMPTS):
        mapper, rec, seeds = _seed(cache, names, positions, metas, tri, turn)
        lap("triangulation" if attempt == 0 else f"triangulation {attempt + 1}")
        record.update(n_seeded=len(seeds), n_points3D_triangulated=rec.num_points3D())
        # a common error of the gimbal's heading (compass, meridian convergence) leaves the block, loosely
        # held, turned as a whole about its priors (a flat valley for the BA): the best Sim(3) onto the
        # positions turns it back, cameras and points alike, and the BA goes on from there
        turns = []
        for _ in range(SEED_BA_ROUNDS):
            _prior_ba(rec, positions, set(), accuracy, num_threads, SEED_BA_FIRST_ITERATIONS)
            turns.append(_onto_priors(rec, [rec.images[i].name for i in seeds], positions))
            if turns[-1] is None or turns[-1] < SEED_TURN_DONE_DEG:
                break
        record["sim3_to_priors_deg"] = turns
        lap("bundle adjustment" if attempt == 0 else f"bundle adjustment {attempt + 1}")
        common = _common_turn(rec, seeds)
        left_deg = rotation_angle_deg(common, np.eye(3))
        if left_deg < SEED_RESEED_DEG:
            break
        if left_deg > SEED_MAX_HEADING_DEG:
            record["fallback"] = (f"the photos do not fit their priors: the seeding BA turned them {left_deg:.0f} deg "
                                  f"in common (a gimbal's heading error is a few degrees)")
            return Seeded(None, record)
        if attempt == SEED_ATTEMPTS - 1:
            record["fallback"] = (f"the gimbal attitude is off by {rotation_angle_deg(turn @ common, np.eye(3)):.1f} deg "
                                  f"in common, {left_deg:.1f} deg of it left after {SEED_ATTEMPTS} seedings")
            return Seeded(None, record)
        # the points were made with that error in every ray: made again from priors without it
        turn = turn @ common
        record["heading_correction_deg"] = round(rotation_angle_deg(turn, np.eye(3)), 3)
    obs = mapper.observation_manager
    by_name = {im.name: iid for iid, im in rec.images.items()}
    mapper.complete_and_merge_tracks(tri)
    mapper.filter_points(mopts)
    lap("tracks merged")
    common = _common_turn(rec, seeds)
    record["common_turn_deg"] = round(rotation_angle_deg(common, np.eye(3)), 3)
    suspects = _suspects(rec, seeds, common)
    lap("photos checked")
    if len(suspects) > 2 * MAX_MISFIT_SHARE * len(seeds):
        iid, why = next(iter(suspects.items()))
        record["fallback"] = (f"{len(suspects)} of {len(seeds)} photos do not fit their priors: e.g. "
                              f"{rec.images[iid].name}: {why}")
        return Seeded(None, record)
    # the positions' scatter about the block the images made: what the GPS is worth, measured
    ok = [rec.images[i].name for i in seeds if i not in suspects]
    r = np.array([rec.images[by_name[n]].projection_center() - positions[n] for n in ok]).reshape(-1, 3)
    scatter = float(np.median(np.linalg.norm(r - np.median(r, axis=0), axis=1))) if len(r) else 0.0
    record["position_scatter_m"] = round(scatter, 4)
    if scatter > MAX_PRIOR_ACCURACY_M:
        record["fallback"] = (f"the positions scatter {scatter:.2f} m about the block the photos make "
                              f"(> {MAX_PRIOR_ACCURACY_M} m: not RTK-grade)")
        return Seeded(None, record)
    # suspects and photos without a prior: registered from their matches to the block's points, as the
    # incremental mapper registers a photo; a suspect its matches place away from its prior misfits
    for iid in suspects:
        obs.deregister_frame(rec.images[iid].frame_id)
    left = [by_name[n] for n in names if n in by_name and by_name[n] not in seeds]
    misfit, placed, failed, checked = {}, {}, {}, []
    for iid in list(suspects) + left:
        name = rec.images[iid].name
        why = suspects.get(iid, "no prior pose (position or gimbal attitude missing)")
        if not mapper.register_next_image(mopts, iid):
            failed[name] = f"{why}; not registered from its matches either"
            continue
        mapper.triangulate_image(tri, iid)
        if iid not in seeds:
            placed[name] = why
            continue
        shift, off_deg = _off_prior(rec.images[iid].cam_from_world(), seeds[iid], common)
        if shift > MISFIT_SHIFT_M or off_deg > MISFIT_ROTATION_DEG:
            misfit[name] = f"{why}; its matches place it {shift:.2f} m / {off_deg:.1f} deg from its prior"
        else:
            checked.append(name)
    bad = len(misfit) + sum(1 for n in failed if by_name[n] in seeds)
    record["misfit_share"] = round(bad / max(1, len(seeds)), 3)
    if bad > MAX_MISFIT_SHARE * len(seeds):
        name, why = next(iter({**misfit, **failed}.items()))
        record["fallback"] = (f"{bad} of {len(seeds)} photos do not fit their priors (more than "
                              f"{100 * MAX_MISFIT_SHARE:.0f} %): e.g. {name}: {why}")
        return Seeded(None, record)
    outliers = set(misfit) | set(failed)
    if suspects or left:
        mapper.complete_and_merge_tracks(tri)
        lap("photos placed by their matches")
    # the final BA, always: on the merged, filtered tracks (and the photos placed again), to convergence
    _prior_ba(rec, positions, outliers, accuracy, num_threads, SEED_BA_ITERATIONS)
    mapper.filter_points(mopts)
    lap("final bundle adjustment")
    mapper.filter_frames(mopts)
    clock["total"] = round(time.time() - t0, 1)
    record.update({"misfits": misfit, "placed_by_matches": placed, "not_registered": failed,
                   "suspects_that_fit": checked})
    log.info("seeded block: %d photos at their priors, %d placed by their matches instead (%d of them misfit "
             "their priors), %d not registered, %d points in %.1f s", len(seeds) - len(suspects),
             len(suspects) + len(left) - len(failed), len(misfit), len(failed), rec.num_points3D(), time.time() - t0)
    return Seeded(rec, record, outliers)
