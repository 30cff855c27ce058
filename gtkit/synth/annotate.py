"""Simulated annotators: GCP clicks in reference photos and tie points between query and
reference photos, as a careful person would click them (true projection + noise, plus a
configurable share of gross mistakes)."""
from __future__ import annotations

import numpy as np

from ..io.tiepoints import Observation, TiePoint
from .flights import Shot


def project(shot: Shot, X: np.ndarray):
    """Pixels of world points in a shot and their camera z."""
    Xc = shot.pose.transform(np.atleast_2d(X))
    uv, front = shot.camera.project(Xc)
    return uv, Xc[:, 2], front


def visible(shot: Shot, depth: np.ndarray, X: np.ndarray, margin: float = 8.0, tol_rel: float = 0.01,
            tol_abs: float = 0.3):
    """(mask, uv) of points that project inside the photo and are not hidden (depth test)."""
    uv, z, front = project(shot, X)
    ok = front & shot.camera.in_image(uv, margin)
    out = np.zeros(len(uv), bool)
    f = shot.camera.width / depth.shape[1]        # depth maps may be stored subsampled
    if ok.any():
        ij = np.floor(uv[ok] / f).astype(int)
        d = depth[np.clip(ij[:, 1], 0, depth.shape[0] - 1), np.clip(ij[:, 0], 0, depth.shape[1] - 1)].astype(np.float64)
        out[ok] = np.isfinite(d) & (np.abs(d - z[ok]) < tol_rel * z[ok] + tol_abs)
    return out, uv


def gcp_clicks(gcps: np.ndarray, ref_shots: list[Shot], depths: dict[str, np.ndarray], sigma: float,
               max_clicks: int, rng: np.random.Generator) -> list[tuple[int, str, float, float]]:
    """(gcp index, image name, px, py): each GCP in its ``max_clicks`` most central views."""
    out = []
    for g, X in enumerate(gcps):
        cands = []
        for sh in ref_shots:
            vis, uv = visible(sh, depths[sh.name], X[None], margin=20)
            if vis[0]:
                c = np.array([sh.camera.width, sh.camera.height]) / 2
                cands.append((float(np.linalg.norm(uv[0] - c)), sh.name, uv[0]))
        cands.sort(key=lambda c: (c[0], c[1]))
        for _, name, uv in cands[:max_clicks]:
            n = rng.normal(0, sigma, 2)
            out.append((g, name, float(uv[0] + n[0]), float(uv[1] + n[1])))
    return out


def _candidates(gray: np.ndarray, depth: np.ndarray, exclude: np.ndarray, n: int) -> np.ndarray:
    """Well-textured pixels (corner response), as pixel coordinates (COLMAP convention)."""
    import cv2

    mask = (np.isfinite(depth) & ~exclude).astype(np.uint8) * 255
    mask = cv2.erode(mask, np.ones((7, 7), np.uint8))
    pts = cv2.goodFeaturesToTrack(gray, maxCorners=n, qualityLevel=0.02, minDistance=25, mask=mask,
                                  blockSize=7)
    if pts is None:
        return np.zeros((0, 2))
    ij = np.round(pts.reshape(-1, 2)).astype(int)       # integer array index -> pixel centre
    return ij + 0.5


def backproject(shot: Shot, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    ij = np.floor(uv).astype(int)
    z = depth[ij[:, 1], ij[:, 0]].astype(np.float64)
    xn = shot.camera.image_to_world(uv)
    Xc = np.column_stack([xn * z[:, None], z])
    return (Xc - shot.pose.t) @ shot.pose.R


def tie_points(queries: list[tuple[Shot, np.ndarray, np.ndarray, np.ndarray]], ref_shots: list[Shot],
               ref_depths: dict[str, np.ndarray], settings, rng: np.random.Generator, exclude_water=None):
    """queries: (shot, clean gray uint8, depth, moving-target mask). Returns (tiepoints, truth list)."""
    tps, truth = [], []
    for query in queries:
        query_tie_points(query, ref_shots, ref_depths, settings, rng, tps, truth, exclude_water)
    add_gross_mistakes(tps, truth, ref_shots, settings, rng)
    return tps, truth


def query_tie_points(query: tuple[Shot, np.ndarray, np.ndarray, np.ndarray], ref_shots: list[Shot],
                     ref_depths: dict[str, np.ndarray], settings, rng: np.random.Generator, tps: list,
                     truth: list, exclude_water=None) -> None:
    """Append one query photo's tie points to ``tps`` / ``truth`` (the generator calls it as each
    photo is rendered, so no full-size photo is kept; the same draws as :func:`tie_points`)."""
    a = settings
    ref_centres = np.array([r.pose.center for r in ref_shots])
    shot, gray, depth, tmask = query
    lo, hi = a.tiepoints_zoom if shot.kind == "zoom" else a.tiepoints_wide
    want = int(rng.integers(lo, hi + 1))
    excl = tmask.copy()
    if exclude_water is not None:
        excl |= exclude_water(shot, depth)
    uv = _candidates(gray, depth, excl, 300)
    if not len(uv):
        return
    X = backproject(shot, uv, depth)
    # reference views that see each candidate
    vis = np.zeros((len(X), len(ref_shots)), bool)
    ref_uv = np.zeros((len(X), len(ref_shots), 2))
    # only reference views near the clicked area can see it
    reach = np.hypot(ref_centres[:, 0] - X[:, 0].mean(), ref_centres[:, 1] - X[:, 1].mean())
    spread = np.hypot(*(X[:, :2].max(0) - X[:, :2].min(0)))
    near = reach < spread + 3.0 * np.maximum(ref_centres[:, 2] - X[:, 2].min(), 1.0)
    for k in np.flatnonzero(near):
        r = ref_shots[k]
        vis[:, k], ref_uv[:, k] = visible(r, ref_depths[r.name], X, margin=10)
    nvis = vis.sum(1)
    order = rng.permutation(len(X))
    order = order[np.argsort(-np.minimum(nvis[order], 2), kind="stable")]
    chosen = [i for i in order if nvis[i] >= 1][:want]
    for i in sorted(chosen):
        ks = np.flatnonzero(vis[i])
        # the views a person would pick: cameras closest to the query's viewing direction
        d_q = X[i] - shot.pose.center
        d_r = X[i] - ref_centres[ks]
        cosang = (d_r @ d_q) / (np.linalg.norm(d_r, axis=1) * np.linalg.norm(d_q))
        ks = ks[np.argsort(-cosang, kind="stable")]
        n_refs = int(rng.integers(a.refs_per_tiepoint[0], a.refs_per_tiepoint[1] + 1))
        ks = ks[:max(1, n_refs)]
        tid = f"tp{len(tps) + 1:04d}"
        obs = [Observation(shot.name, *(uv[i] + rng.normal(0, a.tie_sigma_px, 2)))]
        obs += [Observation(ref_shots[k].name, *(ref_uv[i, k] + rng.normal(0, a.tie_sigma_px, 2))) for k in ks]
        for o in obs:
            o.x, o.y = round(float(o.x), 3), round(float(o.y), 3)
        tps.append(TiePoint(tid, obs, source="simulated"))
        truth.append({"id": tid, "xyz": [round(float(v), 4) for v in X[i]], "gross_mistake": False,
                      "wrong_image": None,
                      "true_pixels": {shot.name: [round(float(v), 3) for v in uv[i]],
                                      **{ref_shots[k].name: [round(float(v), 3) for v in ref_uv[i, k]]
                                         for k in ks}}})


def add_gross_mistakes(tps: list, truth: list, ref_shots: list[Shot], settings, rng: np.random.Generator) -> None:
    """Exactly round(share * n) tie points get one wrong reference click (after every photo's ties)."""
    a = settings
    cams = {r.name: r.camera for r in ref_shots}
    n_bad = int(round(a.gross_share * len(tps)))
    for t in sorted(rng.choice(len(tps), n_bad, replace=False).tolist()) if n_bad else []:
        obs = tps[t].observations
        j = int(rng.integers(1, len(obs)))
        o, cam = obs[j], cams[obs[j].image]
        dist = rng.uniform(*a.gross_px)
        for ang in rng.uniform(0, 2 * np.pi) + np.arange(12) * (np.pi / 6):  # stay inside the photo
            nx, ny = o.x + dist * np.cos(ang), o.y + dist * np.sin(ang)
            if 1 <= nx <= cam.width - 1 and 1 <= ny <= cam.height - 1:
                break
        obs[j] = Observation(o.image, round(float(nx), 3), round(float(ny), 3))
        truth[t]["gross_mistake"], truth[t]["wrong_image"] = True, o.image
