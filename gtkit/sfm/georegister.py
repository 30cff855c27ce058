"""Georegister a block: robust Sim(3) from SfM camera centres to GPS centres (and/or from
triangulated GCPs to their surveyed coordinates), then GCP residuals in metres."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from ..io.odm import GCP
from .geometry import (RegistrationError, Sim3Fit, model_cameras, model_poses, robust_sim3, sim3_apply,
                       triangulate_clicks)

log = logging.getLogger(__name__)


@dataclass
class GeoregisterSettings:
    use: str = "gps+gcp"        # gps | gcp | gps+gcp: what the Sim(3) is fitted to
    gps_inlier_m: float = 2.0   # RANSAC threshold on camera centres (RTK: small; consumer GPS: 3-5 m)
    gcp_max_px: float = 4.0     # clicks of a GCP farther than this from the triangulated point are dropped


def triangulate_gcps(rec: pycolmap.Reconstruction, gcps: list[GCP], max_px: float) -> dict[str, dict]:
    """Each GCP triangulated in ``rec``'s current frame from its clicks in registered images."""
    poses, cams = model_poses(rec), model_cameras(rec)
    out = {}
    for g in gcps:
        clicks = [c for c in g.clicks if c.image in poses]
        tri = triangulate_clicks([cams[c.image] for c in clicks], [poses[c.image] for c in clicks],
                                 np.array([[c.x, c.y] for c in clicks]).reshape(-1, 2), max_px=max_px)
        out[g.name] = {"xyz": tri.xyz, "clicks_used": int(tri.used.sum()), "clicks_total": len(g.clicks),
                       "clicks_in_model": len(clicks), "reason": tri.reason,
                       "click_residuals_px": [float(r) for r in tri.residuals_px]}
    return out


def georegister(rec: pycolmap.Reconstruction, gps: dict[str, np.ndarray], gcps: list[GCP],
                settings: GeoregisterSettings) -> dict:
    """Transform ``rec`` in place into the project's local world frame; returns a report dict."""
    poses = model_poses(rec)
    src, tgt, kinds, names = [], [], [], []
    if "gps" in settings.use:
        for n, p in poses.items():
            if n in gps and np.all(np.isfinite(gps[n])):
                src.append(p.center), tgt.append(gps[n]), kinds.append("gps"), names.append(n)
    gcp_sfm = triangulate_gcps(rec, gcps, settings.gcp_max_px) if gcps else {}
    if "gcp" in settings.use:
        for g in gcps:
            if gcp_sfm[g.name]["xyz"] is not None:
                src.append(gcp_sfm[g.name]["xyz"]), tgt.append(g.xyz), kinds.append("gcp"), names.append(g.name)
    if not src:
        raise RegistrationError(f"no GPS positions or triangulated GCPs to georegister with (use={settings.use})")
    src, tgt = np.array(src), np.array(tgt)
    fit: Sim3Fit = robust_sim3(src, tgt, settings.gps_inlier_m, what="georegistration points")
    rec.transform(fit.tgt_from_src)
    kinds = np.array(kinds)
    report = {"used": settings.use, "n_gps": int((kinds == "gps").sum()), "n_gcp_in_fit": int((kinds == "gcp").sum()),
              "scale": float(fit.tgt_from_src.scale), "n_inliers": int(fit.inliers.sum()),
              "rmse_inliers_m": fit.rmse_inliers_m,
              "gps_residual_median_m": float(np.median(fit.residuals_m[kinds == "gps"])) if (kinds == "gps").any() else None,
              "outliers": [n for n, ok in zip(names, fit.inliers) if not ok]}
    gres = {}
    for g in gcps:
        s = gcp_sfm[g.name]
        if s["xyz"] is None:
            gres[g.name] = {"status": "not triangulated", "reason": s["reason"] or "fewer than 2 clicks in registered images",
                            "clicks_in_model": s["clicks_in_model"]}
            continue
        d = sim3_apply(fit.tgt_from_src, s["xyz"][None])[0] - g.xyz
        gres[g.name] = {"status": "ok", "dx_m": float(d[0]), "dy_m": float(d[1]), "dz_m": float(d[2]),
                        "err_m": float(np.linalg.norm(d)), "clicks_used": s["clicks_used"],
                        "clicks_total": s["clicks_total"], "in_fit": "gcp" in settings.use,
                        "click_residuals_px": s["click_residuals_px"]}
    ok = [v["err_m"] for v in gres.values() if v["status"] == "ok"]
    report["gcp_residuals"] = gres
    report["gcp_median_err_m"] = float(np.median(ok)) if ok else None
    report["gcp_rmse_m"] = float(np.sqrt(np.mean(np.square(ok)))) if ok else None
    return report
