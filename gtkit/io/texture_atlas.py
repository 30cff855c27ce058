"""A textured part's texture cut down to the texels its faces use: charts packed into one page.

A photo-textured part (``gtkit model build``: the faces each photo textures best) takes its faces
from all over the photo, so the bounding box of their texture coordinates is nearly the whole
photo while the faces use a fraction of it. Here the part's faces are split into charts (groups of
faces joined by shared vertices), each chart's texel box (``margin`` texels around it, so that
bilinear filtering and the first mipmap levels read the chart's own texels) is copied into a page,
boxes placed on shelves, tallest first, and the texture coordinates moved with their box. Boxes
are aligned to ``align`` texels in both textures, so mipmap levels up to ``log2(align)`` hold the
same texel averages on the page as in the photo: a view that samples those levels sees what it saw
before (to float32 rounding of the coordinates); coarser levels mix a chart's border with its
neighbour on the page.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

MAX_PAGE = 8192          # texels a side; wider parts keep their texture as it is


def charts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Each vertex's chart label (connected components of the faces' shared vertices)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    a = np.concatenate([f[:, 0], f[:, 1]])
    b = np.concatenate([f[:, 1], f[:, 2]])
    g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n_vertices, n_vertices))
    return connected_components(g, directed=False)[1]


def _shelves(w: np.ndarray, h: np.ndarray, page_w: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Positions (x, y) of boxes ``w`` x ``h`` on shelves of width ``page_w``, tallest first; the
    page height."""
    order = np.argsort(-h, kind="stable")
    X = np.zeros(len(w), np.int64)
    Y = np.zeros(len(w), np.int64)
    x = y = shelf_h = 0
    for i in order:
        if x + w[i] > page_w:
            y += shelf_h
            x = shelf_h = 0
        X[i], Y[i] = x, y
        x += w[i]
        shelf_h = max(shelf_h, h[i])
    return X, Y, y + shelf_h


def pack_charts(part, margin: int = 4, align: int = 4):
    """``part`` with its texture replaced by a page of the charts its faces use (the part itself
    when it has no texture, or packing would not make the texture smaller). Boxes start and end on
    multiples of ``align`` texels in both textures, so mipmap levels up to ``log2(align)`` average the
    same texels on the page as in the texture."""
    if part.texture is None or part.uv is None or len(part.faces) == 0:
        return part
    tex = part.texture
    H, W = tex.shape[:2]
    nv = len(part.vertices)
    px = part.uv[:, 0].astype(np.float64) * W
    py = (1.0 - part.uv[:, 1].astype(np.float64)) * H          # from the top row
    lab = charts(part.faces, nv)
    used = np.zeros(nv, bool)
    used[np.asarray(part.faces).ravel()] = True
    n = int(lab.max()) + 1
    lo_x = np.full(n, np.inf); hi_x = np.full(n, -np.inf)
    lo_y = np.full(n, np.inf); hi_y = np.full(n, -np.inf)
    np.minimum.at(lo_x, lab[used], px[used]); np.maximum.at(hi_x, lab[used], px[used])
    np.minimum.at(lo_y, lab[used], py[used]); np.maximum.at(hi_y, lab[used], py[used])
    keep = np.isfinite(lo_x)                                       # charts of faces (not lone vertices)
    x0 = np.zeros(n, np.int64); x1 = np.zeros(n, np.int64); y0 = np.zeros(n, np.int64); y1 = np.zeros(n, np.int64)
    a = int(align)
    x0[keep] = np.clip(np.floor((lo_x[keep] - margin) / a) * a, 0, None)
    x1[keep] = np.clip(np.ceil((hi_x[keep] + margin) / a) * a, x0[keep] + a, None)
    y0[keep] = np.clip(np.floor((lo_y[keep] - margin) / a) * a, 0, None)
    y1[keep] = np.clip(np.ceil((hi_y[keep] + margin) / a) * a, y0[keep] + a, None)
    w, h = x1 - x0, y1 - y0                      # multiples of align; the copy stops at the texture's edge
    area = int((w * h)[keep].sum())
    page_w = int(min(MAX_PAGE, max(int(w[keep].max()), int(np.ceil(np.sqrt(area * 1.1) / a)) * a)))
    idx = np.flatnonzero(keep)
    X = np.zeros(n, np.int64); Y = np.zeros(n, np.int64)
    X[idx], Y[idx], page_h = _shelves(w[idx], h[idx], page_w)
    if page_h > MAX_PAGE or page_w * page_h >= W * H:
        return part
    page = np.zeros((page_h, page_w) + tex.shape[2:], tex.dtype)
    for c in idx:
        src = tex[y0[c]:y1[c], x0[c]:x1[c]]
        page[Y[c]:Y[c] + src.shape[0], X[c]:X[c] + src.shape[1]] = src
    nx = px + (X - x0)[lab]
    ny = py + (Y - y0)[lab]
    uv = np.stack([nx / page_w, 1.0 - ny / page_h], 1).astype(part.uv.dtype)
    return replace(part, uv=uv, texture=page)
