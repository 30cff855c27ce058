"""Ray marching against a height grid (DSM) to the FIRST surface crossing.

A DSM is a 2.5D surface z = h(x, y). A ray ``p(s) = o + s d`` (``d`` unit, ``s`` in metres)
is above the surface while ``f(s) = p_z(s) - h(p_x(s), p_y(s)) > 0``. We march ``s`` from the
ray's entry into the DSM's box in steps of at most half a cell, take the FIRST step where ``f``
changes from > 0 to <= 0, and refine only inside that bracketing step by bisection down to
``tol`` metres along the ray. A plain bisection over the whole ray could converge to any
crossing (e.g. the ground behind a building); marching first cannot.

Heights are sampled bilinearly between cell centres; cells with no data (NaN) count as "no
surface" (the ray may pass over them). Every ray gets a status:

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


@dataclass
class HeightGrid:
    """Heights on a regular north-up grid in the world frame (see :mod:`gtkit.conventions`).

    ``heights[i, j]`` is the height at the centre of the cell covering
    x in [x0 + j*dx, x0 + (j+1)*dx], y in [y0 - (i+1)*dy, y0 - i*dy] (row 0 = north edge,
    as in a GeoTIFF). NaN = no data.
    """

    heights: np.ndarray   # (H, W) float
    x0: float             # west edge (world x)
    y0: float             # north edge (world y)
    dx: float             # cell size east (m)
    dy: float             # cell size north (m), positive

    def __post_init__(self):
        self.heights = np.asarray(self.heights, dtype=np.float64)
        if self.heights.ndim != 2 or min(self.heights.shape) < 2:
            raise GtkitError(f"height grid must be 2D with at least 2x2 cells, got {self.heights.shape}")
        if not (self.dx > 0 and self.dy > 0):
            raise GtkitError(f"height grid cell size must be positive, got {self.dx}, {self.dy}")
        valid = np.isfinite(self.heights)
        if not valid.any():
            raise GtkitError("height grid has no valid cell")
        self.hmin = float(self.heights[valid].min())
        self.hmax = float(self.heights[valid].max())

    @classmethod
    def from_affine(cls, heights, transform, origin=(0.0, 0.0, 0.0), nodata=None) -> "HeightGrid":
        """From a rasterio-style affine (a, b, c, d, e, f) in CRS coordinates; ``origin`` is the
        project's local origin (subtracted from x, y and the heights). Rotated grids are refused."""
        a, b, c, d, e, f = (float(v) for v in tuple(transform)[:6])
        if abs(b) > 1e-12 or abs(d) > 1e-12 or e >= 0:
            raise GtkitError("only north-up rasters (no rotation, row 0 = north) are supported")
        h = np.asarray(heights, dtype=np.float64).copy()
        if nodata is not None and np.isfinite(nodata):
            h[h == nodata] = np.nan
        ox, oy, oz = (float(v) for v in origin)
        return cls(h - oz, c - ox, f - oy, a, -e)

    @property
    def shape(self):
        return self.heights.shape

    @property
    def cell(self) -> float:
        return min(self.dx, self.dy)

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the cell centres (where bilinear sampling is defined)."""
        H, W = self.heights.shape
        return (self.x0 + 0.5 * self.dx, self.y0 - (H - 0.5) * self.dy,
                self.x0 + (W - 0.5) * self.dx, self.y0 - 0.5 * self.dy)

    def sample(self, x, y) -> np.ndarray:
        """Bilinear height at world (x, y); NaN outside the grid of cell centres or where all four
        neighbours have no data (neighbours without data are left out of the weights)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        H, W = self.heights.shape
        fc = (x - self.x0) / self.dx - 0.5   # continuous column (0 = first cell centre)
        fr = (self.y0 - y) / self.dy - 0.5   # continuous row
        inside = (fc >= 0) & (fc <= W - 1) & (fr >= 0) & (fr <= H - 1)
        fc = np.clip(np.where(inside, fc, 0.0), 0, W - 1)
        fr = np.clip(np.where(inside, fr, 0.0), 0, H - 1)
        c0 = np.minimum(np.floor(fc).astype(np.int64), W - 2)
        r0 = np.minimum(np.floor(fr).astype(np.int64), H - 2)
        tc, tr = fc - c0, fr - r0
        hz = self.heights
        acc = np.zeros(x.shape)
        wsum = np.zeros(x.shape)
        for dr, dc, w in ((0, 0, (1 - tr) * (1 - tc)), (0, 1, (1 - tr) * tc),
                          (1, 0, tr * (1 - tc)), (1, 1, tr * tc)):
            v = hz[r0 + dr, c0 + dc]
            ok = np.isfinite(v)
            acc += np.where(ok, v * w, 0.0)
            wsum += np.where(ok, w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where((wsum <= 1e-12) | ~inside, np.nan, acc / wsum)
        return out if out.ndim else float(out)


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


def cast_rays(grid: HeightGrid, origins, directions, *, step: float | None = None, tol: float = 0.01,
              max_distance: float = 20000.0, block: int = 64, chunk: int = 8192) -> RayHits:
    """First crossing of each ray with the height grid.

    ``step`` (metres along the ray) defaults to half the smaller cell size and is capped at it;
    ``tol`` is the bisection tolerance along the ray (default 1 cm). Rays are processed
    ``chunk`` at a time, ``block`` steps per vectorised pass.
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
    parts = [_cast_chunk(grid, o[i:i + chunk], d[i:i + chunk], step, tol, max_distance, block)
             for i in range(0, len(o), chunk)] or [_cast_chunk(grid, o, d, step, tol, max_distance, block)]
    return RayHits(np.concatenate([p.points for p in parts]), np.concatenate([p.distance for p in parts]),
                   np.concatenate([p.status for p in parts]))


def _cast_chunk(grid, o, d, step, tol, max_distance, block) -> RayHits:
    n = len(o)
    half = 0.5 * grid.cell
    step = half if step is None else min(float(step), half)
    pts = np.full((n, 3), np.nan)
    dist = np.full(n, np.nan)
    status = np.full(n, OUTSIDE, dtype=object)

    xmin, ymin, xmax, ymax = grid.bounds()
    lo = np.array([xmin, ymin, grid.hmin - 1.0])
    hi = np.array([xmax, ymax, grid.hmax + 1e-6])
    s0, s1 = _box_interval(o, d, lo, hi)
    s1 = np.minimum(s1, max_distance)

    h0 = grid.sample(o[:, 0], o[:, 1])
    below = np.isfinite(h0) & (o[:, 2] < h0)
    status[below] = STARTS_BELOW
    sky = (d[:, 2] >= 0) & (o[:, 2] > grid.hmax) & ~below
    status[sky] = SKY

    active = np.where(~below & ~sky & (s1 > s0))[0]
    if len(active):
        s_prev = s0[active].copy()
        f_prev = _f(grid, o[active], d[active], s_prev)
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
            f = P[..., 2] - grid.sample(P[..., 0], P[..., 1])
            crossed = np.isfinite(f) & (f <= 0)
            any_c = crossed.any(axis=1)
            if any_c.any():
                rows = np.where(any_c)[0]
                k = crossed[rows].argmax(axis=1)
                sb = s[rows, k]
                sa = np.where(k > 0, s[rows, np.maximum(k - 1, 0)], s_prev[rows])
                sh = _bisect(grid, oa[rows], da[rows], sa, sb, tol)
                idx = active[rows]
                dist[idx] = sh
                pts[idx] = o[idx] + sh[:, None] * d[idx]
                status[idx] = HIT
            done = any_c | (s[:, -1] >= s1[active] - 1e-9)
            s_prev = s[:, -1][~done]
            active = active[~done]
    return RayHits(pts, dist, status)


def _f(grid, o, d, s):
    p = o + s[:, None] * d
    return p[:, 2] - grid.sample(p[:, 0], p[:, 1])


def _bisect(grid, o, d, sa, sb, tol):
    """Shrink [sa, sb] (f(sa) > 0 or no data, f(sb) <= 0) to ``tol``; returns the crossing s."""
    sa, sb = sa.copy(), sb.copy()
    n_iter = int(np.ceil(np.log2(max((sb - sa).max(), tol) / tol))) + 1
    for _ in range(n_iter):
        sm = 0.5 * (sa + sb)
        fm = _f(grid, o, d, sm)
        below = np.isfinite(fm) & (fm <= 0)
        sb = np.where(below, sm, sb)
        sa = np.where(below, sa, sm)
    return 0.5 * (sa + sb)
