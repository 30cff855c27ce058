"""Georegister a block: robust Sim(3) from SfM camera centres to GPS centres (and/or from
triangulated GCPs to their surveyed coordinates), then GCP and check-point residuals in metres.

Thresholds adapt to each group's own scatter (LO-RANSAC: metre-grade GCPs are kept and their
residuals reported), never under 3 sigma of a stated accuracy (geo.txt accuracy columns, the
``gcp_accuracy_m`` setting); GPS without a stated accuracy keeps the fixed ``gps_inlier_m``. GPS and
GCPs together are weighted by their own scatter.
Check points (``check`` in gcp_list.txt, or named in ``checkpoints``) never enter the fit.

GPS alone (no usable GCPs): a prior decides only what the evidence cannot (issue 45). The free
Sim(3)'s tilt is held by the positions, about their own line and across it, to their scatter (never
under their stated accuracy) over their spread (``tilt_hold``); gravity comes from the gimbal
attitude (a measurement), else the aerial prior where the photos look down under the positions'
fit, else the level prior (a terrestrial / facade capture: photos level and upright). Where the two
agree, each tilt axis is taken from both weighted by their variances (``choose_gps_fit``: the free
fit, the gravity-held fit of gtkit.sfm.gps_fit, or a combination, e.g. a single strip's roll about
its line from gravity); where they disagree, surveyed positions against gravity are refused with
both figures, positions without a stated accuracy (consumer GPS, drifting heights) yield to
gravity, and the aerial prior yields to positions under which the photos look level. Every result
is then checked for plausibility (gtkit.sfm.plausibility: the aerial checks only for aerial blocks
or blocks nothing holds; rotations consistent with the gimbal attitude; scale) and refused with
its cause when it fails.

GCP clicks made on resized photos are found and scaled (gtkit.sfm.gcp_click_scale,
``gcp_click_scale``); the click threshold follows the clicks' consistency and the photo size
(``gcp_max_px`` = None). ``used`` in the report says what the fit used: gps, gcp or gps+gcp."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..io.exif import capture_seconds
from ..io.odm import GCP
from .geometry import (RegistrationError, Sim3Fit, model_cameras, model_poses, robust_sim3, sim3_apply,
                       triangulate_clicks)
from .accuracy_claim import claim_of_fit, fitted_to
from .gcp_click_scale import click_threshold_px, detect_click_scale, scaled
from .gps_fit import claimed_accuracy, gravity_held_fit
from .gravity import block_up, up_from_level_prior
from .plausibility import check_block
from .similarity import collinearity, group_weighted_refit

log = logging.getLogger(__name__)


@dataclass
class GeoregisterSettings:
    use: str = "gps+gcp"        # gps | gcp | gps+gcp: what the Sim(3) is fitted to
    gps_inlier_m: float = 2.0   # threshold on camera centres without a stated accuracy (RTK: small; consumer GPS: 3-5 m)
    gcp_accuracy_m: float | None = None  # the GCPs' stated accuracy (1 sigma); None: from their own scatter
    gcp_max_inlier_m: float = 5.0        # GCPs of unknown accuracy farther off than this are outliers
    # clicks of a GCP farther than this (px) from the triangulated point are dropped; None: from the
    # clicks' own consistency and the photo size (gtkit.sfm.gcp_click_scale.click_threshold_px: 4 px
    # per 2,000 px of photo diagonal at least)
    gcp_max_px: float | None = None
    # GCP clicks made on resized photos (gtkit.sfm.gcp_click_scale): "auto" applies a scale found by
    # both the clicks' box and their reprojection; "off" never (a GCP refusal then names it); "2" etc.
    # multiplies every click by that factor
    gcp_click_scale: str = "auto"
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


def _click_scale(rec: pycolmap.Reconstruction, gcps: list[GCP], mode: str,
                 in_fit: bool = True) -> tuple[list[GCP], dict | None, str]:
    """The GCPs with their clicks at the photos' scale (see gtkit.sfm.gcp_click_scale), a record of
    what was found and done, and a note for a refusal where a scale was found but not applied.
    "off" with a scale the reprojection confirms, GCPs in the fit: refused (the clicks are known wrong)."""
    mode = str(mode).strip().lower()
    if mode not in ("auto", "off"):
        try:
            k = float(mode)
        except ValueError:
            raise RegistrationError(f'[sfm.georegister] gcp_click_scale = "{mode}": expected auto, off or a factor')
        if k != 1.0:
            log.warning("GCP clicks multiplied by %g (gcp_click_scale = %s)", k, mode)
        return scaled(gcps, k), {"factor": k, "applied": True, "line": f"clicks multiplied by {k:g} (gcp_click_scale)"}, ""
    cs = detect_click_scale(gcps, model_cameras(rec), model_poses(rec))
    if cs is None:
        return gcps, None, ""
    line = cs.line()
    if mode == "auto" and cs.confirmed:
        log.warning("%s: clicks multiplied by %g (set [sfm.georegister] gcp_click_scale = \"off\" to keep them)",
                    line, cs.factor)
        return scaled(gcps, cs.factor), {**cs.record(), "applied": True}, ""
    how = f'set [sfm.georegister] gcp_click_scale = "{cs.factor:g}" to apply it'
    if cs.confirmed and in_fit:
        # "off" and the reprojection confirms the scale: the clicks as given are known wrong
        raise RegistrationError(f"{line}: {how} (gcp_click_scale = \"off\" keeps them as given)")
    return gcps, {**cs.record(), "applied": False}, f"{line}: {how}"


def check_gcp_clicks(gcps: list[GCP], block_names: list[str]) -> dict[str, list[str]]:
    """{GCP name: photos it is clicked in that are not photos of this block}."""
    have = set(block_names)
    out = {}
    for g in gcps:
        missing = sorted({c.image for c in g.clicks if c.image not in have})
        if missing:
            out[g.name] = missing
    return out


def _range(v: list[float], unit: str) -> str:
    v = sorted(v)
    return f"{v[0]:.1f} {unit}" if len(v) == 1 or abs(v[-1] - v[0]) < 0.05 else f"{v[0]:.1f}-{v[-1]:.1f} {unit}"


def _names(names: list[str], most: int = 4) -> str:
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def _not_usable(gcp_sfm: dict, names: list[str], n_photos: int) -> str:
    """Why these GCPs cannot be used, one clause per cause (not per GCP)."""
    import re

    by: dict[str, list[str]] = {}
    for n in names:
        r = gcp_sfm[n]["reason"] or "fewer than 2 clicks in posed images"
        key = ("few" if r.startswith("fewer than 2") else "disagree" if r.startswith("clicks disagree")
               else "parallel" if r.startswith("rays nearly parallel") else r)
        by.setdefault(key, []).append(n)
    parts = []
    for key, ns in by.items():
        if key == "few":
            parts.append((f"no GCP has 2 clicks in this model's {n_photos} photos ({len(ns)} GCPs)"
                          if len(ns) == len(names) else
                          f"{len(ns)} GCPs have fewer than 2 clicks in this model's {n_photos} photos ({_names(ns)})"))
        elif key == "disagree":
            px = [float(m.group(1)) for n in ns for m in [re.search(r"reprojection ([0-9.]+) px", gcp_sfm[n]["reason"])] if m]
            lim = re.search(r"> ([0-9.]+) px", gcp_sfm[ns[0]]["reason"])
            parts.append(f"the clicks of {len(ns)} GCP{'s' if len(ns) > 1 else ''} disagree (reprojection "
                         f"{_range(px, 'px')} > {lim.group(1) if lim else '?'} px: {_names(ns)})")
        elif key == "parallel":
            parts.append(f"{len(ns)} GCP{'s' if len(ns) > 1 else ''} seen along nearly parallel rays ({_names(ns)})")
        else:
            parts.append(f"{key} ({_names(ns)})")
    return "; ".join(parts)


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


@dataclass
class TiltHold:
    """How well points (camera positions or GCPs) hold a fit's tilt, about two horizontal axes: the
    points' own line (``axes[0]``: its principal horizontal direction) and the axis across it. A
    single strip or a short arc holds the roll about its own line weakly (``sigma_deg[0]`` large)."""
    axes: np.ndarray          # (2, 3) unit horizontal axes in the world frame: along the points' line, across it
    sigma_deg: np.ndarray     # (2,) 1-sigma of the rotation about each axis
    scatter_m: float          # per-axis scatter of the points used (max of stated and measured)

    def record(self) -> dict:
        return {"about_line_deg": round(float(self.sigma_deg[0]), 4), "across_line_deg": round(float(self.sigma_deg[1]), 4),
                "scatter_m": round(self.scatter_m, 4)}


def tilt_hold(world_src: np.ndarray, tgt: np.ndarray, stated_m: float | None = None) -> TiltHold:
    """:class:`TiltHold` of points placed at ``world_src`` by a fit, against their targets ``tgt``:
    per-axis scatter = max(stated accuracy, the residuals' robust scatter); a rotation about a
    horizontal axis a is held to scatter / sqrt(sum of the points' squared distances from a)."""
    world_src, tgt = np.asarray(world_src, float), np.asarray(tgt, float)
    d = world_src - tgt
    measured = float(1.4826 * np.median(np.abs(d - np.median(d, axis=0)))) if len(d) >= 3 else np.inf
    scatter = max(measured, stated_m or 0.0, 1e-6)
    P = tgt - tgt.mean(0)
    w, V = np.linalg.eigh(P[:, :2].T @ P[:, :2])
    line = np.r_[V[:, 1], 0.0]
    across = np.r_[-V[1, 1], V[0, 1], 0.0]
    sig = []
    for a in (line, across):
        info = float(np.sum(P ** 2) - np.sum((P @ a) ** 2))
        sig.append(np.degrees(scatter / np.sqrt(max(info, 1e-18))))
    return TiltHold(np.array([line, across]), np.minimum(np.array(sig), 180.0), scatter)


def tilt_between(R: np.ndarray, up: np.ndarray, hold: TiltHold) -> tuple[float, np.ndarray]:
    """How far a fit (rotation ``R``, block to world) tilts the block from ``up`` (in the block's
    frame): the whole angle and its components about ``hold``'s two axes (degrees)."""
    v = R @ (np.asarray(up, float) / np.linalg.norm(up))
    z = np.array([0.0, 0.0, 1.0])
    total = float(np.degrees(np.arccos(np.clip(v[2], -1, 1))))
    comp = np.array([np.degrees(np.arctan2(v @ np.cross(a, z), v[2])) for a in hold.axes])
    return total, comp


def median_view_z(rec: pycolmap.Reconstruction, R: np.ndarray | None = None) -> float | None:
    """The photos' median optical-axis z in the world frame a rotation ``R`` (block to world) would give."""
    zs = [im.cam_from_world().rotation.matrix()[2] for im in rec.images.values() if im.has_pose]
    if not zs:
        return None
    zs = np.array(zs) if R is None else np.array(zs) @ np.asarray(R).T
    return float(np.median(zs[:, 2]))


def camera_plane(src: np.ndarray, up, level_up, min_ratio: float = 10.0) -> str | None:
    """Where the SfM camera centres lie in a clear plane (its second spread over its third >=
    ``min_ratio``) that the level prior holds level (< 20 deg) and the aerial prior tilts (> 45 deg):
    a line saying so (a terrestrial capture at one height); else None."""
    if up is None or level_up is None or up.source != "aerial prior" or len(src) < 4:
        return None
    P = np.asarray(src, float) - np.mean(src, axis=0)
    w, V = np.linalg.eigh(P.T @ P)
    if w[1] < min_ratio * max(w[0], 1e-18):
        return None
    n = V[:, 0]
    a_aer = float(np.degrees(np.arccos(min(1.0, abs(n @ up.vector)))))
    a_lev = float(np.degrees(np.arccos(min(1.0, abs(n @ level_up.vector)))))
    if a_aer > 45.0 and a_lev < 20.0:
        return (f"the cameras lie in a plane level by the level prior ({a_lev:.0f} deg) and {a_aer:.0f} deg from "
                "level by the aerial prior: a terrestrial capture, the aerial prior does not apply")
    return None


AERIAL_VIEW_Z = -0.26    # photos looking more than 15 deg below the horizon: an aerial view
CONSISTENT_CHI2 = 9.21   # 99 % of a chi-square with 2 degrees of freedom (two tilt axes)
PRIOR_BIAS_DEG = 1.5     # a gravity estimate's systematic error (gimbal calibration, camera mount)
PRIOR_FLOOR_DEG = 0.05   # no gravity estimate is weighted as surer than this (photos of a synthetic or
                         # perfectly level camera agree to 0.002 deg; a real mount does not)


@dataclass
class GpsChoice:
    choice: str                      # "free" | "gravity" | "combined"
    why: str
    up: object = None                # the Up the tilt is held by ("gravity" / "combined")
    hold: TiltHold | None = None     # how well the positions hold the free fit's tilt
    record: dict = field(default_factory=dict)


def choose_gps_fit(free: Sim3Fit | None, free_error: str | None, grav, up, src: np.ndarray, tgt: np.ndarray,
                   mode: str, *, rec: pycolmap.Reconstruction | None = None, stated_m: float | None = None,
                   level_up=None) -> GpsChoice:
    """Which fit places a block by GPS alone; evidence first, a prior only for what it cannot hold.

    The free Sim(3)'s tilt is held by the positions to ``hold.sigma_deg`` about the positions' line
    and across it (their scatter, never under their stated accuracy ``stated_m``). The prior that
    applies is the gimbal attitude (a measurement), else the aerial prior where the photos look down
    under the free fit, else (level photos: a terrestrial or facade capture) the level prior.
    - prior and positions agree (within both uncertainties): each tilt axis from whichever holds it
      better, weighted by their variances (the roll about a single strip's line from gravity);
    - they disagree: surveyed positions (a stated accuracy) against gimbal attitude or the aerial
      prior of a block that looks down: refused with both figures; positions without a stated
      accuracy (consumer GPS: heights drift) against either: gravity; the aerial prior on photos
      that look level under a fit the positions hold: the prior does not apply, the positions place it;
    - the free fit failed, or fewer than half of the positions agree with it: gravity.
    The SfM cameras themselves tell a terrestrial capture at one height (``camera_plane``: their
    plane level by the level prior, tilted > 45 deg by the aerial prior): the level prior then
    applies, so that positions too weak to hold the tilt never let the aerial prior lay a facade flat.
    ``grav``: the gravity-held fit by ``up`` where one could be made (None: failed or not tried)."""
    if mode == "gps" or (up is None and level_up is None):
        return GpsChoice("free", "tilt_from = gps" if mode == "gps" else "no gravity estimate (photos neither carry "
                         "attitude nor look down)")
    if mode == "gravity":
        return GpsChoice("gravity", "tilt_from = gravity", up)
    plane = camera_plane(np.asarray(src), up, level_up)
    base = level_up if plane else up      # the prior that applies where the positions hold nothing
    if free is None:
        return GpsChoice("gravity", (plane + "; " if plane else "") + f"a free Sim(3) failed ({free_error})", base)
    inl = free.inliers
    share = float(inl.mean())
    R = free.tgt_from_src.rotation.matrix()
    world = free.tgt_from_src.scale * np.asarray(src)[inl] @ R.T + free.tgt_from_src.translation
    hold = tilt_hold(world, np.asarray(tgt)[inl], stated_m)
    held = f"{hold.sigma_deg[1]:.3g} deg across their line, {hold.sigma_deg[0]:.3g} deg about it"
    if share < 0.5:
        return GpsChoice("gravity", (plane + "; " if plane else "") + f"only {100 * share:.0f} % of the GPS positions "
                         "agree with a free Sim(3)", base, hold)
    vz = median_view_z(rec, R) if rec is not None else None
    aerial_view = vz is None or vz < AERIAL_VIEW_Z
    prior = up
    note = ""
    if plane is not None and aerial_view:
        # the cameras lie in a plane that the level prior holds level and the aerial prior tilts: a
        # terrestrial capture at one height (a flight at one altitude is level by the aerial prior)
        aerial_view = False
        note = plane + "; "
    if up is not None and up.source == "aerial prior" and not aerial_view:
        if level_up is None:
            # no level prior either: the positions alone hold the tilt, or nothing does
            if max(hold.sigma_deg) > 5.0:
                raise RegistrationError(
                    f"the photos look level under the GPS positions' fit (median viewing direction z = {vz:+.2f}), "
                    f"so the aerial prior does not apply, and the positions hold the tilt only to {held}: "
                    "nothing places this block's tilt (give surveyed positions, GCPs or gimbal attitude)")
            return GpsChoice("free", f"the photos look level under the GPS positions' fit (z = {vz:+.2f}): "
                             f"the aerial prior does not apply; the positions hold the tilt to {held}", None, hold)
        prior = level_up
        note = note or f"photos level under the positions (z = {vz:+.2f}): the aerial prior does not apply; "
    if prior is None and level_up is not None and not aerial_view:
        prior = level_up
    if prior is None:
        return GpsChoice("free", f"the positions hold the tilt to {held} (no gravity estimate)", None, hold)
    total, comp = tilt_between(R, prior.vector, hold)
    var_pos, var_pri = hold.sigma_deg ** 2, max(prior.sigma_deg, PRIOR_FLOOR_DEG) ** 2
    # agreement is judged with the prior's systematic error too (a gimbal's or a camera mount's bias
    # does not average down over photos): never under PRIOR_BIAS_DEG
    chi2 = float(np.sum(comp ** 2 / (var_pos + max(prior.sigma_deg, PRIOR_BIAS_DEG) ** 2)))
    rec_ = {"prior": prior.source, "prior_sigma_deg": round(float(prior.sigma_deg), 4), "positions_hold": hold.record(),
            "free_tilt_from_prior_deg": round(total, 4), "chi2": round(chi2, 2), "free_view_z": vz}
    if total > 60.0 or chi2 > CONSISTENT_CHI2:
        both = (f"the GPS positions tilt the block {total:.1f} deg from gravity ({prior.source}, held to "
                f"{prior.sigma_deg:.2g} deg); the positions hold their tilt to {held}")
        if prior.source == "level prior":
            if max(hold.sigma_deg) < 1.0:
                return GpsChoice("free", note + f"the positions place it: the level prior disagrees by {total:.1f} deg "
                                 f"and they hold the tilt to {held}", None, hold, rec_)
            return GpsChoice("gravity", note + f"the positions hold the tilt only to {held} (and tilt the block "
                             f"{total:.1f} deg from the level prior): the level prior holds it", prior, hold, rec_)
        if not stated_m:
            return GpsChoice("gravity", both + " but state no accuracy (consumer heights drift): gravity holds the tilt",
                             prior, hold, rec_)
        raise RegistrationError(f"the positions and gravity disagree: {both} with a stated accuracy of "
                                f"{stated_m:.3g} m (set [sfm.georegister] tilt_from = \"gps\" or \"gravity\" to choose)")
    alpha = var_pos / (var_pos + var_pri)       # per axis: the prior's share
    if np.all(alpha < 0.1):
        return GpsChoice("free", note + f"the GPS positions hold the tilt to {held}, better than gravity "
                         f"({prior.source}, {prior.sigma_deg:.2g} deg), which agrees ({total:.2f} deg)", None, hold, rec_)
    if np.all(alpha > 0.9) and prior is up:
        return GpsChoice("gravity", f"the GPS heights hold the tilt to {held}, gravity ({prior.source}) to "
                         f"{prior.sigma_deg:.2f} deg", prior, hold, rec_)
    # each axis from both, weighted: the block's up in its own frame
    z = np.array([0.0, 0.0, 1.0])
    v = z.copy()
    for a, c, al in zip(hold.axes, comp, alpha):
        v = v + np.tan(np.radians(al * c)) * np.cross(a, z)
    v /= np.linalg.norm(v)
    sig = np.sqrt(var_pos * var_pri / (var_pos + var_pri))
    from .gravity import Up

    combined = Up(R.T @ v, f"positions + {prior.source}", prior.n_photos, prior.spread_deg, float(sig.max()))
    axis = "roll about the positions' line" if alpha[0] > alpha[1] else "tilt across the positions' line"
    rec_["combined_sigma_deg"] = [round(float(x), 4) for x in sig]
    return GpsChoice("combined", note + f"the {axis} held mostly by gravity ({prior.source}, {prior.sigma_deg:.2g} deg), "
                     f"the rest by the positions ({held})", combined, hold, rec_)


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
                metas: dict | None = None, gcp_accuracy: dict[str, tuple] | None = None) -> dict:
    """Transform ``rec`` in place into the project's local world frame; returns a report dict.
    ``gps_accuracy``: {photo: stated 1-sigma accuracy in metres} (geo.txt): its threshold's floor.
    ``metas``: {photo: PhotoMeta} (gimbal attitude, time, relative altitude) for the GPS-alone fit and
    the plausibility check; None: the free Sim(3) as before, checked without attitude.
    ``gcp_accuracy``: {GCP name: (stated h, stated v) metres} (the GCP points file's accuracy
    columns; a GCP not in it takes ``settings.gcp_accuracy_m``): only for the accuracy claimed
    (``report["claimed_accuracy"]``, :func:`accuracy_claim`), never for the fit."""
    notes: dict = {}
    try:
        return _georegister(rec, gps, gcps, settings, gps_accuracy, metas, notes, gcp_accuracy or {})
    except RegistrationError as e:
        # a click scale found but not applied is named with whatever refusal follows from it
        if notes.get("click_scale") and notes["click_scale"] not in str(e):
            raise RegistrationError(f"{notes['click_scale']}; {e}") from e
        raise


def _gcp_residuals(gcps: list[GCP], gcp_sfm: dict, fit: Sim3Fit, names: list[str], kinds: np.ndarray,
                   checks: set) -> dict:
    """Each GCP's and check point's residual after the fit (or why it was not triangulated), and the
    median / RMSE of both kinds."""
    report = {}
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


def _georegister(rec, gps, gcps, settings, gps_accuracy, metas, notes: dict, gcp_accuracy: dict) -> dict:
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
    gcp_sfm, click_scale, click_scale_note, click_thr = {}, None, "", None
    if gcps:
        gcps, click_scale, click_scale_note = _click_scale(rec, gcps, settings.gcp_click_scale, "gcp" in settings.use)
        notes["click_scale"] = click_scale_note
        cams_m = model_cameras(rec)
        click_thr = ({"max_px": float(settings.gcp_max_px), "from": "gcp_max_px"} if settings.gcp_max_px
                     else {**click_threshold_px(gcps, cams_m, poses), "from": "the clicks' consistency and photo size"})
        gcp_sfm = triangulate_gcps(rec, gcps, click_thr["max_px"])
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
                                    + (f"; not usable: {_not_usable(gcp_sfm, bad, len(poses))}" if bad else ""))
        if n_gps == 0 and collinearity(np.array([g.xyz for g in usable])) < 1e-3:
            raise RegistrationError("the usable GCPs are collinear (" + ", ".join(g.name for g in usable)
                                    + "): the rotation about their line is undetermined; add a GCP off that line")
    if not src:
        raise RegistrationError(f"no GPS positions or triangulated GCPs to georegister with (use={settings.use})")
    fit_record = {"mode": "free", "why": "GCPs in the fit" if n_gps < len(src) else "no photo metadata"}
    gps_quality = None
    held_by_evidence = None
    if n_gps == len(src) and metas is not None:
        up = block_up(rec, metas)   # in the block's own frame, before it moves
        # GPS alone: a free Sim(3) only where the positions hold the tilt; else gravity holds it
        free, free_error = None, None
        try:
            free = robust_sim3(np.array(src), np.array(tgt), np.array(cap), what="GPS positions",
                               adaptive=np.array(adaptive), floors=np.array(floor), groups=np.array(kinds))
        except RegistrationError as e:
            free_error = str(e)
        stated = [gps_accuracy[n] for n in names if gps_accuracy.get(n)]
        stated_m = float(np.median(stated)) if len(stated) >= len(names) / 2 else None
        level_up = up_from_level_prior(rec) if metas is not None else None
        times = capture_times(names, metas)
        acc_arr = np.array([gps_accuracy.get(n, 0.0) for n in names])
        grav, grav_error = None, None
        if up is not None and settings.tilt_from != "gps":
            try:
                grav = gravity_held_fit(names, np.array(src), np.array(tgt), times, up, acc_arr)
            except RegistrationError as e:
                grav_error = str(e)
        if grav is None and grav_error and (free is None or settings.tilt_from == "gravity"):
            raise RegistrationError(grav_error)
        ch = choose_gps_fit(free, free_error, grav, up, np.array(src), np.array(tgt), settings.tilt_from,
                            rec=rec, stated_m=stated_m, level_up=level_up)
        why = ch.why
        if ch.choice == "free" and free is None:
            raise RegistrationError(free_error or "no fit")
        if ch.choice == "gravity" and ch.up is not up:
            grav = gravity_held_fit(names, np.array(src), np.array(tgt), times, ch.up, acc_arr)
        if ch.choice == "combined":
            grav = gravity_held_fit(names, np.array(src), np.array(tgt), times, ch.up, acc_arr)
        if ch.choice in ("gravity", "combined"):
            if grav is None:
                raise RegistrationError(grav_error or "no gravity-held fit")
            r3 = np.hypot(grav.residuals_h, grav.residuals_v)   # after the altitudes' drift
            fit = Sim3Fit(grav.sim, grav.inliers, r3, float(np.sqrt(np.mean(r3[grav.inliers] ** 2))), None)
            fit_record = {**grav.record, "why": why, "decision": ch.record}
            if ch.choice == "combined":
                fit_record["mode"] = "combined"
            gps_quality = grav.record
        else:
            fit = free
            fit_record = {"mode": "free", "why": why, "decision": ch.record}
            if ch.hold is not None:
                fit_record["positions_hold_tilt"] = ch.hold.record()
            if grav is not None:
                fit_record["gravity_check"] = {"tilt_from": up.source, "up": up.record()}
        held_by_evidence = ch.choice in ("free", "combined") and ch.hold is not None and \
            float(ch.hold.sigma_deg.min()) < 1.0
        if ch.hold is not None and not held_by_evidence:
            notes["evidence"] = (f"the {len(names)} GPS positions hold it only to {float(ch.hold.sigma_deg.max()):.2g} deg"
                                 + (", placed by the level prior" if ch.up is not None and ch.up.source == "level prior"
                                    else ""))
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
    if held_by_evidence is None:
        # positions / GCPs in a free fit: they hold its tilt where their residuals and spread say so
        inl = fit.inliers
        stated_all = [gps_accuracy.get(n) if k == "gps" else settings.gcp_accuracy_m for n, k in zip(names, kinds)]
        stated_in = [v for v, ok in zip(stated_all, inl) if ok and v]
        hold = tilt_hold(sim3_apply(fit.tgt_from_src, np.array(src)[inl]), np.array(tgt)[inl],
                         float(np.median(stated_in)) if len(stated_in) >= inl.sum() / 2 else None)
        fit_record["points_hold_tilt"] = hold.record()
        held_by_evidence = inl.sum() >= 3 and float(hold.sigma_deg.max()) < 2.0
    rec.transform(fit.tgt_from_src)
    if gps_quality is None and (kinds == "gps").any():
        gps_quality = _gps_quality(fit, kinds, np.array(src), np.array(tgt), gps_accuracy, names)
    used = "+".join(k for k in ("gps", "gcp") if (fit.inliers & (kinds == k)).any()) or settings.use
    plaus = (check_block(rec, metas, held_by=(fitted_to(kinds, fit.inliers) if held_by_evidence else None),
                         evidence=notes.get("evidence"))
             if settings.check_plausibility else None)
    report = {"used": used, "used_setting": settings.use, "gcp_click_scale": click_scale, "gcp_click_threshold": click_thr,
              "fitted_to": fitted_to(kinds, fit.inliers), "fit": fit_record,
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
    report.update(_gcp_residuals(gcps, gcp_sfm, fit, names, kinds, checks))
    report["claimed_accuracy"] = claim_of_fit(
        names, kinds, fit.inliers, src, tgt, sigmas, np.array([p.center for p in poses.values()]).reshape(-1, 3),
        (gps_accuracy, gcp_accuracy, settings.gcp_accuracy_m), fit_record.get("mode", "free"), gps_quality, report)
    return report
