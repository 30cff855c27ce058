"""Ray marching against a height grid (DSM) to the FIRST surface crossing.

A DSM is a 2.5D surface z = h(x, y). A ray ``p(s) = o + s d`` (``d`` unit, ``s`` in metres)
is above the surface while ``f(s) = p_z(s) - h(p_x(s), p_y(s)) > 0``. We march ``s`` from the
ray's entry into the DSM's box in steps of at most half a cell, take the FIRST step where ``f``
changes from > 0 to <= 0, and refine only inside that bracketing step by bisection down to
``tol`` metres along the ray. Free space above the surface is skipped first with a block-max
pyramid (8x8 cells, dilated by one block), which only skips segments that provably cannot
cross the surface, so the result is the same as marching from the start. A plain bisection
over the whole ray could converge to any crossing (e.g. the ground behind a building);
marching first cannot.

Heights come from the DSM reader of the export stage (:class:`gtkit.export.dsm.Dsm`,
bilinear between cell centres); cells with no data (NaN) count as "no surface" (the ray may
pass over them). This module adds the vectorised marcher (many rays at once) and the
statuses. Every ray gets a status:

``hit``        the first crossing was found (``point`` is finite);
``sky``        the ray does not descend and starts above every DSM height: it never meets it;
``outside``    the ray leaves the DSM's extent (or goes below its lowest height through cells
               with no data) without crossing the surface.

Rays that miss get NaN coordinates, never a made-up point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import GtkitError

HIT, SKY, OUTSIDE, STARTS_BELOW = "hit", "sky", "outside", "starts_below"

MESSAGES = {
    HIT: "",
    SKY: "the ray points at or above the horizon and starts above every DSM height: it never meets the surface",
    OUTSIDE: "the ray leaves the DSM extent (or crosses only cells without data) without meeting the surface",
    STARTS_BELOW: "the ray starts below the DSM surface (camera position under the terrain?)",
}


def surface_range(dsm) -> tuple[float, float]:
    """(lowest, highest) height of a DSM (cached on the object)."""
    r = getattr(dsm, "_gtkit_track_zrange", None)
    if r is None:
        v = dsm.heights[np.isfinite(dsm.heights)]
        if not len(v):
            raise GtkitError("the DSM has no valid cell", getattr(dsm, "path", None))
        r = (float(v.min()), float(v.max()))
        dsm._gtkit_track_zrange = r
    return r


def dsm_from_array(heights, xmin: float, ymax: float, res: float, frame=None):
    """A :class:`gtkit.export.dsm.Dsm` from a numpy grid (row 0 = north, world frame), for
    synthetic tests and benchmarks."""
    from ..export.dsm import Dsm
    from ..export.grid import Grid
    from ..geo import GeoFrame

    h = np.asarray(heights, dtype=np.float64)
    frame = frame or GeoFrame("EPSG:32633", (0.0, 0.0, 0.0))
    return Dsm(h, Grid(float(xmin), float(ymax), float(res), h.shape[1], h.shape[0]), frame)


@dataclass
class RayHits:
    points: np.ndarray     # (N, 3) world; NaN where no hit
    distance: np.ndarray   # (N,) metres along the ray; NaN where no hit
    status: np.ndarray     # (N,) str: hit / sky / outside / starts_below

    @property
    def ok(self) -> np.ndarray:
        return self.status == HIT

    def message(self, i: int) -> str:
        return MESSAGES[str(self.status[i])]


def _box_interval(o, d, lo, hi):
    """Slab test: s-interval where the ray is inside the axis-aligned box [lo, hi] (per ray)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.where(np.isfinite(t1) & np.isfinite(t2), np.minimum(t1, t2), -np.inf)
    tmax = np.where(np.isfinite(t1) & np.isfinite(t2), np.maximum(t1, t2), np.inf)
    # a zero direction component: inside the slab for all s, or never
    par = ~np.isfinite(t1) | ~np.isfinite(t2)
    outside_par = par & ((o < lo) | (o > hi))
    tmin = np.where(par, -np.inf, tmin)
    tmax = np.where(par, np.inf, tmax)
    s0 = np.maximum(tmin.max(axis=1), 0.0)
    s1 = tmax.min(axis=1)
    s1 = np.where(outside_par.any(axis=1), -np.inf, s1)
    return s0, s1


def cast_rays(dsm, origins, directions, *, step: float | None = None, tol: float = 0.01,
              max_distance: float = 20000.0, block: int = 64, chunk: int = 8192, skip: bool = True) -> RayHits:
    """First crossing of each ray with the DSM (a :class:`gtkit.export.dsm.Dsm`: its
    ``height_at`` sampler, ``heights`` and ``grid`` are used).

    ``step`` (metres along the ray) defaults to half the smaller cell size and is capped at it;
    ``tol`` is the bisection tolerance along the ray (default 1 cm). Rays are processed
    ``chunk`` at a time, ``block`` steps per vectorised pass. ``skip`` jumps over free space
    with a block-max pyramid first (exact; off only to check that it is).
    """
    o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    if o.shape[-1] != 3 or d.shape[-1] != 3:
        raise GtkitError("ray origins and directions must be (N, 3)")
    o, d = np.broadcast_arrays(o, d)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if not np.all(np.isfinite(o)) or not np.all(np.isfinite(d)) or np.any(norm == 0):
        raise GtkitError("ray origins/directions must be finite and directions non-zero")
    o, d = o.copy(), d / norm
    parts = [_cast_chunk(dsm, o[i:i + chunk], d[i:i + chunk], step, tol, max_distance, block, skip)
             for i in range(0, len(o), chunk)] or [_cast_chunk(dsm, o, d, step, tol, max_distance, block, skip)]
    return RayHits(np.concatenate([p.points for p in parts]), np.concatenate([p.distance for p in parts]),
                   np.concatenate([p.status for p in parts]))


def _cast_chunk(dsm, o, d, step, tol, max_distance, block, skip=True) -> RayHits:
    n = len(o)
    g = dsm.grid
    zmin, zmax = surface_range(dsm)
    half = 0.5 * g.res
    step = half if step is None else min(float(step), half)
    pts = np.full((n, 3), np.nan)
    dist = np.full(n, np.nan)
    status = np.full(n, OUTSIDE, dtype=object)

    lo = np.array([g.xmin, g.ymin, zmin - 1.0])
    hi = np.array([g.xmax, g.ymax, zmax + 1e-6])
    s0, s1 = _box_interval(o, d, lo, hi)
    s1 = np.minimum(s1, max_distance)

    h0 = dsm.height_at(o[:, 0], o[:, 1])
    below = np.isfinite(h0) & (o[:, 2] < h0)
    status[below] = STARTS_BELOW
    sky = (d[:, 2] >= 0) & (o[:, 2] > zmax) & ~below
    status[sky] = SKY

    active = np.where(~below & ~sky & (s1 > s0))[0]
    if len(active):
        # skip free space with the block-max pyramid (exact: only provably empty segments)
        s_prev = (_coarse_start(dsm, o[active], d[active], s0[active], s1[active]) if skip
                  else s0[active].copy())
        f_prev = _f(dsm, o[active], d[active], s_prev)
        # f_prev NaN (no data) counts as above the surface; starting in the box but under the
        # surface is the "starts below" case handled above, or a hit right at s0
        at_start = np.isfinite(f_prev) & (f_prev <= 0)
        if at_start.any():
            idx = active[at_start]
            dist[idx] = s0[idx]
            pts[idx] = o[idx] + s0[idx, None] * d[idx]
            status[idx] = HIT
        keep = ~at_start
        active, s_prev = active[keep], s_prev[keep]
        ks = np.arange(1, block + 1, dtype=np.float64)
        while len(active):
            oa, da = o[active], d[active]
            s = s_prev[:, None] + step * ks[None, :]                      # (m, block)
            s = np.minimum(s, s1[active, None])
            P = oa[:, None, :] + s[..., None] * da[:, None, :]
            f = P[..., 2] - dsm.height_at(P[..., 0], P[..., 1])
            crossed = np.isfinite(f) & (f <= 0)
            any_c = crossed.any(axis=1)
            if any_c.any():
                rows = np.where(any_c)[0]
                k = crossed[rows].argmax(axis=1)
                sb = s[rows, k]
                sa = np.where(k > 0, s[rows, np.maximum(k - 1, 0)], s_prev[rows])
                sh = _bisect(dsm, oa[rows], da[rows], sa, sb, tol)
                idx = active[rows]
                dist[idx] = sh
                pts[idx] = o[idx] + sh[:, None] * d[idx]
                status[idx] = HIT
            done = any_c | (s[:, -1] >= s1[active] - 1e-9)
            s_prev = s[:, -1][~done]
            active = active[~done]
    return RayHits(pts, dist, status)


SKIP_BLOCK = 8  # cells per side of the free-space skipping blocks


def _block_max(dsm):
    """(max height over each SKIP_BLOCK x SKIP_BLOCK block, dilated by one block; -inf = empty),
    cached on the DSM object."""
    cached = getattr(dsm, "_gtkit_track_blockmax", None)
    if cached is not None:
        return cached
    from scipy.ndimage import maximum_filter

    B = SKIP_BLOCK
    h = np.where(np.isfinite(dsm.heights), dsm.heights, -np.inf)
    H, W = h.shape
    hp = np.full((-(-H // B) * B, -(-W // B) * B), -np.inf)
    hp[:H, :W] = h
    m = hp.reshape(hp.shape[0] // B, B, hp.shape[1] // B, B).max(axis=(1, 3))
    m = maximum_filter(m, size=3, mode="constant", cval=-np.inf)
    dsm._gtkit_track_blockmax = m
    return m


def _coarse_start(dsm, o, d, s0, s1, K: int = 32):
    """Per ray, the s from which the fine march must run: the start of the first segment that is
    not provably above the surface. A segment from s_k to s_k + (B-1)*res moves less than one
    block (B cells) horizontally, so every height sampled under it (bilinear, from cells within
    one cell of the point) is bounded by the block max at s_k dilated by one block; if the ray
    stays above that bound the segment cannot cross the surface."""
    g = dsm.grid
    M = _block_max(dsm)
    blen = SKIP_BLOCK * g.res
    seg = (SKIP_BLOCK - 1) * g.res
    nbi, nbj = M.shape
    start = s0.copy()
    cur = s0.copy()
    todo = np.arange(len(o))
    ks = np.arange(0, K + 1, dtype=np.float64)
    while len(todo):
        sk = np.minimum(cur[todo, None] + seg * ks[None, :], s1[todo, None])  # (m, K+1)
        P = o[todo, None, :] + sk[..., None] * d[todo, None, :]
        bi = np.floor((g.ymax - P[..., 1]) / blen).astype(np.int64)
        bj = np.floor((P[..., 0] - g.xmin) / blen).astype(np.int64)
        inside = (bi >= 0) & (bi < nbi) & (bj >= 0) & (bj < nbj)
        m = np.where(inside, M[np.clip(bi, 0, nbi - 1), np.clip(bj, 0, nbj - 1)], -np.inf)
        z = P[..., 2]
        safe = np.minimum(z[:, :-1], z[:, 1:]) > m[:, :-1]
        unsafe = ~safe.all(axis=1)
        first = np.where(unsafe, (~safe).argmax(axis=1), K)
        start[todo] = sk[np.arange(len(todo)), first]
        cont = ~unsafe & (sk[:, -1] < s1[todo] - 1e-9)
        cur[todo[cont]] = sk[cont, -1]
        todo = todo[cont]
    return start


def _f(dsm, o, d, s):
    p = o + s[:, None] * d
    return p[:, 2] - dsm.height_at(p[:, 0], p[:, 1])


def _bisect(dsm, o, d, sa, sb, tol):
    """Shrink [sa, sb] (f(sa) > 0 or no data, f(sb) <= 0) to ``tol``; returns the crossing s."""
    sa, sb = sa.copy(), sb.copy()
    n_iter = int(np.ceil(np.log2(max((sb - sa).max(), tol) / tol))) + 1
    for _ in range(n_iter):
        sm = 0.5 * (sa + sb)
        fm = _f(dsm, o, d, sm)
        below = np.isfinite(fm) & (fm <= 0)
        sb = np.where(below, sm, sb)
        sa = np.where(below, sa, sm)
    return 0.5 * (sa + sb)
