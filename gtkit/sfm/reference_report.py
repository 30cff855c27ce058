"""``reports/reference.json`` and ``reports/reference.md``: what the reference SfM made of the
photos, written by ``gtkit sfm DIR --block reference`` (from the block's summary only; no truth)."""
from __future__ import annotations

import numpy as np

from ..io.atomic import write_json, write_text
from ..project import Paths

GEO_KEYS = ("used", "fitted_to", "fit", "gps_quality", "plausibility", "n_inliers", "n_gps", "n_gcp_in_fit", "n_checkpoints", "gcp_threshold_m",
            "gcp_median_err_m", "gcp_rmse_m", "checkpoint_median_err_m", "checkpoint_rmse_m", "outliers", "error",
            "gcp_click_scale", "gcp_click_threshold", "claimed_accuracy")


def reference_report(summary: dict) -> dict:
    geo = summary.get("georegistration", {})
    return {"n_images": summary["n_images"], "n_registered": summary.get("n_registered", 0),
            "n_models": summary.get("n_models", 0), "mean_reproj_px": summary.get("mean_reproj_px"),
            "n_points3D": summary.get("n_points3D"), "pairings": summary.get("pairings"),
            "n_pairs": summary.get("n_pairs"), "intrinsics_policy": summary.get("intrinsics_policy"),
            "mapper": summary.get("mapper"), "mapper_why": summary.get("mapper_why"), "seeded": summary.get("seeded"),
            "intrinsics": summary.get("intrinsics"),
            "georegistration": {**{k: geo.get(k) for k in GEO_KEYS if k in geo},
                                **({"rmse_m": geo["rmse_inliers_m"]} if "rmse_inliers_m" in geo else {})},
            "gcp_residuals": geo.get("gcp_residuals", {}),
            "gcp_rmse_xyz_m": gcp_rmse(geo.get("gcp_residuals", {}), False),
            "checkpoint_rmse_xyz_m": gcp_rmse(geo.get("gcp_residuals", {}), True),
            "held_by_positions": summary.get("held_by_positions"),
            "gcp_clicks_outside_block": summary.get("gcp_clicks_outside_block", {}),
            "models": [{k: v for k, v in m.items() if k != "photos"} for m in summary.get("models", [])],
            "unregistered": summary.get("unregistered", {}), "seconds": summary.get("seconds", {}),
            "poses": "work/sfm_reference/poses.txt", "frame": summary.get("frame")}


def by_reason(unregistered: dict[str, str]) -> list[tuple[str, list[str]]]:
    """Photos left out, grouped by their reason (each reason stated once), most photos first."""
    groups: dict[str, list[str]] = {}
    for n, why in unregistered.items():
        groups.setdefault(why, []).append(n)
    return sorted(((w, sorted(ns)) for w, ns in groups.items()), key=lambda g: (-len(g[1]), g[0]))


def _f(v, nd=3):
    return "–" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def _fit_lines(fit: dict, q: dict | None, plaus: dict | None, claim: dict | None = None) -> list[str]:
    """The georegistration's method, the GPS quality and what the block can claim, in words
    (``claim``: the georegistration's ``claimed_accuracy`` record; a block made before it had one:
    the GPS quality's figures as they were)."""
    out = []
    if fit.get("mode") == "gravity-held":
        out.append(f"- tilt held by gravity ({fit.get('tilt_from')}, spread {_f(fit['up']['spread_deg'], 2)} deg over "
                   f"{fit['up']['n_photos']} photos); heading, scale and position from the GPS: {fit.get('why')}")
    elif fit.get("mode") == "combined":
        out.append(f"- tilt from the positions and gravity together ({fit.get('tilt_from')}): {fit.get('why')}")
    elif fit.get("mode") == "free":
        out.append(f"- free Sim(3): {fit.get('why')}")
    if q:
        drift = q.get("altitude_drift_m")
        out.append(f"- GPS quality: {q.get('n_inliers')} of {q.get('n_positions')} positions kept "
                   f"({_f(100 * (q.get('share_kept') or 0), 0)} %); residual median "
                   f"{_f(q.get('horizontal_residual_median_m'), 2)} m horizontal, {_f(q.get('vertical_residual_median_m'), 2)} m "
                   "vertical" + (f"; the altitudes drift {drift:+.1f} m over the flight (taken out)" if drift else ""))
    if claim:
        out.append(f"- absolute accuracy the site can claim: {claim['line'].removeprefix('absolute accuracy ')}"
                   + (f"; heading to ~{_f(q.get('heading_precision_deg'), 2)} deg" if q and q.get("heading_precision_deg")
                      else ""))
    elif q:
        out.append(f"- absolute accuracy the site can claim (1 sigma, from the GPS): ~{_f(q.get('absolute_accuracy_h_m'), 1)} m "
                   f"horizontal, ~{_f(q.get('absolute_accuracy_v_m'), 1)} m vertical"
                   + (f"; heading to ~{_f(q.get('heading_precision_deg'), 2)} deg" if q.get("heading_precision_deg") else "")
                   + (" (the positions agree among themselves to "
                      f"{_f(q.get('scatter_h_m'), 2)} / {_f(q.get('scatter_v_m'), 2)} m; a common GPS bias cannot be "
                      "measured from the photos and is assumed: give GCPs, or geo.txt with accuracy columns, to claim more)"
                      if q.get("bias_assumed") else ""))
    if plaus and plaus.get("aerial_checks"):
        out.append(f"- aerial checks (cameras above the ground, photos looking down): {plaus['aerial_checks']}")
    if plaus:
        out.append(f"- plausibility: cameras above what they see in {_f(100 * (plaus.get('share_above_their_points') or 0), 0)} % "
                   f"of the photos, {_f(plaus.get('median_height_above_points_m'), 1)} m above it; median viewing direction "
                   f"z {_f(plaus.get('median_view_z'), 2)}"
                   + (f"; rotations {_f(plaus['median_attitude_disagreement_deg'], 1)} deg from the gimbal attitude"
                      if plaus.get("median_attitude_disagreement_deg") is not None else ""))
    return out


def _seeded_line(seeded: dict | None) -> str:
    """What the seeded mapper did with the photos' priors, after the mapper line ('' when it did not run)."""
    if not seeded or "fallback" in seeded:
        return ""
    n_off = len(seeded.get("misfits", {})) + len(seeded.get("not_registered", {}))
    return (f"; {seeded['n_seeded'] - n_off} photos at their prior pose, refined"
            + (f", {len(seeded['misfits'])} placed by their matches away from a prior that does not fit ("
               + ", ".join(f"`{n}`" for n in sorted(seeded["misfits"])[:5]) + (", ..." if len(seeded["misfits"]) > 5 else "")
               + ")" if seeded.get("misfits") else "")
            + (f", {len(seeded['placed_by_matches'])} without a prior placed by their matches"
               if seeded.get("placed_by_matches") else "")
            + f"; positions scatter {_f(seeded.get('position_scatter_m'))} m about the block")


def _rms(v) -> float | None:
    v = [float(x) for x in v if x is not None and np.isfinite(x)]
    return float(np.sqrt(np.mean(np.square(v)))) if v else None


def gcp_rmse(residuals: dict, check: bool) -> dict | None:
    """RMSE of the X / Y / Z errors (and 3D) of the GCPs (``check`` False) or check points."""
    rows = [r for r in residuals.values() if r.get("status") == "ok" and bool(r.get("check")) == check
            and not r.get("outlier")]
    if not rows:
        return None
    return {"n": len(rows), **{k: _rms([r[f"d{k}_m"] for r in rows]) for k in ("x", "y", "z")},
            "3d": _rms([r["err_m"] for r in rows])}


def gcp_table(residuals: dict) -> list[str]:
    """Each GCP and check point (X / Y / Z error, image residual, photos) and the RMSE of both kinds,
    as a survey report lists them."""
    out = ["", "| point | kind | dX (m) | dY (m) | dZ (m) | 3D (m) | image residual (px, RMS) | photos (used / clicked) |",
           "|---|---|---|---|---|---|---|---|"]
    for n, r in residuals.items():
        kind = "check point" if r.get("check") else ("GCP, outlier" if r.get("outlier") else "GCP")
        if r["status"] == "ok":
            # the clicks used are those the triangulation kept: the smallest residuals
            res = _rms(sorted(x for x in r.get("click_residuals_px", []) if np.isfinite(x))[:r["clicks_used"]])
            out.append(f"| {n} | {kind} | {r['dx_m']:+.3f} | {r['dy_m']:+.3f} | {r['dz_m']:+.3f} | {r['err_m']:.3f} | "
                       f"{_f(res, 2)} | {r['clicks_used']} / {r['clicks_total']} |")
        else:
            out.append(f"| {n} | {kind} | – | – | – | – | – | {r.get('reason', '')} |")
    out.append("")
    for label, check in (("GCPs", False), ("check points", True)):
        m = gcp_rmse(residuals, check)
        if m:
            out.append(f"- RMSE of {m['n']} {label}: X {m['x']:.3f} m, Y {m['y']:.3f} m, Z {m['z']:.3f} m, "
                       f"3D {m['3d']:.3f} m" + (" (never in the fit)" if check else ""))
    return out


def _ba_run(h: dict) -> str:
    """How the pose-prior BA ran (gtkit.sfm.prior_ba): its steps, and the points left out of it."""
    from .prior_ba import MIN_TRI_ANGLE_DEG

    it, drop = h.get("iterations") or {}, h.get("points_dropped") or {}
    out = ""
    if it:
        out += f"; {it['steps']} steps ({it['failed']} failed)" + ("" if h.get("converged") else ", not converged")
    if sum(drop.values()):
        out += (f"; {sum(drop.values())} points it cannot place left out ({drop.get('near_a_photo', 0)} near a photo, "
                f"{drop.get('small_angle', 0)} seen under < {MIN_TRI_ANGLE_DEG:g} deg)")
    return out


def write_reference_report(paths: Paths, summary: dict) -> dict:
    rep = reference_report(summary)
    write_json(paths.reports / "reference.json", rep)
    g = rep["georegistration"]
    lines = ["# Reference block", "",
             f"- photos registered: **{rep['n_registered']} / {rep['n_images']}** in {rep['n_models']} model(s); "
             f"{_f(rep['n_points3D'])} 3D points; mean reprojection {_f(rep['mean_reproj_px'], 2)} px",
             f"- pairs: {_f(rep['n_pairs'])} ({' + '.join(rep['pairings'] or [])})",
             f"- mapper: {rep['mapper'] or '–'} ({rep['mapper_why'] or 'no reason recorded'})"
             + _seeded_line(rep["seeded"]),
             f"- frame: {rep['frame']}; poses in `{rep['poses']}`", "",
             "## Georegistration", ""]
    if "error" in g:
        lines.append(f"**failed**: {g['error']}")
    else:
        lines += [f"- fitted to: {g.get('fitted_to') or g.get('used')} ({g.get('n_gps')} GPS positions and "
                  f"{g.get('n_gcp_in_fit')} GCPs given, {g.get('n_checkpoints')} check points); RMSE {_f(g.get('rmse_m'))} m"]
        lines += _fit_lines(g.get("fit") or {}, g.get("gps_quality"), g.get("plausibility"), g.get("claimed_accuracy"))
        if (g.get("gcp_click_scale") or {}).get("line"):
            lines.append(f"- GCP clicks: {g['gcp_click_scale']['line']}")
        if g.get("n_gcp_in_fit") or g.get("n_checkpoints"):
            lines.append(f"- GCP residual median {_f(g.get('gcp_median_err_m'))} m, RMSE {_f(g.get('gcp_rmse_m'))} m; "
                         f"check points median {_f(g.get('checkpoint_median_err_m'))} m")
    h = rep["held_by_positions"]
    if h and h.get("applied"):
        lines.append(f"- held by its positions in a pose-prior BA: {h['n_priors']} photos, sigma {_f(h['sigma_h_m'])} m "
                     f"horizontal / {_f(h['sigma_v_m'])} m vertical ({h['n_stated_accuracy']} with a stated accuracy); "
                     f"residual median {_f(h['residual_median_m']['before'])} -> {_f(h['residual_median_m']['after'])} m"
                     + _ba_run(h))
    elif h:
        lines.append(f"- not held by its positions: {h.get('reason')}")
    if rep["gcp_residuals"]:
        lines += gcp_table(rep["gcp_residuals"])
    for n, photos in rep["gcp_clicks_outside_block"].items():
        lines.append(f"- GCP {n} is clicked in photos that are not reference photos: {', '.join(photos)}")
    lines += ["", "## Cameras", "", "| camera | model | size | params | |", "|---|---|---|---|---|"]
    for cid, c in (rep["intrinsics"] or {}).items():
        lines.append(f"| {cid} | {c['model']} | {c['width']}x{c['height']} | {', '.join(f'{v:.5g}' for v in c['params'])} | "
                     f"{'fixed' if c['fixed'] else 'refined: ' + ', '.join(c.get('refined', []))} |")
    if rep["n_models"] > 1:
        lines += ["", "## Models", ""] + [f"- model {m['model']}: {m['n_registered']} photos, {m['n_points3D']} points, "
                                          + ("kept" if m.get("kept") else m.get("reason", "")) for m in rep["models"]]
    if rep["unregistered"]:
        lines += ["", "## Photos not in the block", ""] + [
            f"- {why}: " + ", ".join(f"`{n}`" for n in names) for why, names in by_reason(rep["unregistered"])]
    lines += ["", "Seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in rep["seconds"].items())]
    write_text(paths.reports / "reference.md", "\n".join(lines) + "\n")
    return rep
