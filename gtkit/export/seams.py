"""An orthophoto mosaicked from the reference photos over the DSM, its seams blended and measured.

Each cell's ground point (the DSM's height at the cell centre, gaps filled) is looked at from the
reference photo that sees it most from above (the largest vertical component of the direction to the
camera): that photo is the cell's **source**, and the cells of one source form its region. Where two
regions meet there is a **seam**. Two things hide it:

- **exposure compensation**: one gain per photo and colour channel, chosen so that photos agree on the
  ground they both see near their seams (least squares over every neighbouring pair, the gains held
  near 1: Brown & Lowe's gain compensation for panoramas, in logarithms);
- **feathering**: within ``feather`` cells of a region, its photo still contributes, its weight falling
  linearly from 1 inside the region to 0 at that distance, so the colours ramp across the seam.

:func:`seam_difference` measures what is left: the median absolute colour difference (0-255, mean
of the three channels) between 4-neighbouring cells that come from different photos, in the mosaic
as sourced (``seam_difference_before``) and as blended (``_after``). Its floor is the same difference
between neighbouring cells of one photo (``seam_difference_within``): texture, not seams. Feathering
alone lowers it (it spreads the jump over the band), so the summary also gives
``seam_photo_difference_before`` / ``_after``: how much the two photos' colours of the same cells at
their seam differ, before and after the gains (what exposure compensation fixes).

Occlusion is not tested (a cell may show a roof that hides it in its source photo); the most
top-down photo keeps that rare on aerial blocks.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.photo import read_photo
from .gapfill import Cameras
from .grid import Grid

log = logging.getLogger(__name__)


@dataclass
class Mosaic:
    rgb: np.ndarray            # (H, W, 3) uint8 blended (gain + feather) or as sourced, per ``blended``
    raw: np.ndarray            # (H, W, 3) uint8 each cell's colour from its source photo alone
    label: np.ndarray          # (H, W) int32 source photo index (-1: no photo sees the cell)
    names: list[str]           # photo of each index
    gains: np.ndarray          # (n_photos, 3) per-channel gains used (1 when not compensated)
    summary: dict


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours (N, 3) float32 of ``img`` at pixel positions ``uv`` (pixel centres at integer + 0.5)."""
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1.001)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1.001)
    x0, y0 = x.astype(np.int64), y.astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    im = img.astype(np.float32)
    return ((im[y0, x0] * (1 - fx) + im[y0, x0 + 1] * fx) * (1 - fy)
            + (im[y0 + 1, x0] * (1 - fx) + im[y0 + 1, x0 + 1] * fx) * fy)


def _ground_box(pose, cam, zlim: tuple[float, float], grid: Grid) -> tuple[int, int, int, int] | None:
    """Rows and columns (r0, r1, c0, c1) of ``grid`` that the photo can see between heights ``zlim``:
    its border's rays met with both planes (a ray at or above the horizon: the whole grid)."""
    t = np.linspace(0.0, 1.0, 9)
    w, h = cam.width, cam.height
    uv = np.concatenate([np.c_[t * w, np.zeros(9)], np.c_[t * w, np.full(9, h)],
                         np.c_[np.zeros(9), t * h], np.c_[np.full(9, w), t * h]])
    d = cam.rays(uv) @ pose.R                     # world directions of the border's pixels
    if (d[:, 2] > -1e-3).any():
        return 0, grid.height, 0, grid.width
    C = pose.center
    pts = np.concatenate([C + d * ((z - C[2]) / d[:, 2])[:, None] for z in zlim])
    if not (C[2] > zlim[1]):
        return 0, grid.height, 0, grid.width
    x0, x1 = pts[:, 0].min(), pts[:, 0].max()
    y0, y1 = pts[:, 1].min(), pts[:, 1].max()
    mx, my = 0.05 * (x1 - x0), 0.05 * (y1 - y0)      # the border between its samples may bulge (distortion)
    x0, x1, y0, y1 = x0 - mx, x1 + mx, y0 - my, y1 + my
    c0 = int(np.clip(np.floor((x0 - grid.xmin) / grid.res) - 1, 0, grid.width))
    c1 = int(np.clip(np.ceil((x1 - grid.xmin) / grid.res) + 1, 0, grid.width))
    r0 = int(np.clip(np.floor((grid.ymax - y1) / grid.res) - 1, 0, grid.height))
    r1 = int(np.clip(np.ceil((grid.ymax - y0) / grid.res) + 1, 0, grid.height))
    return None if r1 <= r0 or c1 <= c0 else (r0, r1, c0, c1)


def seam_difference(rgb: np.ndarray, label: np.ndarray) -> tuple[float | None, float | None, int]:
    """(median |colour jump| across seams, the same between neighbours of one photo, number of seam
    pairs). Colours 0-255, the mean of the channels' absolute differences; cells with label -1 left out."""
    c = rgb.astype(np.float32)
    across, within = [], []
    for a, b, la, lb in ((c[:, :-1], c[:, 1:], label[:, :-1], label[:, 1:]),
                         (c[:-1], c[1:], label[:-1], label[1:])):
        ok = (la >= 0) & (lb >= 0)
        d = np.abs(a - b).mean(axis=-1)
        across.append(d[ok & (la != lb)])
        within.append(d[ok & (la == lb)])
    across, within = np.concatenate(across), np.concatenate(within)
    med = (lambda v: float(np.median(v)) if len(v) else None)
    return med(across), med(within), int(len(across))


def _gains(pairs: dict, n: int, sigma_pair: float = 0.02, sigma_gain: float = 0.2) -> np.ndarray:
    """Per-photo, per-channel gains from how photos' colours of the same cells compare:
    ``pairs[(i, j)] = (count, median log(colour of j / colour of i) per channel)``. In logarithms, so
    that no common scale can shrink them all (a plain least-squares gain fit drifts towards 0 on large
    overlaps): minimises sum w_ij (l_i - l_j - t_ij)^2 / sigma_pair^2 + sum l_i^2 / sigma_gain^2,
    ``w_ij`` the pair's share of the largest overlap, ``g = exp(l)`` kept within [0.5, 2]."""
    g = np.ones((n, 3))
    if not pairs:
        return g
    top = max(v[0] for v in pairs.values())
    for ch in range(3):
        A = np.eye(n) / sigma_gain ** 2
        b = np.zeros(n)
        for (i, j), (cnt, ratio) in pairs.items():
            w = (cnt / top) / sigma_pair ** 2
            t = float(ratio[ch])                    # g_i I_i = g_j I_j  <=>  l_i - l_j = log(I_j / I_i)
            A[i, i] += w
            A[j, j] += w
            A[i, j] -= w
            A[j, i] -= w
            b[i] += w * t
            b[j] -= w * t
        g[:, ch] = np.clip(np.exp(np.linalg.solve(A, b)), 0.5, 2.0)
    return g


def mosaic(grid: Grid, heights: np.ndarray, cameras: Cameras, images: Path, *, feather_cells: int = 8,
           compensate: bool = True, feather: bool = True) -> Mosaic:
    """The reference photos mosaicked over ``heights`` (world z per cell of ``grid``; NaN: no cell)."""
    from scipy.ndimage import distance_transform_edt

    names = sorted(n for n in cameras.cams if n in cameras.poses)
    H, W = grid.shape
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    ok = np.isfinite(heights)
    cell = np.flatnonzero(ok.ravel())
    P = np.c_[X.ravel()[cell], Y.ravel()[cell], heights.ravel()[cell].astype(np.float64)]
    best = np.full(len(cell), -np.inf, np.float32)
    lab = np.full(len(cell), -1, np.int32)
    seen = {}
    pos_of = np.full(H * W, -1, np.int64)
    pos_of[cell] = np.arange(len(cell))
    pos_of = pos_of.reshape(H, W)
    zlim = (float(np.nanmin(heights)), float(np.nanmax(heights))) if len(cell) else (0.0, 0.0)
    for k, name in enumerate(names):
        pose, cam = cameras.poses[name], cameras.cams[name]
        box = _ground_box(pose, cam, zlim, grid)
        if box is None:
            continue
        cand = pos_of[box[0]:box[1], box[2]:box[3]].ravel()
        cand = cand[cand >= 0]
        uv, front = cam.project(pose.transform(P[cand]))
        vis = front & cam.in_image(uv, margin=1.0)
        idx = cand[vis]
        uv = uv[vis]
        if not len(idx):
            continue
        v = pose.center - P[idx]
        score = (v[:, 2] / np.linalg.norm(v, axis=1)).astype(np.float32)
        better = score > best[idx]
        best[idx[better]] = score[better]
        lab[idx[better]] = k
        seen[k] = (idx, uv.astype(np.float32))
    label = np.full(H * W, -1, np.int32)
    label[cell] = lab
    label = label.reshape(H, W)
    F = max(int(feather_cells), 1) if feather else 0
    B = max(F, 2)                  # every photo is sampled this far outside its region (seam measures)
    # colours of each photo on its region and the band around it
    cols: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # k -> (positions in `cell`, colour, distance)
    for k, (idx, uv) in seen.items():
        region = label == k
        rows, colsx = np.nonzero(region)
        if not len(rows):
            continue
        r0, r1 = max(rows.min() - B, 0), min(rows.max() + B + 1, H)
        c0, c1 = max(colsx.min() - B, 0), min(colsx.max() + B + 1, W)
        d = np.full((H, W), np.inf, np.float32)
        d[r0:r1, c0:c1] = distance_transform_edt(~region[r0:r1, c0:c1])
        dk = d.ravel()[cell[idx]]
        keep = dk <= B
        img = read_photo(images / names[k])
        cols[k] = (idx[keep], _bilinear(img, uv[keep]), dk[keep])
    src = np.zeros((len(cell), 3), np.float32)        # each cell's colour from its source photo
    for k, (pos, c, _d) in cols.items():
        mine = lab[pos] == k
        src[pos[mine]] = c[mine]
    # pairs of photos on the cells next to their seams: photo k just outside its region, on j's cells
    n = len(names)
    shared: dict[tuple[int, int], list] = {}         # (i, j), i < j -> [(colour of i, colour of j) on shared cells]
    seam_obs = []                                      # (k, j, colour of k, colour of j) at seam cells
    for k, (pos, c, dk) in cols.items():
        other = lab[pos]
        sel = (other != k) & (other >= 0)
        near = sel & (dk <= 1.0)
        seam_obs.append((np.full(near.sum(), k), other[near], c[near], src[pos[near]]))
        for j in np.unique(other[sel]):
            m = sel & (other == j)
            ck, cj = c[m], src[pos[m]]
            shared.setdefault((min(k, j), max(k, j)), []).append((ck, cj) if k < j else (cj, ck))
    gains = np.ones((n, 3))
    if compensate and shared:
        pairs = {}
        for key, obs in shared.items():
            ci = np.concatenate([o[0] for o in obs])
            cj = np.concatenate([o[1] for o in obs])
            lit = (ci.min(1) > 8) & (cj.min(1) > 8) & (ci.max(1) < 250) & (cj.max(1) < 250)   # not black, not clipped
            if lit.sum() >= 20:   # the median log ratio: robust to cells one photo sees occluded or misplaced
                pairs[key] = (int(lit.sum()), np.median(np.log(cj[lit] / ci[lit]), axis=0))
        gains = _gains(pairs, n)
    num = np.zeros((len(cell), 3), np.float64)
    den = np.zeros(len(cell), np.float64)
    for k, (pos, c, dk) in cols.items():
        w = np.clip(1.0 - dk / (F + 1.0), 0.0, 1.0) if F else (lab[pos] == k).astype(np.float64)
        num[pos] += w[:, None] * c * gains[k]
        den[pos] += w
    blended = np.where(den[:, None] > 0, num / np.maximum(den, 1e-12)[:, None], src * gains[np.maximum(lab, 0)])
    out_raw = np.zeros((H * W, 3), np.uint8)
    out_raw[cell] = np.clip(np.rint(src), 0, 255).astype(np.uint8)
    out = np.zeros((H * W, 3), np.uint8)
    out[cell] = np.clip(np.rint(blended), 0, 255).astype(np.uint8)
    out_raw, out = out_raw.reshape(H, W, 3), out.reshape(H, W, 3)
    before = seam_difference(out_raw, label)
    after = seam_difference(out, label)
    if seam_obs and sum(len(o[0]) for o in seam_obs):
        ks, js, ck, cj = (np.concatenate(v) for v in zip(*seam_obs))
        photo_before = float(np.median(np.abs(ck - cj).mean(1)))
        photo_after = float(np.median(np.abs(ck * gains[ks] - cj * gains[js]).mean(1)))
    else:
        photo_before = photo_after = None
    summary = {"n_photos_used": int(len(np.unique(lab[lab >= 0]))), "feather_cells": F,
               "gain_compensation": bool(compensate), "covered_share": float((label >= 0).mean()),
               "seam_difference_before": before[0], "seam_difference_after": after[0],
               "seam_difference_within": before[1], "seam_pairs": before[2],
               "seam_photo_difference_before": photo_before, "seam_photo_difference_after": photo_after,
               "gains_range": [float(gains.min()), float(gains.max())],
               "seam_difference": "median |colour jump| (0-255, mean of R,G,B) between 4-neighbouring cells from "
                                  "different photos, in the orthophoto as sourced (before) and as blended (after); "
                                  "_within: the same between neighbours from one photo (texture, the floor); "
                                  "seam_photo_difference: how much the two photos disagree on the same cells at "
                                  "their seam, before and after exposure compensation (feathering aside)"}
    return Mosaic(out, out_raw, label, names, gains, summary)
