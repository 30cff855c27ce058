"""The dataset's datasheet: ``dataset.json`` (every figure, machine-readable) and ``DATASET.md`` (the
same for a reader), with two plots: the query trajectories over the orthophoto and the sigma per photo.

What it states: the site (CRS, origin, extent), the sensors, how the pseudo-GT was made (the reference
block's georegistration and its residuals, the tie points, the joint BA), its accuracy (the sigma
distribution; GCP check points where there are any), the evaluation protocol and its thresholds, the
photos kept out, the files, and the gtkit version and settings that made it. Figures come from the
stages' own records (``block.json``, ``registration.json``, ``stage.json``); nothing under ``truth/``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path, write_json, write_text
from ..project import Project, read_stage_record
from .gt import PublishedGT, load_json

SHEET_MD = "DATASET.md"
PLOTS = "plots"
# The evaluation protocol (UAVD4L's, after Sattler et al.): recall at these (metres, degrees).
THRESHOLDS = ((1.0, 1.0), (3.0, 3.0), (5.0, 5.0))
SIGMA_RULE = ("a photo can judge a threshold (m, deg) only where its pseudo-GT 2-sigma is within it: "
              "2 sigma_pos_m <= m and 2 sigma_rot_deg <= deg")


def _stats(v) -> dict:
    v = np.asarray([x for x in v if x is not None and np.isfinite(x)], dtype=np.float64)
    if not len(v):
        return {}
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max()),
            "min": float(v.min()), "mean": float(v.mean())}


def provenance(project: Project) -> dict:
    """How the pseudo-GT was made, from the stages' records."""
    from ..sfm import registration_record as record

    P = project.paths
    block = load_json(P.stage("sfm_reference") / "block.json")
    geo = block.get("georegistration") or {}
    reg = record.read_registration(P.registration) or {}
    seqs = record.sequences(reg)
    ref = {k: block.get(k) for k in ("n_registered", "n_images", "n_points3D", "mean_reproj_px") if k in block}
    ref["georegistration"] = {k: geo.get(k) for k in ("used", "rmse_inliers_m", "n_inliers", "gcp_median_err_m",
                                                      "gcp_rmse_m", "checkpoint_median_err_m", "checkpoint_rmse_m")
                              if geo.get(k) is not None}
    checks = {n: g for n, g in (geo.get("gcp_residuals") or {}).items() if isinstance(g, dict) and g.get("check_point")}
    if checks:
        ref["check_points"] = checks
    return {
        "reference_block": ref,
        "registration": {
            **{k: reg.get(k) for k in ("n_registered", "n_unverified", "median_reproj_px", "median_tiepoint_reproj_px",
                                       "median_auto_tiepoint_reproj_px", "n_tiepoints_in_ba", "n_auto_tiepoints_in_ba",
                                       "ba_final_cost") if reg.get(k) is not None},
            "sequences": {q: {"outcome": record.outcome(s), "how": record.describe(s)} for q, s in sorted(seqs.items())},
            "outcomes": {k: v for k, v in record.counts(seqs).items() if v}},
        "settings": {st: (rec.settings if (rec := read_stage_record(P.stage(st))) else None)
                     for st in ("sfm_reference", "sfm_queries", "register", "render_db")},
    }


def sheet(project: Project, gt: PublishedGT, parts: dict, settings: dict, version: str) -> dict:
    """``dataset.json``'s content (without the files and the export key, added by the stage)."""
    f = project.frame
    centres = np.array([p.center for p in gt.poses.values()])
    sp = [gt.sigma[n][0] for n in sorted(gt.poses)]
    sr = [gt.sigma[n][1] for n in sorted(gt.poses)]
    kinds: dict[str, int] = {}
    for k, _ in gt.kept_out.values():
        kinds[k] = kinds.get(k, 0) + 1
    judge = {f"{m:g}m{d:g}deg": int(sum(1 for n in gt.poses if 2 * gt.sigma[n][0] <= m and 2 * gt.sigma[n][1] <= d))
             for m, d in THRESHOLDS}
    return {
        "format": "gtkit-dataset", "format_version": 1,
        "site": {"name": project.name, "crs": f.crs_spec, "origin": list(f.origin),
                 "frame": "world = CRS coordinates minus origin (metres), z up; poses world-to-camera, OpenCV axes, "
                          "quaternions qw qx qy qz; COLMAP pixel convention (top-left pixel centre at 0.5, 0.5)",
                 "query_extent_world": [centres.min(0).tolist(), centres.max(0).tolist()]},
        "pseudo_gt": {"n_published": len(gt.poses), "n_kept_out": len(gt.kept_out), "kept_out_by_kind": kinds,
                      "sequences": sorted({gt.sequences.get(n, "") for n in gt.poses}),
                      "sigma_pos_m": _stats(sp), "sigma_rot_deg": _stats(sr),
                      "photos_that_can_judge": judge},
        "provenance": provenance(project),
        "protocol": {"thresholds_m_deg": [list(t) for t in THRESHOLDS],
                     "recall": "share of the published photos whose estimate is within both the position (camera "
                               "centre distance) and rotation (geodesic angle) threshold; a photo without an estimate fails",
                     "sigma_aware": SIGMA_RULE,
                     "command": "gtkit evaluate results DATASET RESULTS (hloc pose file, kapture folder or COLMAP model)"},
        "parts": parts,
        "export": {"gtkit_version": version, "settings": settings},
    }


def _fmt(v, nd=3, unit=""):
    return "–" if v is None else (f"{v:.{nd}f}{unit}" if isinstance(v, float) else f"{v}{unit}")


def markdown(d: dict, gt: PublishedGT) -> str:
    s, pg, pv, parts = d["site"], d["pseudo_gt"], d["provenance"], d["parts"]
    ref, reg = pv["reference_block"], pv["registration"]
    geo = ref.get("georegistration", {})
    sp, sr = pg["sigma_pos_m"], pg["sigma_rot_deg"]
    q = parts.get("kapture_query") or {}
    L = [f"# Dataset: {s['name']}", "",
         f"Pseudo-GT 6-DoF poses of {pg['n_published']} UAV query photos "
         f"({', '.join(x for x in pg['sequences'] if x) or 'one sequence'}), each with its covariance, made by "
         f"gtkit {d['export']['gtkit_version']}; {pg['n_kept_out']} query photos kept out (`kept_out.txt`).", "",
         "## Site and frame", "",
         f"- CRS `{s['crs']}`, origin `{s['origin']}`: {s['frame']}.",
         f"- Query camera centres span x {s['query_extent_world'][0][0]:.1f}..{s['query_extent_world'][1][0]:.1f}, "
         f"y {s['query_extent_world'][0][1]:.1f}..{s['query_extent_world'][1][1]:.1f}, "
         f"z {s['query_extent_world'][0][2]:.1f}..{s['query_extent_world'][1][2]:.1f} m (world).", "",
         "## Sensors", ""]
    for cam in sorted(set(gt.cameras.values()), key=lambda c: c.to_line()):
        L.append(f"- query camera `{cam.to_line()}` ({sum(1 for c in gt.cameras.values() if c == cam)} photos)")
    if q.get("n_zoom_photos"):
        L.append(f"- zoom camera{'s' if len(q['zoom_cameras']) > 1 else ''} {', '.join(f'`{z}`' for z in q['zoom_cameras'])} "
                 f"on the rig `uav` ({q['n_zoom_photos']} photos, "
                 "kapture/query/sensors/rigs.txt; no pseudo-GT of their own: the rig gives it)")
    L.append(f"- GNSS: {q.get('n_gnss_records', 0)} EXIF GPS records (EPSG:4326); attitude priors: "
             f"{(q.get('priors') or {}).get('n_photos', 0)} photos (kapture/query_priors)")
    m = parts.get("kapture_mapping") or {}
    if m:
        L.append(f"- mapping: {m.get('n_reference_photos', 0)} reference photos, {m.get('n_rendered_views', 0)} "
                 f"rendered database views, {m.get('n_depth_maps', 0)} depth maps"
                 + (f" (`{m['render_camera']}`)" if m.get("render_camera") else ""))
    gcp = (f"; GCP residual median {_fmt(geo['gcp_median_err_m'], 3, ' m')}, RMSE {_fmt(geo.get('gcp_rmse_m'), 3, ' m')}"
           if geo.get("gcp_median_err_m") is not None else "; no GCPs")
    reproj = [f"{_fmt(reg[k], 2, ' px')} ({what})" for k, what in (("median_reproj_px", "SfM points"),
                                                                  ("median_tiepoint_reproj_px", "clicked tie points"))
              if reg.get(k) is not None]
    L += ["", "## How the pseudo-GT was made", "",
          f"- Reference block: {ref.get('n_registered', '–')} / {ref.get('n_images', '–')} photos, "
          f"mean reprojection {_fmt(ref.get('mean_reproj_px'), 2, ' px')}; georegistration by "
          f"{geo.get('used', '–')}: RMSE {_fmt(geo.get('rmse_inliers_m'), 3, ' m')} over {geo.get('n_inliers', '–')} "
          f"inliers{gcp}.",
          f"- Joint bundle adjustment: {reg.get('n_tiepoints_in_ba', 0)} clicked and {reg.get('n_auto_tiepoints_in_ba', 0)} "
          f"automatic tie points" + (f"; median reprojection {', '.join(reproj)}" if reproj else "") + ".",
          "- Sequences:"]
    L += [f"  - {name}: {v['how']}" for name, v in pv["registration"]["sequences"].items()]
    if ref.get("check_points"):
        L.append(f"- GCP check points (not used in the fit): {len(ref['check_points'])}, "
                 f"median error {_fmt(geo.get('checkpoint_median_err_m'), 3, ' m')}.")
    judge = pg["photos_that_can_judge"]
    L += ["", "## Accuracy (the pseudo-GT's own covariance)", "",
          "| | median | 90th percentile | max |", "|---|---|---|---|",
          f"| position sigma (1-sigma radius) | {_fmt(sp.get('median'))} m | {_fmt(sp.get('p90'))} m | {_fmt(sp.get('max'))} m |",
          f"| rotation sigma | {_fmt(sr.get('median'))}° | {_fmt(sr.get('p90'))}° | {_fmt(sr.get('max'))}° |", "",
          "![trajectories](plots/trajectories.jpg)  ![sigma per photo](plots/sigma.png)", "",
          "## Evaluation protocol", "",
          "Recall at (1 m, 1°), (3 m, 3°), (5 m, 5°) over the published photos (a photo a method does not "
          "localize fails), and the median position and rotation errors. Sigma-aware: "
          f"{SIGMA_RULE}. Photos that can judge each threshold here: "
          + ", ".join(f"({m:g} m, {dg:g}°) {judge[f'{m:g}m{dg:g}deg']} of {pg['n_published']}" for m, dg in THRESHOLDS)
          + ".", "", "```", "gtkit evaluate results DATASET RESULTS   # hloc pose file, kapture folder or COLMAP model",
          "```", "", "## Files", "", "| path | what |", "|---|---|"]
    L += [f"| `{p}` | {w} |" for p, w in FILES if _present(p, parts)]
    kept = sorted(gt.kept_out.items())
    if kept:
        L += ["", "## Kept out", "", "| photo | kind | reason |", "|---|---|---|"]
        L += [f"| {n} | {k} | {why} |" for n, (k, why) in kept[:50]]
        if len(kept) > 50:
            L.append(f"| ... {len(kept) - 50} more in kept_out.txt | | |")
    L += ["", "## Made by", "", f"gtkit {d['export']['gtkit_version']}, `gtkit export dataset` with "
          f"`{json.dumps(d['export']['settings'])}`; the stages' settings are in dataset.json (provenance.settings).", ""]
    return "\n".join(L)


FILES = (
    ("kapture/query/", "kapture: query sensors, rig, pseudo-GT trajectories, records_camera, records_gnss; photos in sensors/records_data/"),
    ("kapture/query_priors/", "kapture: the same photos' GPS + gimbal priors as trajectories"),
    ("kapture/mapping/", "kapture: reference photos and rendered database views (records_depth: depth maps)"),
    ("colmap/queries/", "COLMAP text model of the published query photos (no 3D points)"),
    ("hloc/pseudo_gt_poses.txt", "hloc pose file: name qw qx qy qz tx ty tz (world-to-camera)"),
    ("hloc/queries_with_intrinsics.txt", "hloc query list: name MODEL W H params"),
    ("pseudo_gt_uncertainty.txt", "sigma and the full 6x6 covariance of every published pose (header documents it)"),
    ("kept_out.txt", "query photos kept out (unverified, refused, not registered) and why"),
    ("model/", "the reference model (OBJ + offset sidecar) and the DSM (--with-model)"),
    ("plots/", "trajectories over the orthophoto, sigma per photo"),
)


def _present(p: str, parts: dict) -> bool:
    key = {"kapture/query/": "kapture_query", "kapture/mapping/": "kapture_mapping", "colmap/queries/": "colmap",
           "hloc/pseudo_gt_poses.txt": "hloc", "hloc/queries_with_intrinsics.txt": "hloc", "model/": "model"}.get(p)
    if p == "kapture/query_priors/":
        return bool(((parts.get("kapture_query") or {}).get("priors") or {}).get("folder"))
    return key is None or bool(parts.get(key))


def plots(out: Path, project: Project, gt: PublishedGT) -> list[Path]:
    """``plots/trajectories.jpg`` (over ``exports/ortho.tif`` where there is one) and ``plots/sigma.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = out / PLOTS
    d.mkdir(parents=True, exist_ok=True)
    names = sorted(gt.poses)
    seqs = sorted({gt.sequences.get(n, "") for n in names})
    colours = {q: plt.cm.tab10(i % 10) for i, q in enumerate(seqs)}
    fig, ax = plt.subplots(figsize=(7, 7))
    C = {n: gt.poses[n].center for n in names}
    o = np.asarray(project.frame.origin, dtype=np.float64)
    if project.paths.ortho.is_file():
        import rasterio

        with rasterio.open(project.paths.ortho) as src:
            img = np.moveaxis(src.read(out_shape=(src.count, min(src.height, 1500), min(src.width, 1500))), 0, -1)
            b = src.bounds
        ax.imshow(img[..., :3], extent=(b.left - o[0], b.right - o[0], b.bottom - o[1], b.top - o[1]))
    for q in seqs:
        pts = np.array([C[n] for n in names if gt.sequences.get(n, "") == q])
        ax.plot(pts[:, 0], pts[:, 1], "o-", ms=3, lw=1, color=colours[q], label=q or "queries")
    ax.set_xlabel("x (m, world = CRS - origin)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    ax.set_title("pseudo-GT query trajectories" + (" over the orthophoto" if project.paths.ortho.is_file() else ""))
    fig.tight_layout()
    paths = [d / "trajectories.jpg"]
    with atomic_path(paths[0]) as tmp:
        fig.savefig(tmp, dpi=110, pil_kwargs={"quality": 85})
    plt.close(fig)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(max(7, 0.12 * len(names)), 5.5), sharex=True)
    x = np.arange(len(names))
    col = [colours[gt.sequences.get(n, "")] for n in names]
    a1.bar(x, [gt.sigma[n][0] for n in names], color=col)
    a1.set_ylabel("position sigma (m)")
    a2.bar(x, [gt.sigma[n][1] for n in names], color=col)
    a2.set_ylabel("rotation sigma (deg)")
    a2.set_xticks(x, [Path(n).stem for n in names], rotation=90, fontsize=6)
    a1.set_title("pseudo-GT 1-sigma per published photo (colour: sequence)")
    fig.tight_layout()
    paths.append(d / "sigma.png")
    with atomic_path(paths[1]) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return paths


def write(out: Path, d: dict, gt: PublishedGT) -> tuple[Path, Path]:
    from .folder import SHEET_JSON

    return write_text(out / SHEET_MD, markdown(d, gt)), write_json(out / SHEET_JSON, d)
