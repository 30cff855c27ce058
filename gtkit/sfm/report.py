"""The pseudo-GT quality report from what the estimating stages wrote (blocks, registration,
annotators' review): ``reports/gt_report.json`` plus a readable ``reports/gt_report.md`` with SVG
plots. Checks against anything the estimator never sees (the sample's ``truth/``, an independent
point cloud) are added by :mod:`gtkit.evaluate.gt_report`, which ``gtkit report`` runs; this module
never reads them."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_json, write_text
from ..io.poses import read_poses
from ..project import Project
from .blocks import QUERIES_STAGE, REFERENCE_STAGE
from .register import STAGE as REGISTER_STAGE
from . import registration_record as record


def _recalibrated(co: dict) -> str:
    """'; the self-calibrated reference camera calibrated again ...' of a co-estimation record ('' where not)."""
    words = []
    for c in (co.get("calibrated") or {}).values():
        b, a = c["before"], c["after"]
        pp = float(np.hypot(a[1] - b[1], a[2] - b[2])) if len(a) > 2 and "principal point" in c["parts"] else None
        words.append(f"focal {b[0]:.0f} -> {a[0]:.0f} px" + (f", principal point moved {pp:.0f} px" if pp is not None else ""))
    n = len(co.get("joined_reference_camera") or [])
    nj = co.get("not_joined_reference_camera")
    return ((f"; the self-calibrated reference camera calibrated again with {n} query photos of it ("
             + "; ".join(words) + ")") if words else "") + (
        f"; the query photos kept their own camera, not the reference's: {nj['why']}" if nj else "")


def _load(p: Path):
    """A stage's record, None where the stage has not run; a record that cannot be read is a one-line
    error naming it (the report never reads a damaged record as "not run")."""
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise GtkitError(f"unreadable record ({e}); re-run its stage with --force", p) from None


def _svg_bars(title: str, labels: list[str], values: list[float], unit: str, limit: float | None = None) -> str:
    w, h, left, bottom = 720, 260, 60, 70
    n = max(len(values), 1)
    vmax = max([v for v in values if np.isfinite(v)] + [limit or 0, 1e-9]) * 1.1
    bw = (w - left - 10) / n
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="10">',
           f'<text x="{w / 2}" y="14" text-anchor="middle" font-size="13">{title}</text>',
           f'<line x1="{left}" y1="{h - bottom}" x2="{w - 10}" y2="{h - bottom}" stroke="black"/>']
    for frac in (0, 0.5, 1.0):
        y = h - bottom - frac * (h - bottom - 25)
        out.append(f'<text x="{left - 4}" y="{y + 3}" text-anchor="end">{frac * vmax:.3g} {unit}</text>')
    for k, (lab, v) in enumerate(zip(labels, values)):
        x = left + k * bw
        vv = v if np.isfinite(v) else vmax
        bh = vv / vmax * (h - bottom - 25)
        col = "#c0392b" if not np.isfinite(v) or (limit and v > limit) else "#2e86c1"
        out.append(f'<rect x="{x + 1:.1f}" y="{h - bottom - bh:.1f}" width="{max(bw - 2, 1):.1f}" height="{bh:.1f}" fill="{col}"/>')
        out.append(f'<text transform="translate({x + bw / 2:.1f},{h - bottom + 6}) rotate(60)" font-size="8">{lab}</text>')
    if limit:
        y = h - bottom - limit / vmax * (h - bottom - 25)
        out.append(f'<line x1="{left}" y1="{y:.1f}" x2="{w - 10}" y2="{y:.1f}" stroke="#c0392b" stroke-dasharray="4"/>')
    out.append("</svg>")
    return "\n".join(out)


def _fmt(v, nd=3):
    return "–" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def collect(project: Project) -> dict:
    """The report's figures from the stages' own outputs (no truth): blocks, registration, review."""
    P = project.paths
    ref = _load(P.stage(REFERENCE_STAGE) / "block.json")
    qsum = _load(P.stage(QUERIES_STAGE) / "summary.json") or {}
    reg = record.read_registration(P.registration)
    from ..review import read_review  # review.json as the annotator writes it (gtkit.review)

    review = {n: r["status"] for n, r in read_review(P.review).items()}  # image -> accept|reject|needs-work
    rep: dict = {"project": project.name, "reference_block": ref, "query_blocks": qsum}
    est = {}
    if reg:
        est = read_poses(P.poses(REGISTER_STAGE)) if P.poses(REGISTER_STAGE).is_file() else {}
        rep.update({k: reg.get(k) for k in ("median_reproj_px", "mean_reproj_px", "median_tiepoint_reproj_px",
                                             "n_registered", "n_unverified", "n_images", "sequences", "bad_tiepoints",
                                             "n_tiepoints_in_ba", "n_auto_tiepoints_in_ba", "tie_surface",
                                             "coestimation")})
        rep["per_image"] = {n: dict(v) for n, v in reg.get("images", {}).items()}
        rep["sequences_needing_clicks"] = {q: s.get("error") for q, s in record.sequences(reg).items()
                                           if record.outcome(s) == record.NEEDS_CLICKS}
    else:
        rep.update({"median_reproj_px": None, "median_tiepoint_reproj_px": None, "n_registered": 0, "n_images": 0,
                    "per_image": {}})
    # every query photo of the blocks, registered or not
    names = sorted(set(rep["per_image"]) | {n for b in qsum.values() for n in (b.get("unregistered") or {})})
    for n in names:
        rep["per_image"].setdefault(n, {"registered": False})
        rep["per_image"][n]["registered"] = n in est and "unverified" not in rep["per_image"][n]
        if n in review:
            rep["per_image"][n]["review"] = review[n]
    if review:
        vals = list(review.values())
        rep["review"] = {k: vals.count(k) for k in ("accept", "reject", "needs-work")}
    return rep


def write(project: Project, rep: dict, checks=None) -> dict:
    """Write ``reports/gt_report.json`` and ``gt_report.md``. ``checks`` (from evaluation) adds to the
    Markdown: ``rows`` of the figure table, lines ``after_table``, per-image bar ``plots``
    ``(title, key, file, limit)`` and per-image ``columns`` ``(key, header)``."""
    P = project.paths
    P.reports.mkdir(parents=True, exist_ok=True)
    write_json(P.reports / "gt_report.json", rep, indent=1)
    write_text(P.reports / "gt_report.md", _markdown(rep, P.reports, checks or {}))
    return rep


def run(project: Project | str | Path) -> dict:
    """The report from the stages' outputs alone (``gtkit report`` adds evaluation's checks:
    :func:`gtkit.evaluate.gt_report.run`)."""
    project = project if isinstance(project, Project) else Project.load(project)
    return write(project, collect(project))


def scene_links(folder: Path) -> list[str]:
    """The 3D scene snapshots ``gtkit view`` wrote into ``folder`` (reports/), as markdown images."""
    shots = [p.name for p in sorted(Path(folder).glob("scene_*.png"))]
    return ["", "## 3D scene (`gtkit view`)", ""] + [f"![{n}]({n})" for n in shots] if shots else []


def _markdown(rep: dict, folder: Path, checks: dict) -> str:
    L = [f"# Pseudo-GT report: {rep['project']}", ""]
    L += ["| figure | value |", "|---|---|",
          f"| query photos registered (a pose with its sigma) | {rep['n_registered']} / {rep['n_images']} |"]
    if rep.get("n_unverified"):
        L.append(f"| query photos UNVERIFIED (a pose without a usable sigma: not a result) | {rep['n_unverified']} |")
    L += [
          f"| median reprojection error (SfM points, joint BA) | {_fmt(rep.get('median_reproj_px'), 2)} px |",
          f"| median tie-point reprojection error | {_fmt(rep.get('median_tiepoint_reproj_px'), 2)} px |",
          f"| clicked / automatic tie points in the joint BA | {rep.get('n_tiepoints_in_ba', 0)} / "
          f"{rep.get('n_auto_tiepoints_in_ba', 0)} |"]
    ts = rep.get("tie_surface")
    if ts:   # how the automatic ties were judged: by the model in 3D, or not (no model)
        L.append(f"| automatic ties on the model: smooth / off smooth surface / undecided (kept) | {ts['n_smooth']} / "
                 f"{ts['n_rough']} / {ts['n_undecided']} |" if ts.get("model") else f"| automatic ties | {ts['why']} |")
    co = rep.get("coestimation")
    if co:   # the query photos adjusted together with a small reference block (gtkit.sfm.register.coestimate)
        L.append("| query photos co-estimated with the reference block | "
                 + (f"{co['n_photos']} photos, moved {1000 * co['query_moved_median_m']:.1f} mm (median) from the joint "
                    f"adjustment, the move added to their sigma{_recalibrated(co)} |" if co.get("applied")
                    else f"no: {co.get('reason')} |"))
    seqs = rep.get("sequences") or {}
    if seqs:
        n = record.counts(seqs)
        L.append(f"| sequences by clicked tie points / by automatic matches (no clicks) / as single photos / "
                 f"need clicks / not registered otherwise | {n[record.CLICKED]} / {n[record.AUTOMATIC]} / "
                 f"{n[record.SINGLE_PHOTOS]} / {n[record.NEEDS_CLICKS]} / {n[record.ERROR]} of {len(seqs)} |")
    L += list(checks.get("rows", []))
    ref = rep.get("reference_block")
    if ref:
        geo = ref.get("georegistration", {})
        L += [f"| reference block | {ref['n_registered']} / {ref['n_images']} photos, {ref.get('n_points3D')} points, "
              f"mean reprojection {_fmt(ref.get('mean_reproj_px'), 2)} px |",
              f"| georegistration ({geo.get('used')}) | RMSE {_fmt(geo.get('rmse_inliers_m'))} m over "
              f"{geo.get('n_inliers')} inliers |",
              f"| GCP residual median / RMSE | {_fmt(geo.get('gcp_median_err_m'))} m / {_fmt(geo.get('gcp_rmse_m'))} m |"]
        claim = geo.get("claimed_accuracy")   # gtkit.sfm.georegister.accuracy_claim's record
        if claim:
            L.append(f"| site's absolute accuracy (reference block, 1 sigma) | {claim['line'].removeprefix('absolute accuracy ')} |")
    L += list(checks.get("after_table", []))
    if ref and ref.get("georegistration", {}).get("gcp_residuals"):
        L += ["", "## GCP residuals", "", "| GCP | dx m | dy m | dz m | error m | clicks used |", "|---|---|---|---|---|---|"]
        for n, g in ref["georegistration"]["gcp_residuals"].items():
            L.append(f"| {n} | {_fmt(g.get('dx_m'))} | {_fmt(g.get('dy_m'))} | {_fmt(g.get('dz_m'))} | "
                     f"{_fmt(g.get('err_m'))} | {g.get('clicks_used', '–')}/{g.get('clicks_total', '–')} |"
                     if g["status"] == "ok" else f"| {n} | {g['reason']} | | | | |")
    need = rep.get("sequences_needing_clicks") or {}
    if need:
        L += ["", "## Sequences that need clicks", "",
              "Their photos' metadata and automatic matches could not place them; click tie points there "
              "(`gtkit annotate DIR`) and run `gtkit register DIR` again.", ""]
        L += [f"- **{seq}**: {why}" for seq, why in need.items()]
    unver = {n: e["unverified"] for n, e in (rep.get("per_image") or {}).items() if e.get("unverified")}
    if unver:
        L += ["", "## Unverified photos", "", "A pose without a sigma, or with one larger than the photo's distance to "
              "what it sees, is not a result: these photos are left out of the exports' ground truth.", ""]
        L += [f"- {n}: {why}" for n, why in sorted(unver.items())]
    L += ["", "## Sequences", ""]
    for seq, s in (rep.get("sequences") or {}).items():
        L.append(f"- **{seq}**: " + record.describe(s))
    for seq, b in (rep.get("query_blocks") or {}).items():
        for n, why in (b.get("unregistered") or {}).items():
            L.append(f"  - not in the {seq} block: {n}: {why}")
    bad = rep.get("bad_tiepoints") or {}
    if bad:
        L += ["", "## Bad tie points (excluded or corrected)", ""]
        for tid, b in bad.items():
            L.append(f"- {tid}: {b['reason']}" + "".join(f"; {c['image']} off by {c['residual_px']:.0f} px"
                                                          for c in b.get("dropped_clicks", [])))
    per = rep.get("per_image", {})
    if per:
        names = sorted(per)
        short = [n.split("/")[-2] + "/" + n.split("/")[-1].split(".")[0] for n in names]
        for title, key, file, limit in checks.get("plots", []):  # per-image bars from evaluation
            v = [per[n].get(key, np.inf) for n in names]
            write_text(folder / file, _svg_bars(title, short, v, "m", limit))
            L += ["", f"![{title}]({file})"]
        sv = [per[n].get("sigma_pos_m", np.nan) for n in names]
        if np.any(np.isfinite(sv)):
            write_text(folder / "gt_sigma.svg", _svg_bars("position standard deviation per query photo (BA, reference block, swing)", short,
                                                          [x if np.isfinite(x) else 0.0 for x in sv], "m"))
            L += ["", "![position sigma](gt_sigma.svg)"]
        cols = list(checks.get("columns", []))  # (key, header) added by evaluation
        L += ["", "## Per image", "", "| image | registered | σ pos m | σ rot ° | " + "".join(f"{h} | " for _k, h in cols)
              + "review |", "|---|---|---|---|" + "---|" * len(cols) + "---|"]
        for n in names:
            e = per[n]
            said = 'yes' if e.get('registered') else ('unverified' if e.get('unverified') else 'NO')
            L.append(f"| {n} | {said} | {_fmt(e.get('sigma_pos_m'))} | "
                     f"{_fmt(e.get('sigma_rot_deg'))} | " + "".join(f"{_fmt(e.get(k))} | " for k, _h in cols)
                     + f"{e.get('review', '')} |")
    L += scene_links(folder)
    return "\n".join(L) + "\n"
