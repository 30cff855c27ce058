"""The stage's record: ``registration.json`` (each sequence's outcome, each query photo's, each tie
point's final residuals and the clicks dropped as mistakes), the poses and their covariances, and the
next clicks suggested (``guided_clicks.json``). Its one reader of the sequence outcomes is
:mod:`gtkit.sfm.registration_record`."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...io.atomic import write_json
from ...io.poses import COVARIANCES, INTRINSICS, POSES, write_covariances, write_intrinsics, write_poses
from ...project import Project, mark_stage_done
from ..crossmatch import AUTO_PREFIX
from ..guided_clicks import (COVARIANCE_FILE, GUIDANCE_FILE, GuidanceSettings, guidance, reference_views, save_states,
                             sequence_states)
from .joint import Joint, point_reprojection_errors
from .settings import RegisterSettings


def _write_guidance(out: Path, rec, cov, ref_ids, floors, ref_rec, settings: GuidanceSettings,
                    unregistered: dict[str, list[str]]) -> None:
    """``guided_clicks.json`` (the next clicks per sequence, :mod:`gtkit.sfm.guided_clicks`; for the
    ``unregistered`` sequences, photos to click first) and the sequences' joint covariances it was
    computed from (``sequence_covariance.npz``)."""
    for f in (GUIDANCE_FILE, COVARIANCE_FILE):
        (out / f).unlink(missing_ok=True)
    if not settings.enabled or cov is None:
        return
    states = sequence_states(rec, cov, ref_ids, floors)
    save_states(out / COVARIANCE_FILE, states)
    write_json(out / GUIDANCE_FILE, guidance(states, rec, reference_views(ref_rec), settings, unregistered))


def _count_query_images(P, seq_dirs) -> int:
    """All photos of the query blocks (registered or not), from each block's record."""
    from ...queries import query_photos

    n = 0
    for seq, d in seq_dirs.items():
        f = d.parent / "block.json"
        n += json.loads(f.read_text())["n_images"] if f.is_file() else len(query_photos(Project.load(P.root), seq))
    return n


def tie_table(j: Joint, clicks: dict, statuses: dict, dropped: dict, seq_report: dict,
              prefixes: tuple[str, ...]) -> tuple[dict, dict]:
    """Per clicked tie point: its final residuals; and the bad ones (gross click mistakes)."""
    rec = j.rec
    tie_table, bad = {}, {}
    status_by_id = {s.id: (seq, s) for seq, st in statuses.items() for s in st}
    for tid in clicks:
        if tid.startswith(AUTO_PREFIX):
            continue
        seq, s = status_by_id.get(tid, (None, None))
        note = s.reason if s else "not usable for the Sim(3)"
        if seq is None:   # no Sim(3) status (its sequence placed by automatic matches, or its photo left out
            # of its sequence's SfM): named by its query clicks, which still count in the joint BA
            seq = next((n.split("/")[1] for n in clicks[tid] if n.startswith(prefixes)), None)
            if seq is not None and seq_report[seq].get("registered_by") == "automatic matches":
                note = "its sequence was placed by the automatic matches (its clicks not used for the Sim(3))"
        row = {"sequence": seq, "sim3_inlier": bool(s and s.inlier), "sim3_residual_m": s.sim3_residual_m if s else None,
               "in_final_ba": tid in j.tie_pids, "note": note}
        if tid in j.tie_pids:
            p = rec.points3D[j.tie_pids[tid]]
            row["reproj_px"] = {rec.images[e.image_id].name: float(np.linalg.norm(
                np.asarray(rec.images[e.image_id].project_point(p.xyz)) - rec.images[e.image_id].points2D[e.point2D_idx].xy))
                for e in p.track.elements}
        drops = (s.dropped_clicks if s else []) + dropped.get(tid, [])
        if drops or (s and s.mistake and tid not in j.tie_pids):
            seen = {}
            for dd in drops:
                seen.setdefault(dd["image"], dd)
            bad[tid] = {"sequence": seq, "reason": ("clicks dropped as mistakes" if drops else s.reason),
                        "dropped_clicks": [{"image": v["image"], "residual_px": float(v["residual_px"])} for v in seen.values()],
                        "in_final_ba": tid in j.tie_pids}
        tie_table[tid] = row
    return tie_table, bad


def joint_record(j: Joint, summary, per_image: dict, tie_rows: dict, bad: dict, auto: dict, n_auto_found: int,
                 smooth_only: list[str], auto_choice: dict, seconds: dict) -> dict:
    """registration.json's fields from the joint adjustment (the sequences' and photos' records aside)."""
    rec = j.rec
    tie_set = set(j.tie_pids.values())
    sfm_err = point_reprojection_errors(rec, [p for p in rec.points3D if p not in tie_set])
    tie_err = [r for row in tie_rows.values() for r in row.get("reproj_px", {}).values()]
    return {
        # registered: a pose with its sigma; unverified: a pose the BA could not give a sigma (not a result)
        "n_registered": sum(1 for i in per_image.values() if "unverified" not in i),
        "n_unverified": sum(1 for i in per_image.values() if "unverified" in i), "images": per_image,
        "median_reproj_px": float(np.median(sfm_err)) if len(sfm_err) else None,
        "mean_reproj_px": float(np.mean(sfm_err)) if len(sfm_err) else None,
        "median_tiepoint_reproj_px": float(np.median(tie_err)) if tie_err else None,
        "median_auto_tiepoint_reproj_px": (float(np.median(point_reprojection_errors(
            rec, [pid for t, pid in j.tie_pids.items() if t.startswith(AUTO_PREFIX)])))
            if any(t.startswith(AUTO_PREFIX) for t in j.tie_pids) else None),
        "n_tiepoints_in_ba": sum(1 for t in j.tie_pids if not t.startswith(AUTO_PREFIX)),
        "n_auto_tiepoints_found": n_auto_found, "auto_tiepoints_on_smooth_surface_only": smooth_only,
        "auto_ties_test_by_sequence": auto_choice,
        "n_auto_tiepoints": len(auto), "n_auto_tiepoints_in_ba": sum(1 for t in j.tie_pids if t.startswith(AUTO_PREFIX)),
        "bad_tiepoints": bad, "tiepoints": tie_rows,
        "ba_final_cost": float(summary.final_cost) if hasattr(summary, "final_cost") else None,
        "seconds": seconds}


def write_empty(out: Path, result: dict, settings: RegisterSettings, inputs: dict) -> dict:
    """The record of a run that registered no sequence (the outputs of an earlier run removed)."""
    for f in (POSES, INTRINSICS, COVARIANCES, GUIDANCE_FILE, COVARIANCE_FILE):
        (out / f).unlink(missing_ok=True)
    write_json(out / "registration.json", result)
    mark_stage_done(out, settings, inputs, n_registered=0)
    return result


def write_record(out: Path, project: Project, j: Joint, cov, ref_rec, poses: dict, cams: dict, covs: dict,
                 floors: dict, result: dict, settings: RegisterSettings, inputs: dict) -> dict:
    """The joint model, the poses, cameras and covariances, the guidance and registration.json."""
    rec = j.rec
    (out / "model").mkdir(exist_ok=True)
    rec.write(out / "model")
    write_poses(out / POSES, poses, header="pseudo-GT poses of the query photos (gtkit register)")
    write_intrinsics(out / INTRINSICS, cams)
    if covs:
        write_covariances(out / "covariances.txt", covs)
    from ...queries import query_photos
    _write_guidance(out, rec, cov, j.ref_ids, floors, ref_rec, settings.guidance,
                    {q: query_photos(project, q) for q, v in result["sequences"].items() if v.get("status") == "error"})
    write_json(out / "registration.json", result)
    mark_stage_done(out, settings, inputs, n_registered=result["n_registered"])
    return result
