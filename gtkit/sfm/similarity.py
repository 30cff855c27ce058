"""Robust 3D similarity (Sim(3)) between point sets: closed-form Umeyama on minimal and inlier
sets inside an LO-RANSAC with per-point thresholds.

gtkit's own, because ``pycolmap.estimate_sim3d_robust`` returns None whenever either point set is
exactly coplanar (every GCP at Z = 0, as many ``gcp_list.txt`` files have when heights were not
surveyed). Umeyama needs only three non-collinear points.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np


@dataclass
class Similarity:
    scale: float
    R: np.ndarray      # 3x3
    t: np.ndarray      # 3

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x, float) @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        return np.hstack([self.scale * self.R, self.t[:, None]])


def umeyama(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray | None = None) -> Similarity | None:
    """Least-squares similarity tgt ~ s R src + t (Umeyama 1991), optionally weighted.
    None when the points are degenerate (coincident or collinear)."""
    src, tgt = np.asarray(src, float), np.asarray(tgt, float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    ms, mt = w @ src, w @ tgt
    xs, xt = src - ms, tgt - mt
    var_s = float(w @ (xs ** 2).sum(1))
    if var_s <= 1e-18:
        return None
    C = (xt * w[:, None]).T @ xs
    U, D, Vt = np.linalg.svd(C)
    if D[1] <= 1e-9 * max(D[0], 1e-300):  # collinear: rotation about the line undetermined
        return None
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s)
    return Similarity(s, R, mt - s * R @ ms)


def collinearity(x: np.ndarray) -> float:
    """Second over first singular value of the centred points: 0 for collinear points."""
    x = np.asarray(x, float)
    if len(x) < 2:
        return 0.0
    sv = np.linalg.svd(x - x.mean(0), compute_uv=False)
    return float(sv[1] / sv[0]) if sv[0] > 0 else 0.0


@dataclass
class RobustFit:
    sim: Similarity
    inliers: np.ndarray      # bool
    residuals: np.ndarray    # |sim(src) - tgt|
    thresholds: np.ndarray   # per point, as finally used


def lo_ransac_similarity(src: np.ndarray, tgt: np.ndarray, thresholds: np.ndarray, *,
                         adaptive: np.ndarray | None = None, floors: np.ndarray | None = None,
                         groups: np.ndarray | None = None, max_trials: int = 2000, seed: int = 0) -> RobustFit | None:
    """LO-RANSAC similarity. ``thresholds``: inlier distance per point. ``adaptive`` (bool per point):
    those points' threshold is re-estimated from their group's inliers' own scatter (3 x 1.4826 x
    the median distance, within [``floors``, ``thresholds``]; floors default 5 cm) — survey points
    whose accuracy is unknown, or stated but smaller than the reconstruction's own error.
    Minimal sets: every triple when there are few points, else ``max_trials`` random triples."""
    src, tgt = np.asarray(src, float), np.asarray(tgt, float)
    th = np.asarray(thresholds, float).copy()
    n = len(src)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    if n * (n - 1) * (n - 2) // 6 <= max_trials:
        triples = itertools.combinations(range(n), 3)
    else:
        triples = (tuple(rng.choice(n, 3, replace=False)) for _ in range(max_trials))

    def score(sim):
        r = np.linalg.norm(sim.apply(src) - tgt, axis=1)
        return np.minimum((r / th) ** 2, 1.0).sum(), r

    best = None
    for tri in triples:
        idx = list(tri)
        if collinearity(src[idx]) < 1e-3 or collinearity(tgt[idx]) < 1e-3:
            continue
        sim = umeyama(src[idx], tgt[idx])
        if sim is None or not np.isfinite(sim.scale) or sim.scale <= 0:
            continue
        cost, r = score(sim)
        if best is None or cost < best[0]:
            best = (cost, sim, r)
    if best is None:
        return None
    sim, r = best[1], best[2]
    inl = r <= th
    for _ in range(20):  # local optimisation: refit on the inliers until they stop changing
        if inl.sum() < 3 or collinearity(src[inl]) < 1e-3:
            break
        refit = umeyama(src[inl], tgt[inl])
        if refit is None:
            break
        sim = refit
        r = np.linalg.norm(sim.apply(src) - tgt, axis=1)
        if adaptive is not None:
            # 3 x 1.4826 x median distance: lenient on purpose (few points, metre-grade survey data
            # must be kept and reported), yet a point 10x farther off than its group is dropped
            grp = np.zeros(n, int) if groups is None else np.asarray(groups)
            lo = np.full(n, 0.05) if floors is None else np.asarray(floors, float)
            for g in np.unique(grp):
                a = adaptive & inl & (grp == g)
                if a.any():
                    sel = adaptive & (grp == g)
                    th[sel] = np.clip(3.0 * 1.4826 * np.median(r[a]), lo[sel], np.asarray(thresholds, float)[sel])
        new = r <= th
        if np.array_equal(new, inl):
            break
        inl = new
    return RobustFit(sim, inl, r, th)


def group_weighted_refit(src: np.ndarray, tgt: np.ndarray, inliers: np.ndarray, groups: np.ndarray,
                         iterations: int = 5, floor: float = 0.01) -> tuple[Similarity, dict]:
    """Refit on the inliers with each group of points (e.g. GPS centres, GCPs) weighted by the
    inverse variance of its own residuals, re-estimated each round (floor ``floor`` metres): points
    of unknown accuracy are weighted by how well they agree, so metre-grade GCPs beside centimetre
    GPS (or the reverse) no longer tilt the fit. Returns the similarity and {group: sigma}."""
    src, tgt, groups = np.asarray(src, float), np.asarray(tgt, float), np.asarray(groups)
    inl = np.asarray(inliers, bool)
    sim = umeyama(src[inl], tgt[inl])
    sigma = {}
    for _ in range(iterations):
        r = np.linalg.norm(sim.apply(src) - tgt, axis=1)
        sigma = {g: max(float(np.sqrt(np.mean(r[inl & (groups == g)] ** 2) / 3.0)), floor)
                 for g in np.unique(groups[inl])}
        w = np.array([1.0 / sigma[g] ** 2 for g in groups[inl]])
        new = umeyama(src[inl], tgt[inl], w)
        if new is None:
            break
        sim = new
    return sim, sigma
