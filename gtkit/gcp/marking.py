"""Where each GCP is in each photo, from the reference block and whatever has been clicked so far.

:func:`load_block` reads the reference block (``work/sfm_reference``): the georegistered model when
``gtkit sfm`` placed it (by GPS or by an earlier ``gcp_list.txt``), else the unplaced model it kept
when nothing could place it (no GPS, no clicks yet). :func:`solve` then, from the GCP coordinates and
the clicks:

- triangulates every GCP clicked in 2+ photos (the block's own frame; clicks farther than
  ``max_px`` from the rest are dropped, as georegistration does), with its image residual;
- fits the block to the world: a block placed by GPS is refined by a 7-parameter correction
  weighted by what its GPS fit holds (:func:`gps_held_fit`: one GCP fixes the shift, more the
  heading, tilt and scale as far as they beat the GPS); a block placed by GCPs alone, or not placed,
  gets a Sim(3) once 3 GCPs, not on one line, are triangulated (a shift before that where placed). Check points never enter it; they get their X / Y / Z error;
- predicts every GCP in every photo that sees it (in front, inside the photo, not hidden behind
  the block's own points there): from its triangulated position where it has one, else from its
  coordinates through the fit, each with its 1-sigma uncertainty in pixels (the placement's or the
  fit's accuracy + the GCP's stated accuracy, or the triangulation's from its clicks), ranked by how
  well the photo shows it (near the photo's centre, near the camera). A GCP predicted just outside a
  photo whose 2-sigma ellipse reaches into it is listed too, marked ``near_edge`` (on a real GCP site
  2 of 15 clicked GCPs fell 1-2 sigma outside the photos they were clicked in, sigma 120-600 px).

Pixels are full-resolution pixels in gtkit's convention (:mod:`gtkit.conventions`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.poses import POSES
from ..pose import Pose
from ..sfm.geometry import triangulate_clicks
from ..sfm.similarity import Similarity, collinearity, umeyama
from ..io.gcp_points import GCPPoint

CLICK_SIGMA_PX = 1.0     # a careful click on a GCP target (the sample's clicks: 0.5 px)
FIT_FLOOR_M = 0.03       # a fit's residual scale is never taken below this (block shape + triangulation)
MARGIN_PX = 4.0         # a prediction this close outside the photo's edge is still in the photo
EDGE_SIGMAS = 2.0       # a prediction outside the photo is listed when this many sigma reach into it,
EDGE_MAX_SIGMA = 0.5    # and its sigma is at most this share of the photo's diagonal (a point near the
                        # camera's horizon projects thousands of px out, sigma 3,500 px: nowhere to look)
TILT_FLOOR_DEG = {"aerial prior": 1.5, "gimbal": 0.2}   # systematic error of a gravity source (1 sigma)


@dataclass
class Block:
    poses: dict[str, Pose]
    cams: dict[str, Camera]
    seen: dict[str, np.ndarray]     # photo -> the block's 3D points it observes (for visibility)
    placed: bool                    # block frame = the project's world frame
    sigma_h_m: float | None = None  # the placement's 1-sigma accuracy (placed blocks)
    sigma_v_m: float | None = None
    how: str = ""
    by_gps: bool = False            # placed by 3+ GPS positions (its rotation and scale held by many points)
    # how well the GPS fit holds the block's heading, tilt and scale (1 sigma, rad / relative)
    heading_sigma: float = 0.0
    tilt_sigma: float = 0.0
    scale_sigma: float = 0.0
    centre: np.ndarray | None = None  # where the block's rotation and scale are least uncertain

    @property
    def photos(self) -> list[str]:
        return sorted(self.poses)


def load_block(paths) -> Block:
    """The reference block of ``paths`` (see the module doc); a GtkitError naming what to run when
    there is none."""
    import pycolmap

    from ..sfm.geometry import model_cameras, model_poses

    d = Path(paths.root) / "work" / "sfm_reference"
    placed = (d / "model").is_dir() and (d / POSES).is_file()
    mdir = d / "model" if placed else d / "unplaced_model"
    if not mdir.is_dir():
        raise GtkitError("no reference block yet: run `gtkit sfm SITE --block reference` first", d)
    rec = pycolmap.Reconstruction(str(mdir))
    poses, cams = model_poses(rec), model_cameras(rec)
    seen = {}
    for im in rec.images.values():
        if im.has_pose:
            ids = [p.point3D_id for p in im.points2D if p.has_point3D()]
            seen[im.name] = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    sh = sv = None
    how = "not placed in the world (no GPS, no GCP clicks when it was built)"
    if placed:
        try:
            geo = json.loads((d / "block.json").read_text()).get("georegistration", {})
        except (OSError, json.JSONDecodeError):
            geo = {}
        q = geo.get("gps_quality") or {}
        claim = geo.get("claimed_accuracy") or {}   # the one claim every report reads (sfm/accuracy_claim.py)
        if claim.get("h_m"):
            sh, sv = float(claim["h_m"]), float(claim.get("v_m") or claim["h_m"])
        elif q.get("absolute_accuracy_h_m"):   # a block georegistered before the claim was recorded
            sh, sv = float(q["absolute_accuracy_h_m"]), float(q.get("absolute_accuracy_v_m") or q["absolute_accuracy_h_m"])
        elif geo.get("gcp_rmse_m"):
            sh = sv = float(geo["gcp_rmse_m"])
        elif geo.get("rmse_inliers_m"):
            sh = sv = float(geo["rmse_inliers_m"])
        how = f"placed by {geo.get('fitted_to', 'georegistration')}"
        by_gps = int(geo.get("n_gps") or 0) >= 3
    else:
        by_gps, q, geo = False, {}, {}
    C = np.array([p.center for p in poses.values()]).reshape(-1, 3)
    pts = np.concatenate([v for v in seen.values()]) if seen else np.zeros((0, 3))
    centre = np.r_[C[:, :2].mean(0), np.median(pts[:, 2]) if len(pts) else C[:, 2].mean()] if len(C) else None
    block = Block(poses, cams, seen, placed, sh, sv, how, by_gps, centre=centre)
    if by_gps:
        _gps_precision(block, q, geo, C)
    return block


def _gps_precision(block: Block, q: dict, geo: dict, C: np.ndarray) -> None:
    """The GPS fit's heading / tilt / scale precision: as the fit states it (gravity-held fits:
    ``heading_precision_deg``, ``scale_precision``, gravity's sigma), else from the positions'
    scatter over the block's extent and their number."""
    n = max(int(q.get("n_inliers") or geo.get("n_inliers") or len(C)), 1)
    ext = float(np.sqrt(np.mean(np.sum((C[:, :2] - C[:, :2].mean(0)) ** 2, axis=1)))) if len(C) else 1.0
    sh = float(q.get("scatter_h_m") or q.get("horizontal_residual_median_m") or geo.get("rmse_inliers_m") or 0.1)
    sv = float(q.get("scatter_v_m") or q.get("vertical_residual_median_m") or sh)
    per = 1.0 / (max(ext, 1e-6) * np.sqrt(n))
    block.heading_sigma = np.radians(q["heading_precision_deg"]) if q.get("heading_precision_deg") else sh * per
    block.scale_sigma = float(q["scale_precision"]) if q.get("scale_precision") else sh * per
    fit = geo.get("fit") or {}
    up = fit.get("up") or {}
    if fit.get("mode") == "gravity-held" and up.get("sigma_deg") is not None:
        # gravity's stated sigma is its scatter; the systematic error of its source sets a floor
        # (the aerial prior: >= 1.5 deg, as gtkit.sfm.georegister judges it; a gimbal: 0.2 deg)
        floor = TILT_FLOOR_DEG.get(str(up.get("source")), TILT_FLOOR_DEG["gimbal"])
        block.tilt_sigma = np.radians(max(float(up["sigma_deg"]), floor))
    else:
        block.tilt_sigma = sv * per
    block.heading_sigma, block.tilt_sigma, block.scale_sigma = (max(v, 1e-5) for v in
                                                                (block.heading_sigma, block.tilt_sigma, block.scale_sigma))


@dataclass
class Prediction:
    gcp: str
    photo: str
    x: float
    y: float
    sigma_px: float
    depth: float                 # along the optical axis, block units
    rank_score: float            # lower = shows it better
    source: str                  # "triangulated" (its own clicks) or "coordinates" (through the fit)
    near_edge: bool = False      # outside the photo, its EDGE_SIGMAS ellipse reaching into it


@dataclass
class GCPState:
    name: str
    check: bool
    n_clicks: int
    clicks_used: int = 0
    xyz_block: np.ndarray | None = None       # triangulated, block frame
    residuals_px: dict[str, float] = field(default_factory=dict)  # photo -> reprojection residual
    residual_px: float | None = None          # RMS of the used clicks' residuals
    error_m: np.ndarray | None = None         # fitted position - coordinates (X, Y, Z), metres
    in_fit: bool = False
    reason: str = ""

    @property
    def error_3d_m(self) -> float | None:
        return None if self.error_m is None else float(np.linalg.norm(self.error_m))


@dataclass
class Solution:
    world_from_block: Similarity | None
    fit: str                                   # in words
    states: dict[str, GCPState]
    predictions: list[Prediction]
    sigma_fit_m: float | None = None

    def for_gcp(self, name: str) -> list[Prediction]:
        """The photos that see GCP ``name``, best first."""
        return sorted((p for p in self.predictions if p.gcp == name), key=lambda p: p.rank_score)

    def at(self, name: str, photo: str) -> Prediction | None:
        return next((p for p in self.predictions if p.gcp == name and p.photo == photo), None)

    def rmse_m(self, check: bool) -> float | None:
        e = [s.error_3d_m for s in self.states.values() if s.check == check and s.error_m is not None]
        return float(np.sqrt(np.mean(np.square(e)))) if e else None

    def rmse_xyz_m(self, check: bool) -> np.ndarray | None:
        e = [s.error_m for s in self.states.values() if s.check == check and s.error_m is not None]
        return np.sqrt(np.mean(np.square(e), axis=0)) if e else None


def _jacobian(cam: Camera, pose: Pose, X: np.ndarray) -> tuple[np.ndarray, float]:
    """d(pixel)/d(X) (2x3, pinhole part) at block point X, and its depth."""
    pc = pose.R @ X + pose.t
    z = pc[2]
    J = np.array([[cam.fx / z, 0.0, -cam.fx * pc[0] / z ** 2], [0.0, cam.fy / z, -cam.fy * pc[1] / z ** 2]])
    return J @ pose.R, float(z)


def _occluded(block: Block, photo: str, uv: np.ndarray, depth: float) -> bool:
    """Whether the block's own points observed around ``uv`` in ``photo`` lie clearly in front of
    a point at ``depth`` (a roof or a tree between the camera and the GCP)."""
    P = block.seen.get(photo)
    if P is None or len(P) < 10:
        return False
    pose, cam = block.poses[photo], block.cams[photo]
    pc = P @ pose.R.T + pose.t
    front = pc[:, 2] > 1e-9
    px, _ = cam.project(pc[front])
    r = max(15.0, 0.03 * cam.width)
    near = np.linalg.norm(px - uv, axis=1) < r
    if near.sum() < 3:
        return False
    return bool(np.median(pc[front][near, 2]) < 0.93 * depth)


def _point_cov_world(p: GCPPoint, sh: float, sv: float) -> np.ndarray:
    ah = p.acc_h or 0.0
    av = p.acc_v if p.acc_v is not None else ah
    return np.diag([sh ** 2 + ah ** 2, sh ** 2 + ah ** 2, sv ** 2 + av ** 2])


def _sim3(src: np.ndarray, tgt: np.ndarray) -> Similarity | None:
    if len(src) < 3 or collinearity(tgt) < 1e-3 or collinearity(src) < 1e-3:
        return None
    return umeyama(src, tgt)


def _shift(src: np.ndarray, tgt: np.ndarray) -> Similarity:
    return Similarity(1.0, np.eye(3), (tgt - src).mean(0))


def _loo_rms(fit, src: np.ndarray, tgt: np.ndarray) -> float:
    """Leave-one-out error of a fitting rule: each GCP predicted by the fit to the others."""
    e = []
    for i in range(len(src)):
        m = np.arange(len(src)) != i
        f = fit(src[m], tgt[m])
        if f is None:
            return float("inf")
        e.append(np.sum((f.apply(src[i:i + 1])[0] - tgt[i]) ** 2))
    return float(np.sqrt(np.mean(e)))


def _fit(block: Block, used: list[tuple[GCPPoint, np.ndarray]]) -> tuple[Similarity | None, str, float | None, dict]:
    """world_from_block from the triangulated control GCPs ``used`` ((point, block xyz)); the fit in
    words; its residual scale (m); the leverage data.

    Used where :func:`gps_held_fit` is not (a block placed by GCPs alone, or not placed, or a GCP
    without a covariance): a Sim(3) (with its covariance) once 3 GCPs not on one line are
    triangulated; before that a placed block is shifted onto its GCPs. (A block placed by GPS with
    4+ GCPs and no covariance: the Sim(3) only where it predicts left-out GCPs better than the shift;
    on the tiny sample a free Sim(3) to 3 GCPs put a check point 0.59 m off where the GPS held 0.20 m.)"""
    k = len(used)
    src = np.array([x for _, x in used]).reshape(-1, 3)
    tgt = np.array([p.xyz for p, _ in used]).reshape(-1, 3)
    floor = max([FIT_FLOOR_M] + [p.acc_h or 0.0 for p, _ in used])
    use_sim = (not block.by_gps or not block.placed
               or (k >= 4 and _loo_rms(_sim3, src, tgt) < _loo_rms(_shift, src, tgt)))
    if use_sim:
        sim = _sim3(src, tgt)
        if sim is not None:
            r = sim.apply(src) - tgt
            dof = 3 * k - 7
            s0 = float(np.sqrt((r ** 2).sum() / dof)) if dof > 0 else 0.0
            c = tgt.mean(0)
            return sim, f"Sim(3) to {k} GCPs", max(s0, floor), {"centre": c, "spread": float(((tgt - c) ** 2).sum()), "k": k}
    if block.placed and k >= 1:
        sim = _shift(src, tgt)
        r = sim.apply(src) - tgt
        s0 = float(np.sqrt((r ** 2).sum() / (3 * k - 3))) if k > 1 else 0.0
        return sim, f"block placement shifted to {k} GCP{'s' if k > 1 else ''}", max(s0, floor), {"k": k}
    if block.placed:
        return Similarity(1.0, np.eye(3), np.zeros(3)), block.how, None, {"k": 0}
    return None, (f"{k} GCP{'s' if k != 1 else ''} triangulated: 3 not on one line are needed to place the block"
                  if k else "the block is not placed: click 3 GCPs in 2+ photos each"), None, {"k": k}


def _tri_cov(block: Block, X: np.ndarray, photos: list[str], click_sigma_px: float) -> np.ndarray | None:
    """Covariance (block frame) of a point triangulated from clicks in ``photos`` of ``click_sigma_px``."""
    A = np.zeros((3, 3))
    for n in photos:
        J = _jacobian(block.cams[n], block.poses[n], X)[0]
        A += J.T @ J
    try:
        return click_sigma_px ** 2 * np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return None


def _sim_rows(Y: np.ndarray, c: np.ndarray) -> np.ndarray:
    """d(world point)/d(shift, small rotation, log scale) of a Sim(3) at world point Y (3x7),
    rotation and scale about ``c``."""
    from ..pose import skew

    d = Y - c
    return np.hstack([np.eye(3), -skew(d), d[:, None]])


def _sim_cov(sim: Similarity, used, covs_w: list[np.ndarray], c: np.ndarray) -> np.ndarray | None:
    """7x7 covariance of a Sim(3) fitted to GCPs (their triangulation's and coordinates' covariances
    ``covs_w``, world frame), scaled up by the residuals' chi-square where it exceeds its dof."""
    N = np.zeros((7, 7))
    chi2 = 0.0
    for (p, x), C in zip(used, covs_w):
        W = np.linalg.inv(C)
        A = _sim_rows(p.xyz, c)
        N += A.T @ W @ A
        r = sim.apply(x[None])[0] - p.xyz
        chi2 += float(r @ W @ r)
    dof = 3 * len(used) - 7
    try:
        cov = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        return None
    return cov * max(1.0, chi2 / dof if dof > 0 else 1.0)


def _small_sim(theta: np.ndarray, c: np.ndarray) -> Similarity:
    """The Sim(3) Y -> c + (1 + ds) R(w) (Y - c) + dt of a correction theta = (dt, w, ds)."""
    import pycolmap

    w = theta[3:6]
    a = float(np.linalg.norm(w))
    R = pycolmap.Rotation3d(np.r_[np.sin(a / 2) * w / a, np.cos(a / 2)]).matrix() if a > 1e-12 else np.eye(3)
    sc = 1.0 + float(theta[6])
    return Similarity(sc, R, c + theta[:3] - sc * R @ c)


def gps_held_fit(block: Block, used, covs_w: list[np.ndarray]) -> tuple[Similarity, np.ndarray, int]:
    """A block placed by GPS refined by the clicked GCPs: a 7-parameter correction (shift, rotation,
    scale about the block's centre) weighted by what the GPS fit claims for each (absolute accuracy,
    heading / tilt / scale precision) and by each GCP's triangulation + coordinates covariance.
    Returns the corrected world_from_block, the correction's covariance (inflated by the residuals'
    chi-square where it exceeds their count) and the number of GCPs."""
    c = block.centre if block.centre is not None else np.zeros(3)
    sh, sv = block.sigma_h_m or 1.0, block.sigma_v_m or block.sigma_h_m or 1.0
    P = np.diag(1.0 / np.square([sh, sh, sv, block.tilt_sigma, block.tilt_sigma, block.heading_sigma,
                                 block.scale_sigma]))
    N, b = P.copy(), np.zeros(7)
    rows = []
    for (p, x), C in zip(used, covs_w):
        W = np.linalg.inv(C)
        A = _sim_rows(x, c)
        r = p.xyz - x
        N += A.T @ W @ A
        b += A.T @ W @ r
        rows.append((A, W, r))
    theta = np.linalg.solve(N, b)
    cov = np.linalg.inv(N)
    if len(rows) >= 2:   # residuals larger than their covariances say: inflate (dof net of what the GCPs fit)
        chi2 = sum(float((r - A @ theta) @ W @ (r - A @ theta)) for A, W, r in rows)
        p_eff = float(np.trace(cov @ (N - P)))
        cov *= max(1.0, chi2 / max(3 * len(rows) - p_eff, 1.0))
    return _small_sim(theta, c), cov, len(rows)


def solve(block: Block, points: list[GCPPoint], clicks: dict[str, dict[str, tuple[float, float]]],
          click_sigma_px: float = CLICK_SIGMA_PX, max_px: float = 4.0) -> Solution:
    """See the module doc. ``clicks``: {GCP name: {photo: (x, y)}} (photos outside the block are kept
    but not used)."""
    states: dict[str, GCPState] = {}
    used = []
    covs: dict[str, np.ndarray | None] = {}   # triangulated GCPs' covariance, block frame
    for p in points:
        c = {ph: xy for ph, xy in clicks.get(p.name, {}).items() if ph in block.poses}
        st = states[p.name] = GCPState(p.name, p.check, len(clicks.get(p.name, {})))
        if len(c) < 2:
            st.reason = "clicked in fewer than 2 photos of the block" if c or st.n_clicks else "not clicked"
            continue
        names = sorted(c)
        tri = triangulate_clicks([block.cams[n] for n in names], [block.poses[n] for n in names],
                                 np.array([c[n] for n in names], float), max_px=max_px)
        st.residuals_px = {n: float(r) for n, r in zip(names, tri.residuals_px)}
        st.clicks_used = int(tri.used.sum())
        if tri.xyz is None:
            st.reason = tri.reason
            continue
        st.xyz_block = tri.xyz
        st.residual_px = float(np.sqrt(np.mean(tri.residuals_px[tri.used] ** 2)))
        covs[p.name] = _tri_cov(block, tri.xyz, [n for n, u in zip(names, tri.used) if u], click_sigma_px)
        if not p.check:
            used.append((p, tri.xyz))
    if block.placed and block.by_gps and all(covs.get(p.name) is not None for p, _ in used):
        sim, cov, k = gps_held_fit(block, used, [covs[p.name] + _point_cov_world(p, 0.0, 0.0) for p, _ in used])
        how = (f"{block.how}, refined by {k} GCP{'s' if k != 1 else ''} (weighted by the GPS fit's own precision)"
               if k else block.how)
        s0, lev = None, {"k": k, "centre": block.centre, "cov_theta": cov, "gps": True}
    else:
        sim, how, s0, lev = _fit(block, used)
    if sim is not None and "centre" in lev and "gps" not in lev and all(covs.get(p.name) is not None for p, _ in used):
        Rw = sim.scale * sim.R   # block -> world, linear part
        lev["cov_theta"] = _sim_cov(sim, used, [Rw @ covs[p.name] @ Rw.T + _point_cov_world(p, 0.0, 0.0)
                                                for p, _ in used], lev["centre"])
    for p, _ in used:
        states[p.name].in_fit = sim is not None and lev["k"] > 0
    if sim is not None:
        for p in points:
            st = states[p.name]
            if st.xyz_block is not None:
                st.error_m = sim.apply(st.xyz_block[None])[0] - p.xyz
    preds = []
    for p in points:
        st = states[p.name]
        if st.xyz_block is not None:   # its own clicks say where it is, whatever the fit
            X, src = st.xyz_block, "triangulated"
            cov_b = covs.get(p.name)
        elif sim is not None:
            X, src = np.linalg.solve(sim.R * sim.scale, p.xyz - sim.t), "coordinates"
            if lev.get("cov_theta") is not None:   # through the fit's own uncertainty
                A = _sim_rows(p.xyz, lev["centre"])
                cov_w = A @ lev["cov_theta"] @ A.T + _point_cov_world(p, 0.0, 0.0)
            elif lev["k"] == 0:
                cov_w = _point_cov_world(p, block.sigma_h_m or 1.0, block.sigma_v_m or block.sigma_h_m or 1.0)
            else:
                f = 1.0 + 1.0 / lev["k"]
                if "spread" in lev:
                    f += float(((p.xyz - lev["centre"]) ** 2).sum()) / max(lev["spread"], 1e-9)
                cov_w = _point_cov_world(p, s0 * np.sqrt(f), s0 * np.sqrt(f))
            Rb = sim.R.T / sim.scale            # world -> block (linear part)
            cov_b = Rb @ cov_w @ Rb.T
        else:
            continue
        cands = []
        for n in block.photos:
            cam, pose = block.cams[n], block.poses[n]
            pc = pose.R @ X + pose.t
            if pc[2] <= 1e-9:
                continue
            uv, _ = cam.project(pc[None])
            uv = uv[0]
            J, z = _jacobian(cam, pose, X)
            S = J @ cov_b @ J.T if cov_b is not None else None
            edge = not cam.in_image(uv, -MARGIN_PX)
            if edge and (S is None or np.sqrt(max(np.linalg.eigvalsh(S)[-1], 0.0)) > EDGE_MAX_SIGMA * np.hypot(
                    cam.width, cam.height) or not ellipse_meets_rect(uv, S, EDGE_SIGMAS, cam.width, cam.height)):
                continue
            if _occluded(block, n, uv, pc[2]):
                continue
            s = float(np.sqrt(max(np.linalg.eigvalsh(S)[-1], 0.0))) if S is not None else float("nan")
            r_norm = float(np.linalg.norm(uv - [cam.width / 2, cam.height / 2]) / np.hypot(cam.width / 2, cam.height / 2))
            cands.append([n, uv, s, z, r_norm, edge])
        if not cands:
            continue
        zmin = min(c[3] for c in cands)
        for n, uv, s, z, r_norm, edge in cands:
            preds.append(Prediction(p.name, n, float(uv[0]), float(uv[1]), s, z, r_norm + 0.5 * (z / zmin - 1.0), src,
                                    edge))
    return Solution(sim, how, states, preds, s0)


def ellipse_meets_rect(uv, cov: np.ndarray, k: float, width: float, height: float) -> bool:
    """Whether the ``k``-sigma ellipse of a point at ``uv`` with 2x2 covariance ``cov`` overlaps the
    rectangle [0, width] x [0, height]: the smallest Mahalanobis distance from ``uv`` to the rectangle
    (0 inside; else on one of its edges, a quadratic along each) is at most ``k``."""
    uv = np.asarray(uv, float)
    if 0.0 <= uv[0] <= width and 0.0 <= uv[1] <= height:
        return True
    try:
        M = np.linalg.inv(np.asarray(cov, float))
    except np.linalg.LinAlgError:
        return False
    if not np.all(np.isfinite(M)):
        return False
    corners = np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]])
    best = np.inf
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        d0, e = a - uv, b - a
        eme = float(e @ M @ e)
        t = float(np.clip(-(d0 @ M @ e) / eme, 0.0, 1.0)) if eme > 0 else 0.0
        d = d0 + t * e
        best = min(best, float(d @ M @ d))
    return best <= k * k


def predictions_csv(sol: Solution) -> str:
    """``gcp,photo,x,y,sigma_px,source,where`` lines, best photos of each GCP first; ``where`` is
    ``in the photo`` or ``near the edge`` (predicted outside it, its 2-sigma ellipse reaching in)."""
    rows = ["gcp,photo,x,y,sigma_px,source,where"]
    for name in dict.fromkeys(p.gcp for p in sol.predictions):
        for p in sol.for_gcp(name):
            rows.append(f"{p.gcp},{p.photo},{p.x:.2f},{p.y:.2f},{p.sigma_px:.2f},{p.source},"
                        + ("near the edge" if p.near_edge else "in the photo"))
    return "\n".join(rows) + "\n"
