"""``gtkit register DIR``: the stage. Each query sequence placed in the reference frame
(:mod:`.sequences`), automatic tie points found between the placed query photos and the reference
photos, the joint adjustment choosing which of them to keep (:mod:`.tie_bias`, :mod:`.joint`), each
photo's uncertainty (:mod:`.uncertainty`) and the record (:mod:`.record`)."""
from __future__ import annotations

import logging
import time
from pathlib import Path


from ...errors import GtkitError
from ...io.atomic import read_json_object
from ...io.tiepoints import read_tiepoints
from ...photo_positions import positions_and_accuracy
from ...project import Project, file_fingerprint, stage_done, start_stage_clock
from ...queries import reference_calibrations
from .. import quiet_colmap
from ..blocks import QUERIES_STAGE, REFERENCE_STAGE
from ..crossmatch import cross_matches, reference_point_of
from ..extend_reference import extension_ties
from ..geometry import model_cameras, model_poses
from ..registration_record import read_registration
from ..tie_surface import smooth_surface_judge
from .record import _count_query_images, joint_record, tie_table, write_empty, write_record
from .real_photo_terms import feature_side_of
from .reference import ReferenceBlock
from .sequences import Placed, place_sequences
from .settings import STAGE, RegisterSettings, check_settings
from .joint import ties_per_photo
from .tie_bias import _adjust_choosing_ties
from .uncertainty import query_poses, unverify_uninformative
from .coestimate import carry_over, coestimate, why_not

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


def _reference_model(paths) -> Path | None:
    """The project's reference model, or None before one is built or imported."""
    from ...export.sources import reference_model

    try:
        return reference_model(paths)
    except GtkitError:
        return None


def _inputs(P, ref_dir: Path, seq_dirs: dict[str, Path], model: Path | None) -> dict:
    """The fingerprints of what the stage reads (its record is reused while they and the settings hold)."""
    inputs = {"tiepoints": file_fingerprint(P.tiepoints),
              "reference": file_fingerprint(ref_dir / "images.bin"),
              "queries": {s: file_fingerprint(d / "images.bin") for s, d in seq_dirs.items()}}
    if model is not None:   # the automatic ties it keeps depend on it
        from ...export.sources import input_fingerprint_paths
        inputs["model"] = [file_fingerprint(f) for f in input_fingerprint_paths(model)]
    return inputs


def run(project: Project | str | Path, settings: RegisterSettings, force: bool = False) -> dict:
    """``gtkit register DIR``: pseudo-GT poses of every registered query photo."""
    quiet_colmap()
    project = project if isinstance(project, Project) else Project.load(project)
    P = project.paths
    check_settings(settings, project.paths.root)
    out = P.stage(STAGE)
    ref_dir = P.stage(REFERENCE_STAGE) / "model"
    if not ref_dir.is_dir():
        raise GtkitError("reference block missing: run `gtkit sfm DIR --block reference` first", ref_dir)
    seq_dirs = {s: P.stage(QUERIES_STAGE) / s / "model" for s in P.query_sequences()}
    model = _reference_model(P) if settings.cross.enabled and settings.smooth_surface.enabled else None
    inputs = _inputs(P, ref_dir, seq_dirs, model)
    if not force and stage_done(out, settings, inputs):
        return read_registration(project.paths.registration, strict=True)
    start_stage_clock(out)   # (also under --force): its log goes to work/register/log.txt
    t0 = time.time()
    tiepoints = read_tiepoints(P.tiepoints) if P.tiepoints.is_file() else []   # no file: no clicks
    ref = ReferenceBlock(project, ref_dir, P.stage(REFERENCE_STAGE) / "database.db", settings)
    placed = place_sequences(ref, seq_dirs, tiepoints)
    t_sim = time.time()
    result = {"sequences": placed.report, "n_registered": 0, "n_images": _count_query_images(P, seq_dirs),
              "images": {}}
    out.mkdir(parents=True, exist_ok=True)
    if not placed.blocks:
        return write_empty(out, result, settings, inputs)
    # every click of every tie point that touches a registered sequence
    prefixes = tuple(f"queries/{s}/" for s in placed.blocks)
    clicks = {tp.id: {o.image: (o.x, o.y) for o in tp.observations}
              for tp in tiepoints if any(o.image.startswith(prefixes) for o in tp.observations)}
    return _adjust_and_record(project, ref, placed, clicks, model, out, result, inputs, (t0, t_sim))


def _automatic_ties(project: Project, ref: ReferenceBlock, placed: Placed, model: Path | None, out: Path
                    ) -> tuple[dict, set[str], int, dict]:
    """(automatic tie points: id -> {image: (x, y)}, those on rough model surface, how many the cross
    matching found): SIFT matches between the placed query photos and the reference photos, and the
    photos resected on their own joined to the reference block (``[register.extend]``)."""
    P, settings = project.paths, ref.settings
    qp, qc = {}, {}
    for rec_q in placed.blocks.values():
        qp.update(model_poses(rec_q))
        qc.update(model_cameras(rec_q))
    auto = cross_matches(qp, qc, [P.stage(QUERIES_STAGE) / sq / "database.db" for sq in placed.blocks], ref.rec,
                         ref.db, settings.cross, ref=ref.points_read)
    n_auto_found = len(auto)
    rough, surface = _rough_ties(project, ref, auto, model) if auto else (set(), {})
    solo = sorted(n for n, r in placed.resected.items() if r.get("resected") and n in qp)
    if solo and settings.extend.enabled:
        ext, ext_rec = extension_ties(
            ref.rec, ref.db, {n: (qp[n], qc[n], P.stage(QUERIES_STAGE) / n.split("/")[1] / "database.db") for n in solo},
            P.images, out / "extend", settings.extend, num_threads=settings.num_threads,
            reproducible=settings.reproducible)
        for n, r in ext_rec.items():
            placed.resected[n]["extended"] = r
        auto.update(ext)
    return auto, rough, n_auto_found, surface


def _calibration_sources(P, blocks) -> dict[str, dict]:
    """Per sequence, where its cameras' intrinsics came from (its SfM record): cameras.txt, the
    reference block's calibration of the same camera (:mod:`gtkit.sfm.block_cameras`), its EXIF focal,
    or a self-calibration from its own few photos (which the joint BA then replaces by a calibration
    from the reference's points where the ties allow)."""
    import json

    out = {}
    for q in blocks:
        try:
            b = json.loads((P.stage(QUERIES_STAGE) / q / "block.json").read_text())
        except (OSError, ValueError):
            out[q] = {"source": "unknown (no SfM record)"}
            continue
        pol = b.get("intrinsics_policy", {})
        if pol.get("self_calibrated_cameras"):
            out[q] = {"source": "self-calibrated", "n_photos": b.get("n_registered")}
        elif b.get("calibration_from_reference"):
            rules = sorted(b["calibration_from_reference"])
            # taken by size alone (no EXIF camera identity): a guess the ties confirm or correct
            guess = any(r.startswith("same sensor") for r in rules)
            out[q] = {"source": "self-calibrated" if guess else "the reference block's calibration: " + "; ".join(rules),
                      **({"start": "the reference block's calibration (" + "; ".join(rules) + ")"} if guess else {})}
        elif pol.get("fixed_cameras"):
            out[q] = {"source": "cameras.txt"}
        else:
            out[q] = {"source": "EXIF focal" + (", refined by its SfM" if pol.get("exif_focal_refined") else "")}
    return out


def _rough_ties(project: Project, ref: ReferenceBlock, auto: dict, model: Path | None) -> tuple[set[str], dict]:
    """(the automatic ties the model shows off smooth surface, :mod:`gtkit.sfm.tie_surface`; those it
    cannot judge, the disk off the model, are not among them; the record of how they were judged)."""
    settings = ref.settings.smooth_surface
    judge = smooth_surface_judge(model, project.frame, settings, ref.rec,
                                 feature_side_of(project.paths.stage(REFERENCE_STAGE)))
    if judge is None:
        why = ("off ([register.smooth_surface] enabled = false)" if not settings.enabled else
               "no reference model (not built or imported, or it could not be drawn)")
        return set(), {"model": None, "why": f"not judged: {why}; every automatic tie kept on the reference "
                                             "SfM's own points"}
    try:
        ids = sorted(auto)
        keep, decided = judge.judge([reference_point_of(t) for t in ids])
    finally:
        judge.release()
    rough = {t for t, k, d in zip(ids, keep, decided) if d and not k}
    log.info("automatic tie points: %d of %d on smooth model surface, %d off it, %d undecided (kept)",
             int((keep & decided).sum()), len(ids), len(rough), int((~decided).sum()))
    return rough, {"model": str(model), "n_smooth": int((keep & decided).sum()), "n_rough": len(rough),
                   "n_undecided": int((~decided).sum())}


def _adjust_and_record(project: Project, ref: ReferenceBlock, placed: Placed, clicks: dict, model: Path | None,
                       out: Path, result: dict, inputs: dict, times: tuple[float, float]) -> dict:
    """The joint adjustment of the placed sequences with ``clicks`` (every click of every tie point
    touching them) and the automatic tie points, each photo's uncertainty, and the record written."""
    settings, blocks = ref.settings, placed.blocks
    t0, t_sim = times
    prefixes = tuple(f"queries/{s}/" for s in blocks)
    t_cm = time.time()
    auto, rough, n_auto_found, result["tie_surface"] = _automatic_ties(project, ref, placed, model, out)
    clicks.update(auto)
    t_cm = time.time() - t_cm
    calibration = _calibration_sources(project.paths, blocks)
    calibrate = {q: "confirm" if "start" in c else "self" for q, c in calibration.items() if c["source"] == "self-calibrated"}
    j, summary, cov, dropped, auto_choice = _adjust_choosing_ties(ref.rec, blocks, placed.statuses, clicks, set(auto),
                                                                 rough, settings, calibrate)
    for q, c in calibration.items():
        n_ties = c["automatic_ties_per_photo"] = ties_per_photo(j, q)
        if j.seq_cams.get(q) and j.seq_cams[q] <= j.calibrated:
            c["source"] = "calibrated from the reference's 3D points" + (f", starting from {c['start']}" if "start" in c else "")
        elif "start" in c and n_ties >= settings.calibrate_from_ties:
            c["source"] = c.pop("start") + ", confirmed by the ties"
        elif q in calibrate:
            c["why_not_from_reference"] = (f"{n_ties} automatic ties a photo, "
                                           f"{settings.calibrate_from_ties} needed to calibrate from them")
        placed.report[q]["calibration"] = c
    auto = {t: v for t, v in auto.items() if t in j.clicks}
    # the sequences whose automatic ties off smooth surface were dropped
    smooth_only = sorted(q for q, c in auto_choice.items() if c["smooth_only"])
    t_ba = time.time()
    swung = set(blocks) if settings.systematic_swing_where == "all" else set(smooth_only)
    P = project.paths
    # the size each block found its features at; a sequence whose SfM made no model has no record:
    # its features were found at the reference block's size (blocks.block_feature_settings)
    sides = {"reference": feature_side_of(P.stage(REFERENCE_STAGE))}
    sides.update({q: feature_side_of(P.stage(QUERIES_STAGE) / q) or sides["reference"] for q in blocks})

    def ref_positions_of(names):   # the reference photos' own positions: the block's misfit to them scales its term
        try:
            return positions_and_accuracy(project, names, per_axis=True)
        except GtkitError as e:
            log.warning("reference photos' positions unreadable (%s): the reference term is not checked against them", e)
            return None, None
    poses, cams, covs, per_image, floors = query_poses(j, cov, settings.systematic_swing_px, swung, placed.resected,
                                                       P.stage(REFERENCE_STAGE) / "model", settings.sigma, sides,
                                                       ref_positions_of)
    poses, result["coestimation"] = _coestimated(project, ref, placed, poses, cams, covs, per_image, floors, out)
    joined = set(result["coestimation"].get("joined_reference_camera") or [])
    for q in blocks:
        c = placed.report[q].get("calibration")
        mine = [n for n in poses if n.startswith(f"queries/{q}/")]
        if c and mine and all(n in joined for n in mine):
            c["joint_source"] = c["source"]
            c["source"] = ("the reference block's camera, calibrated again with the reference photos and the query "
                           "photos together (co-estimated)")
    for n in unverify_uninformative(per_image):
        log.warning("%s: unverified: %s", n, per_image[n]["unverified"])
    tie_rows, bad = tie_table(j, clicks, placed.statuses, dropped, placed.report, prefixes)
    for seq in blocks:
        placed.report[seq]["n_tiepoints_final_ba"] = sum(1 for r in tie_rows.values()
                                                         if r["sequence"] == seq and r["in_final_ba"])
    result.update(joint_record(j, summary, per_image, tie_rows, bad, auto, n_auto_found, smooth_only, auto_choice,
                               {"sim3": t_sim - t0, "cross_matching": t_cm, "joint_ba": t_ba - t_sim - t_cm}))
    return write_record(out, project, j, cov, ref.rec, poses, cams, covs, floors, result, settings, inputs)


def _coestimated(project: Project, ref: ReferenceBlock, placed: Placed, poses: dict, cams: dict, covs: dict,
                 per_image: dict, floors: dict, out: Path) -> tuple[dict, dict]:
    """(the query poses, co-estimated with a small reference block where :mod:`.coestimate` applies,
    its record)."""
    settings = ref.settings
    block = read_json_object(project.paths.stage(REFERENCE_STAGE) / "block.json") or {}
    held = block.get("held_by_positions")
    why = why_not(ref.rec, held, settings.coestimate)
    if why is None:
        names = sorted(im.name for im in ref.rec.images.values() if im.has_pose)
        try:
            positions, accuracy = positions_and_accuracy(project, names)
        except GtkitError as e:
            positions, why = {}, f"the reference photos' positions unreadable ({e})"
    if why is not None:
        log.info("query photos not co-estimated with the reference block: %s", why)
        return poses, {"applied": False, "reason": why}
    priors = {"positions": positions, "accuracy": accuracy, "sigma_hv": (held["sigma_h_m"], held["sigma_v_m"]),
              # the photos the reference stage did not hold (a record before its "not_held": its georegistration's)
              "outliers": held.get("not_held", (block.get("georegistration") or {}).get("outliers") or [])}
    self_calibrated = {int(c): v.get("refined", []) for c, v in (block.get("intrinsics") or {}).items()
                       if "principal point" in v.get("refined", [])}
    # a photo of the same camera as a self-calibrated reference camera joins the block as that camera:
    # the block's BA calibrates it from every photo, as one SfM of all the photos would
    same = reference_calibrations(project, sorted(poses))[0] if self_calibrated else {}
    photos = {n: (p, cams[n], project.paths.stage(QUERIES_STAGE) / n.split("/")[1] / "database.db")
              for n, p in poses.items()}
    moved_to, calibrated, record = coestimate(ref.rec, ref.db, photos, priors, project.paths.images,
                                              out / "coestimate", settings.coestimate,
                                              num_threads=settings.num_threads, reproducible=settings.reproducible,
                                              self_calibrated=self_calibrated, same_camera=same)
    if not moved_to:
        log.warning("query photos not co-estimated with the reference block: %s", record.get("reason"))
        return poses, record
    cams.update(calibrated)
    return carry_over(poses, covs, per_image, floors, moved_to), record
