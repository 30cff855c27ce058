"""Georegister a block: robust Sim(3) from SfM camera centres to GPS centres (and/or from
triangulated GCPs to their surveyed coordinates), then GCP and check-point residuals in metres.

Thresholds adapt to each group's own scatter (LO-RANSAC: metre-grade GCPs are kept and their
residuals reported), never under 3 sigma of a stated accuracy (geo.txt accuracy columns, the
``gcp_accuracy_m`` setting); GPS without a stated accuracy keeps the fixed ``gps_inlier_m``. GPS and
GCPs together are weighted by their own scatter.
Check points (``check`` in gcp_list.txt, or named in ``checkpoints``) never enter the fit.

GPS alone (no usable GCPs): a free Sim(3) is kept only where the positions hold the block's tilt
better than gravity does (RTK-grade, consistent heights); otherwise the tilt is held by gravity
(gimbal attitude, else the aerial prior) and the positions give heading, scale and position, their
altitudes an offset and a drift (gtkit.sfm.gps_fit). Every result is then checked for plausibility
(gtkit.sfm.plausibility: cameras above what they see, photos looking down, rotations consistent
with the gimbal attitude, scale) and refused with its cause when it fails."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..io.exif import capture_seconds
from ..io.odm import GCP
from .geometry import (RegistrationError, Sim3Fit, model_cameras, model_poses, robust_sim3, sim3_apply,
                       triangulate_clicks)
from .gps_fit import claimed_accuracy, gravity_held_fit
from .gravity import block_up
from .plausibility import check_block
from .similarity import collinearity, group_weighted_refit, umeyama

log = logging.getLogger(__name__)


@dataclass
class GeoregisterSettings:
    use: str = "gps+gcp"        # gps | gcp | gps+gcp: what the Sim(3) is fitted to
    gps_inlier_m: float = 2.0   # threshold on camera centres without a stated accuracy (RTK: small; consumer GPS: 3-5 m)
    gcp_accuracy_m: float | None = None  # the GCPs' stated accuracy (1 sigma); None: from their own scatter
    gcp_max_inlier_m: float = 5.0        # GCPs of unknown accuracy farther off than this are outliers
    gcp_max_px: float = 4.0     # clicks of a GCP farther than this from the triangulated point are dropped
    checkpoints: list[str] = field(default_factory=list)  # GCP names used only as check points
    # GPS alone: what holds the block's tilt. auto: the positions where they hold it better than
    # gravity does (see choose_gps_fit), else gravity; gps: always the positions (a free Sim(3));
    # gravity: always gravity (gimbal attitude, else the aerial prior)
    tilt_from: str = "auto"
    check_plausibility: bool = True   # refuse blocks upside down, tilted, looking up or at an implausible scale


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


def check_gcp_clicks(gcps: list[GCP], block_names: list[str]) -> dict[str, list[str]]:
    """{GCP name: photos it is clicked in that are not photos of this block}."""
    have = set(block_names)
    out = {}
    for g in gcps:
        missing = sorted({c.image for c in g.clicks if c.image not in have})
        if missing:
            out[g.name] = missing
    return out


def _not_usable(gcp_sfm: dict, names: list[str]) -> str:
    return "; ".join(f"{n}: {gcp_sfm[n]['reason'] or 'fewer than 2 clicks in registered photos'} "
                     f"({gcp_sfm[n]['clicks_in_model']} of {gcp_sfm[n]['clicks_total']} clicks in registered photos)"
                     for n in names)


def capture_times(names: list[str], metas: dict) -> np.ndarray:
    """Each photo's capture time (EXIF seconds) where every photo has one, else its order by name."""
    t = [capture_seconds(getattr(metas.get(n), "timestamp", None)) for n in names]
    if all(v is not None for v in t) and len(set(t)) > 1:
        return np.array(t, float)
    order = {n: k for k, n in enumerate(sorted(names))}
    return np.array([order[n] for n in names], float)


def tilt_sigma_deg(src_world: np.ndarray, tgt: np.ndarray) -> float:
    """How well positions with these residuals hold a block's tilt: vertical scatter over the
    horizontal spread, over the square root of their number (degrees)."""
    r = src_world[:, 2] - tgt[:, 2]
    sv = float(1.4826 * np.median(np.abs(r - np.median(r))))
    e = float(np.sqrt(np.mean(np.sum((tgt[:, :2] - tgt[:, :2].mean(0)) ** 2, axis=1))))
    return float(np.degrees(np.arctan2(sv, max(e, 1e-9) * np.sqrt(len(r)))))


def choose_gps_fit(free: Sim3Fit | None, free_error: str | None, grav, up, src: np.ndarray, tgt: np.ndarray,
                   mode: str) -> tuple[str, str]:
    """("free" | "gravity", why). auto: the free Sim(3) where its positions hold the tilt better than
    gravity's own uncertainty (and at least half of them agree, and it tilts the block by less than
    5 deg from gravity), else the gravity-held fit."""
    if mode == "gps" or grav is None:
        return "free", ("tilt_from = gps" if mode == "gps" else "no gravity estimate (photos neither carry attitude "
                        "nor look down)")
    if mode == "gravity":
        return "gravity", "tilt_from = gravity"
    if free is None:
        return "gravity", f"a free Sim(3) failed ({free_error})"
    inl = free.inliers
    share = float(inl.mean())
    w = np.array(src)[inl]
    R = free.tgt_from_src.rotation.matrix()
    sig = tilt_sigma_deg(free.tgt_from_src.scale * w @ R.T + free.tgt_from_src.translation, np.array(tgt)[inl])
    z_free = R @ up.vector
    tilt = float(np.degrees(np.arccos(np.clip(z_free[2], -1, 1))))
    if share < 0.5:
        return "gravity", f"only {100 * share:.0f} % of the GPS positions agree with a free Sim(3)"
    if sig > max(up.sigma_deg, 0.05):
        return "gravity", (f"the GPS heights hold the tilt to {sig:.2f} deg, gravity ({up.source}) to "
                           f"{up.sigma_deg:.2f} deg")
    if tilt > 5.0 + 3.0 * up.spread_deg:
        return "gravity", f"a free Sim(3) tilts the block {tilt:.1f} deg away from gravity ({up.source})"
    return "free", f"the GPS positions hold the tilt to {sig:.3f} deg ({100 * share:.0f} % agree)"


def _fitted_to(kinds: np.ndarray, inliers: np.ndarray) -> str:
    """What the fit rests on, in words: "12 GCPs", "118 GPS positions", "4 GCPs + 120 GPS positions"."""
    parts = []
    for k, label in (("gcp", "GCPs"), ("gps", "GPS positions")):
        n = int((inliers & (kinds == k)).sum())
        if n:
            parts.append(f"{n} {label}")
    return " + ".join(parts) or "nothing"


def _gps_quality(fit: Sim3Fit, kinds: np.ndarray, src: np.ndarray, tgt: np.ndarray, accuracy: dict,
                 names: list[str]) -> dict:
    """The GPS positions' residuals to a fit, horizontal and vertical apart, and what they claim."""
    g = kinds == "gps"
    d = sim3_apply(fit.tgt_from_src, src[g]) - tgt[g]
    inl = fit.inliers[g]
    rh, rv = np.linalg.norm(d[:, :2], axis=1), np.abs(d[:, 2])
    stated = [accuracy[n] for n, k in zip(names, kinds) if k == "gps" and n in accuracy]
    return {"mode": "free", "n_positions": int(g.sum()), "n_inliers": int(inl.sum()),
            "share_kept": round(float(inl.mean()), 3) if len(inl) else None,
            "horizontal_residual_median_m": float(np.median(rh[inl])) if inl.any() else None,
            "vertical_residual_median_m": float(np.median(rv[inl])) if inl.any() else None,
            "stated_accuracy_m": float(np.median(stated)) if stated else None,
            **(claimed_accuracy(float(np.median(rh[inl]) / 1.1774), float(1.4826 * np.median(rv[inl])),
                                float(np.median(stated)) if stated else None) if inl.any() else {})}


def georegister(rec: pycolmap.Reconstruction, gps: dict[str, np.ndarray], gcps: list[GCP],
                settings: GeoregisterSettings, gps_accuracy: dict[str, float] | None = None,
                metas: dict | None = None) -> dict:
    """Transform ``rec`` in place into the project's local world frame; returns a report dict.
    ``gps_accuracy``: {photo: stated 1-sigma accuracy in metres} (geo.txt): its threshold's floor.
    ``metas``: {photo: PhotoMeta} (gimbal attitude, time, relative altitude) for the GPS-alone fit and
    the plausibility check; None: the free Sim(3) as before, checked without attitude."""
    if settings.tilt_from not in ("auto", "gps", "gravity"):
        raise RegistrationError(f'[sfm.georegister] tilt_from = "{settings.tilt_from}": expected auto, gps or gravity')
    poses = model_poses(rec)
    gps_accuracy = gps_accuracy or {}
    checks = {g.name for g in gcps if g.check} | set(settings.checkpoints)
    # per point: threshold cap, floor, adaptive. Without a stated accuracy GPS keeps the fixed
    # gps_inlier_m and GCPs adapt to their scatter (<= gcp_max_inlier_m); with one, the threshold
    # adapts between 3 sigma of the stated accuracy and the cap, since the reconstruction's own
    # error (centimetres) can exceed a surveyed position's millimetres.
    src, tgt, kinds, names, cap, floor, adaptive = [], [], [], [], [], [], []
    if "gps" in settings.use:
        for n, p in poses.items():
            if n in gps and np.all(np.isfinite(gps[n])):
                acc = gps_accuracy.get(n)
                src.append(p.center), tgt.append(gps[n]), kinds.append("gps"), names.append(n)
                cap.append(max(settings.gps_inlier_m, 3.0 * acc) if acc else settings.gps_inlier_m)
                floor.append(3.0 * acc if acc else settings.gps_inlier_m)
                adaptive.append(bool(acc))
    gcp_sfm = triangulate_gcps(rec, gcps, settings.gcp_max_px) if gcps else {}
    control = [g for g in gcps if g.name not in checks]
    usable = [g for g in control if gcp_sfm[g.name]["xyz"] is not None]
    if "gcp" in settings.use:
        acc = settings.gcp_accuracy_m
        for g in usable:
            src.append(gcp_sfm[g.name]["xyz"]), tgt.append(g.xyz), kinds.append("gcp"), names.append(g.name)
            cap.append(max(settings.gcp_max_inlier_m, 3.0 * acc) if acc else settings.gcp_max_inlier_m)
            floor.append(3.0 * acc if acc else 0.05)
            adaptive.append(True)
    n_gps = kinds.count("gps")
    if n_gps < 3 and "gcp" in settings.use and control:
        # the GCPs carry the georegistration: say exactly which cannot be used and why
        if len(usable) + n_gps < 3:
            bad = [g.name for g in control if gcp_sfm[g.name]["xyz"] is None]
            raise RegistrationError(f"only {len(usable)} usable GCPs ({len(control)} control points"
                                    f"{', %d check points' % len(checks) if checks else ''}; 3 or more needed)"
                                    + (f"; not usable: {_not_usable(gcp_sfm, bad)}" if bad else ""))
        if n_gps == 0 and collinearity(np.array([g.xyz for g in usable])) < 1e-3:
            raise RegistrationError("the usable GCPs are collinear (" + ", ".join(g.name for g in usable)
                                    + "): the rotation about their line is undetermined; add a GCP off that line")
    if not src:
        raise RegistrationError(f"no GPS positions or triangulated GCPs to georegister with (use={settings.use})")
    fit_record = {"mode": "free", "why": "GCPs in the fit" if n_gps < len(src) else "no photo metadata"}
    gps_quality = None
    if n_gps == len(src) and metas is not None:
        up = block_up(rec, metas)   # in the block's own frame, before it moves
        # GPS alone: a free Sim(3) only where the positions hold the tilt; else gravity holds it
        free, free_error = None, None
        try:
            free = robust_sim3(np.array(src), np.array(tgt), np.array(cap), what="GPS positions",
                               adaptive=np.array(adaptive), floors=np.array(floor), groups=np.array(kinds))
        except RegistrationError as e:
            free_error = str(e)
        grav, grav_error = None, None
        if up is not None and settings.tilt_from != "gps":
            try:
                grav = gravity_held_fit(names, np.array(src), np.array(tgt), capture_times(names, metas), up,
                                        np.array([gps_accuracy.get(n, 0.0) for n in names]))
            except RegistrationError as e:
                grav_error = str(e)
        if grav is None and grav_error and (free is None or settings.tilt_from == "gravity"):
            raise RegistrationError(grav_error)
        choice, why = choose_gps_fit(free, free_error, grav, up, np.array(src), np.array(tgt), settings.tilt_from)
        if choice == "free" and free is None:
            raise RegistrationError(free_error or "no fit")
        if choice == "gravity":
            r3 = np.hypot(grav.residuals_h, grav.residuals_v)   # after the altitudes' drift
            fit = Sim3Fit(grav.sim, grav.inliers, r3, float(np.sqrt(np.mean(r3[grav.inliers] ** 2))), None)
            fit_record = {**grav.record, "why": why}
            gps_quality = grav.record
        else:
            fit = free
            fit_record = {"mode": "free", "why": why}
            if grav is not None:
                fit_record["gravity_check"] = {"tilt_from": up.source, "up": up.record()}
    else:
        fit: Sim3Fit = robust_sim3(np.array(src), np.array(tgt), np.array(cap), what="georegistration points",
                                   adaptive=np.array(adaptive), floors=np.array(floor), groups=np.array(kinds))
    kinds = np.array(kinds)
    sigmas = None
    if len(set(kinds[fit.inliers])) > 1 and fit.inliers.sum() >= 4:
        # GPS and GCPs together: each group weighted by its own scatter
        sim, sigmas = group_weighted_refit(np.array(src), np.array(tgt), fit.inliers, kinds)
        r = np.linalg.norm(sim.apply(np.array(src)) - np.array(tgt), axis=1)
        fit = Sim3Fit(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.R), sim.t), fit.inliers, r,
                      float(np.sqrt(np.mean(r[fit.inliers] ** 2))), fit.thresholds_m)
    rec.transform(fit.tgt_from_src)
    if gps_quality is None and (kinds == "gps").any():
        gps_quality = _gps_quality(fit, kinds, np.array(src), np.array(tgt), gps_accuracy, names)
    plaus = check_block(rec, metas) if settings.check_plausibility else None
    report = {"used": settings.use, "fitted_to": _fitted_to(kinds, fit.inliers), "fit": fit_record,
              "gps_quality": gps_quality, "plausibility": plaus, "n_gps": int((kinds == "gps").sum()), "n_gcp_in_fit": int((kinds == "gcp").sum()),
              "n_checkpoints": len([g for g in gcps if g.name in checks]),
              "scale": float(fit.tgt_from_src.scale), "n_inliers": int(fit.inliers.sum()),
              "rmse_inliers_m": fit.rmse_inliers_m,
              "gps_residual_median_m": float(np.median(fit.residuals_m[kinds == "gps"])) if (kinds == "gps").any() else None,
              "gcp_threshold_m": (float(np.median(fit.thresholds_m[kinds == "gcp"]))
                                  if fit.thresholds_m is not None and (kinds == "gcp").any() else None),
              "gps_threshold_m": (float(np.median(fit.thresholds_m[kinds == "gps"]))
                                  if fit.thresholds_m is not None and (kinds == "gps").any() else None),
              "group_sigma_m": sigmas,
              "outliers": [n for n, ok in zip(names, fit.inliers) if not ok]}
    gres = {}
    inlier_of = {n: bool(ok) for n, ok, k in zip(names, fit.inliers, kinds) if k == "gcp"}
    for g in gcps:
        s = gcp_sfm[g.name]
        if s["xyz"] is None:
            gres[g.name] = {"status": "not triangulated", "check": g.name in checks,
                            "reason": s["reason"] or "fewer than 2 clicks in registered images",
                            "clicks_in_model": s["clicks_in_model"]}
            continue
        d = sim3_apply(fit.tgt_from_src, s["xyz"][None])[0] - g.xyz
        gres[g.name] = {"status": "ok", "dx_m": float(d[0]), "dy_m": float(d[1]), "dz_m": float(d[2]),
                        "err_m": float(np.linalg.norm(d)), "clicks_used": s["clicks_used"],
                        "clicks_total": s["clicks_total"], "check": g.name in checks,
                        "in_fit": g.name in inlier_of and inlier_of[g.name],
                        "outlier": g.name in inlier_of and not inlier_of[g.name],
                        "click_residuals_px": s["click_residuals_px"]}
    ok = [v["err_m"] for v in gres.values() if v["status"] == "ok" and not v["check"]]
    chk = [v["err_m"] for v in gres.values() if v["status"] == "ok" and v["check"]]
    report["gcp_residuals"] = gres
    report["gcp_median_err_m"] = float(np.median(ok)) if ok else None
    report["gcp_rmse_m"] = float(np.sqrt(np.mean(np.square(ok)))) if ok else None
    report["checkpoint_median_err_m"] = float(np.median(chk)) if chk else None
    report["checkpoint_rmse_m"] = float(np.sqrt(np.mean(np.square(chk)))) if chk else None
    return report
