"""The true scene of a sample site: terrain, lake, roads, buildings, trees and GCP targets.

Everything is in the project's world frame (metres, x east, y north, z up) around the site
centre. The mesh carries a material id per vertex (``MAT_*``) and a pattern uv (metres along a
wall / roof, or a GCP target's local coordinates); :mod:`gtkit.synth.shading` turns material,
world position and uv into colour, so detail exists at every scale.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.mesh import Mesh, MeshPart
from .settings import SynthSettings

MAT_TERRAIN, MAT_WALL, MAT_FLAT_ROOF, MAT_TILE_ROOF, MAT_TREE, MAT_GCP = 0, 1, 2, 3, 4, 5


@dataclass
class Building:
    cx: float
    cy: float
    w: float          # along the building's x axis
    d: float          # along its y axis
    angle: float      # radians, counter-clockwise from east
    base: float       # z of the wall bottom (a little below the terrain)
    height: float     # wall height above the highest terrain point of the footprint
    roof: str         # "flat" | "gabled"
    color: tuple      # facade base colour (0..1)

    def corners(self) -> np.ndarray:
        c, s = np.cos(self.angle), np.sin(self.angle)
        loc = np.array([[-self.w, -self.d], [self.w, -self.d], [self.w, self.d], [-self.w, self.d]]) / 2
        return loc @ np.array([[c, s], [-s, c]]) + [self.cx, self.cy]


@dataclass
class World:
    size: float
    base_height: float
    relief: float
    phases: np.ndarray                       # terrain relief phases
    lake: tuple | None                       # (cx, cy, rx, ry, level)
    town_x0: float                           # town = x > town_x0
    roads: list = field(default_factory=list)      # (x0, y0, x1, y1, half_width)
    buildings: list = field(default_factory=list)  # Building
    trees: np.ndarray = None                 # (N, 6): cx, cy, cz, rx, ry, rz (canopy ellipsoid)
    gcps: np.ndarray = None                  # (N, 3) target centres
    gcp_size: float = 1.6

    # --- terrain --------------------------------------------------------------------
    def terrain_height(self, x, y) -> np.ndarray:
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        p, S = self.phases, self.size
        z = (0.5 * np.sin(2 * np.pi * x / (1.3 * S) + p[0]) * np.cos(2 * np.pi * y / (1.1 * S) + p[1])
             + 0.3 * np.sin(2 * np.pi * (x + 0.7 * y) / (0.6 * S) + p[2])
             + 0.2 * np.sin(2 * np.pi * (0.4 * x - y) / (0.35 * S) + p[3]))
        z = self.base_height + self.relief * z
        if self.lake is not None:
            cx, cy, rx, ry, level = self.lake
            r = np.sqrt(((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2)
            w = np.clip((1.25 - r) / 0.25, 0.0, 1.0)
            z = z * (1 - w) + level * w
        return z

    def obstacle_top(self, x: float, y: float, radius: float) -> float:
        """Highest building or tree top within ``radius`` horizontally of (x, y); -inf if none."""
        top = -np.inf
        for b in self.buildings:
            c, s = np.cos(b.angle), np.sin(b.angle)
            lx, ly = c * (x - b.cx) + s * (y - b.cy), -s * (x - b.cx) + c * (y - b.cy)
            if np.hypot(max(abs(lx) - b.w / 2, 0.0), max(abs(ly) - b.d / 2, 0.0)) <= radius:
                top = max(top, max(float(v[:, 2].max()) for v, _uv, _m in building_faces(b)))
        if self.trees is not None and len(self.trees):
            t = self.trees
            near = np.hypot(t[:, 0] - x, t[:, 1] - y) - np.maximum(t[:, 3], t[:, 4]) <= radius
            if near.any():
                top = max(top, float((t[near, 2] + t[near, 5]).max()))
        return top

    def in_lake(self, x, y, margin: float = 1.0) -> np.ndarray:
        if self.lake is None:
            return np.zeros(np.shape(x), bool)
        cx, cy, rx, ry, _ = self.lake
        return ((np.asarray(x) - cx) / (rx * margin)) ** 2 + ((np.asarray(y) - cy) / (ry * margin)) ** 2 < 1.0

    def road_distance(self, x, y) -> np.ndarray:
        """Distance to the nearest road edge (negative on a road)."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        best = np.full(np.broadcast(x, y).shape, np.inf)
        for x0, y0, x1, y1, hw in self.roads:
            d = np.array([x1 - x0, y1 - y0])
            L2 = d @ d
            t = np.clip(((x - x0) * d[0] + (y - y0) * d[1]) / L2, 0, 1)
            dist = np.hypot(x - (x0 + t * d[0]), y - (y0 + t * d[1])) - hw
            best = np.minimum(best, dist)
        return best

    def to_json(self) -> dict:
        return {"size": self.size, "base_height": self.base_height, "relief": self.relief,
                "terrain_phases": self.phases.tolist(), "lake": list(self.lake) if self.lake else None,
                "town_x0": self.town_x0, "roads": [list(r) for r in self.roads],
                "buildings": [{"cx": b.cx, "cy": b.cy, "w": b.w, "d": b.d, "angle": b.angle, "base": b.base,
                               "height": b.height, "roof": b.roof, "color": list(b.color)} for b in self.buildings],
                "trees_cx_cy_cz_rx_ry_rz": np.round(self.trees, 4).tolist(),
                "gcps": np.round(self.gcps, 4).tolist(), "gcp_size": self.gcp_size}


# --- layout ------------------------------------------------------------------------------


def build_world(s: SynthSettings, rng: np.random.Generator) -> World:
    S = s.site.size_m
    ws = s.world
    half = S / 2
    lake = None
    if ws.lake:
        lake = (-0.17 * S, -0.27 * S, 0.13 * S, 0.085 * S, s.site.base_height - s.site.relief_m - 0.8)
    world = World(S, s.site.base_height, s.site.relief_m, rng.uniform(0, 2 * np.pi, 4), lake,
                  town_x0=half - ws.town_share * S, gcp_size=ws.gcp_size_m)
    # roads: a main east-west road across the site, a town grid, a north-south road in the west
    y_main = 0.06 * S
    world.roads.append((-half, y_main, half, y_main, 4.5))
    xs = np.arange(world.town_x0, half - 0.25 * ws.block_m, ws.block_m)
    ys = np.concatenate([np.arange(y_main, -half + 0.2 * ws.block_m, -ws.block_m)[1:][::-1],
                         np.arange(y_main, half - 0.2 * ws.block_m, ws.block_m)])
    for x in xs:
        world.roads.append((x, -half, x, half, 3.5))
    for y in ys:
        if abs(y - y_main) > 1:
            world.roads.append((world.town_x0, y, half, y, 3.5))
    world.roads.append((-0.32 * S, y_main, -0.32 * S, half, 3.0))
    # buildings: a few per town block
    xe = np.concatenate([xs, [half]])
    ye = np.concatenate([[-half], ys, [half]])
    for i in range(len(xe) - 1):
        for j in range(len(ye) - 1):
            x0, x1, y0, y1 = xe[i] + 7, xe[i + 1] - 7, ye[j] + 7, ye[j + 1] - 7
            if x1 - x0 < 10 or y1 - y0 < 10:
                continue
            along_x = (x1 - x0) >= (y1 - y0)
            n_lots = int(rng.integers(1, 4))
            L = (x1 - x0) if along_x else (y1 - y0)
            for k in range(n_lots):
                a0 = (x0 if along_x else y0) + k * L / n_lots
                a1 = a0 + L / n_lots
                if along_x:
                    lx0, lx1, ly0, ly1 = a0 + 1.5, a1 - 1.5, y0, y1
                else:
                    lx0, lx1, ly0, ly1 = x0, x1, a0 + 1.5, a1 - 1.5
                _add_building(world, rng, ws, lx0, lx1, ly0, ly1)
    # at least one tower near the tallest allowed height, nearest the town centre
    town = [b for b in world.buildings if b.cx > world.town_x0]
    if town and max(b.height for b in town) < 0.8 * ws.building_height_max:
        tc = np.array([(world.town_x0 + half) / 2, y_main])
        b = min(town, key=lambda b: (np.hypot(b.cx - tc[0], b.cy - tc[1]), b.cx))
        b.w, b.d, b.roof = min(b.w, 26.0), min(b.d, 26.0), "flat"
        zt = world.terrain_height(b.corners()[:, 0], b.corners()[:, 1])
        b.base = float(zt.min() - 0.5)
        b.height = float(zt.max() - b.base + rng.uniform(0.85, 1.0) * ws.building_height_max)
    # farm houses in the rural part
    for _ in range(ws.n_farm_houses * 20):
        if sum(b.roof == "gabled" and b.cx < world.town_x0 for b in world.buildings) >= ws.n_farm_houses:
            break
        cx, cy = rng.uniform(-half + 15, world.town_x0 - 15), rng.uniform(-half + 15, half - 15)
        if world.in_lake(cx, cy, 1.5) or world.road_distance(cx, cy) < 8:
            continue
        w, d = rng.uniform(8, 14), rng.uniform(6, 9)
        _place(world, rng, cx, cy, w, d, rng.uniform(0, np.pi), rng.uniform(4, 7), "gabled",
               color=(0.78, 0.72, 0.62))
    world.trees = _place_trees(world, rng, ws)
    world.gcps = _place_gcps(world, rng, ws.n_gcps)
    return world


def _add_building(world, rng, ws, x0, x1, y0, y1):
    if x1 - x0 < 8 or y1 - y0 < 8:
        return
    w = rng.uniform(0.55, 0.9) * (x1 - x0)
    d = rng.uniform(0.55, 0.9) * (y1 - y0)
    cx = rng.uniform(x0 + w / 2, x1 - w / 2)
    cy = rng.uniform(y0 + d / 2, y1 - d / 2)
    if world.in_lake(cx, cy, 1.6):
        return
    if rng.random() < ws.tower_share:
        h = rng.uniform(max(25.0, ws.building_height_min), ws.building_height_max)
        w, d = min(w, 24.0), min(d, 24.0)
    else:
        h = ws.building_height_min + rng.gamma(2.0, 4.0)
        h = min(h, 24.0)
    roof = "gabled" if h < 15 and rng.random() < ws.gabled_share else "flat"
    hue = rng.uniform(0, 1)
    base = np.array([0.75, 0.72, 0.68]) + 0.15 * np.array([np.cos(6.28 * hue), np.cos(6.28 * hue + 2),
                                                           np.cos(6.28 * hue + 4)])
    _place(world, rng, cx, cy, w, d, rng.normal(0, 0.05), h, roof, tuple(np.clip(base, 0.3, 0.95)))


def _place(world, rng, cx, cy, w, d, angle, h, roof, color):
    b = Building(float(cx), float(cy), float(w), float(d), float(angle), 0.0, float(h), roof,
                 tuple(float(c) for c in color))
    cs = b.corners()
    # keep off other buildings
    for o in world.buildings:
        if np.hypot(o.cx - b.cx, o.cy - b.cy) < 0.5 * (np.hypot(o.w, o.d) + np.hypot(b.w, b.d)) + 2:
            return
    if np.any(world.road_distance(cs[:, 0], cs[:, 1]) < 1.5):
        return
    zt = world.terrain_height(cs[:, 0], cs[:, 1])
    b.base = float(zt.min() - 0.5)
    b.height = float(zt.max() - b.base + h)
    world.buildings.append(b)


def _place_trees(world, rng, ws) -> np.ndarray:
    half = world.size / 2
    rural_area = (world.town_x0 + half) * world.size
    n = int(ws.tree_density * rural_area)
    pts = []
    # forest clumps and scattered trees in the rural part
    centres = rng.uniform([-half, -half], [world.town_x0, half], size=(max(1, n // 25), 2))
    for _ in range(n * 4):
        if len(pts) >= n:
            break
        if rng.random() < 0.7:
            c = centres[rng.integers(len(centres))]
            x, y = c + rng.normal(0, 12, 2)
        else:
            x, y = rng.uniform([-half, -half], [world.town_x0, half])
        pts.append((x, y))
    # street trees along town roads
    for x0, y0, x1, y1, hw in world.roads:
        L = np.hypot(x1 - x0, y1 - y0)
        for t in np.arange(6, L - 6, 14.0):
            if rng.random() < 0.5:
                continue
            dx, dy = (x1 - x0) / L, (y1 - y0) / L
            side = rng.choice([-1, 1])
            pts.append((x0 + t * dx - side * dy * (hw + 2.2), y0 + t * dy + side * dx * (hw + 2.2)))
    pts = np.array(pts, float).reshape(-1, 2)
    keep = (np.abs(pts) < half - 3).all(1) & ~world.in_lake(pts[:, 0], pts[:, 1], 1.15)
    keep &= world.road_distance(pts[:, 0], pts[:, 1]) > 1.0
    for b in world.buildings:
        keep &= np.hypot(pts[:, 0] - b.cx, pts[:, 1] - b.cy) > 0.5 * np.hypot(b.w, b.d) + 3
    pts = pts[keep]
    r = rng.uniform(1.8, 3.8, len(pts))
    rz = r * rng.uniform(0.9, 1.4, len(pts))
    z = world.terrain_height(pts[:, 0], pts[:, 1]) + rz + rng.uniform(1.5, 3.0, len(pts))
    return np.column_stack([pts, z, r * rng.uniform(0.85, 1.15, len(pts)), r, rz])


def _place_gcps(world, rng, n) -> np.ndarray:
    """Open-ground spots spread over the inner site (farthest-point sampling of valid spots)."""
    half = world.size / 2
    g = np.linspace(-0.55 * half, 0.55 * half, 23)
    X, Y = (a.ravel() for a in np.meshgrid(g, g))
    X = X + rng.uniform(-2, 2, len(X))
    Y = Y + rng.uniform(-2, 2, len(Y))
    ok = ~world.in_lake(X, Y, 1.4) & (world.road_distance(X, Y) > 0.8)
    for b in world.buildings:
        ok &= np.hypot(X - b.cx, Y - b.cy) > 0.5 * np.hypot(b.w, b.d) + 5
    if len(world.trees):
        d = np.hypot(X[:, None] - world.trees[None, :, 0], Y[:, None] - world.trees[None, :, 1]) - world.trees[None, :, 3]
        ok &= d.min(1) > 4
    P = np.column_stack([X, Y])[ok]
    if not len(P) or n <= 0:
        return np.zeros((0, 3))
    chosen = [int(np.argmin(np.hypot(P[:, 0], P[:, 1])))]
    while len(chosen) < min(n, len(P)):
        d = np.min(np.hypot(P[:, None, 0] - P[None, chosen, 0], P[:, None, 1] - P[None, chosen, 1]), axis=1)
        chosen.append(int(np.argmax(d)))
    P = P[chosen]
    return np.column_stack([P, world.terrain_height(P[:, 0], P[:, 1]) + 0.1])


# --- meshes ------------------------------------------------------------------------------


def terrain_grid(world: World, spacing: float):
    half = world.size / 2
    n = int(round(world.size / spacing)) + 1
    g = np.linspace(-half, half, n)
    X, Y = np.meshgrid(g, g)
    Z = world.terrain_height(X, Y)
    V = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return V, F


def surroundings_grid(world: World, extent: float = 3.0, cells: int = 60):
    n = cells + 1
    g = np.linspace(-extent * world.size / 2, extent * world.size / 2, n)
    X, Y = np.meshgrid(g, g)
    inner = (np.abs(X) < world.size / 2 - 1e-6) & (np.abs(Y) < world.size / 2 - 1e-6)
    Z = world.terrain_height(X, Y) - 0.3 - 8.0 * inner   # well below the site's own terrain
    V = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return V, np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])


def building_faces(b: Building) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Planar polygons of a building: (vertices (k, 3), pattern uv (k, 2), material)."""
    cs = b.corners()
    top = b.base + b.height
    polys = []
    ridge_h = 0.35 * min(b.w, b.d) if b.roof == "gabled" else 0.0
    ridge_along_x = b.w >= b.d
    for k in range(4):
        p0, p1 = cs[k], cs[(k + 1) % 4]
        L = float(np.hypot(*(p1 - p0)))
        v = np.array([[*p0, b.base], [*p1, b.base], [*p1, top], [*p0, top]])
        uv = np.array([[0, 0], [L, 0], [L, b.height], [0, b.height]])
        # gable end: walls perpendicular to the ridge get a triangle on top
        gable_end = b.roof == "gabled" and ((k % 2 == 1) == ridge_along_x)
        if gable_end:
            mid = (p0 + p1) / 2
            v = np.vstack([v[:3], [*mid, top + ridge_h], v[3]])
            uv = np.vstack([uv[:3], [L / 2, b.height + ridge_h], uv[3]])
        polys.append((v, uv, MAT_WALL))
    if b.roof == "flat":
        v = np.column_stack([cs, np.full(4, top)])
        c, s = np.cos(b.angle), np.sin(b.angle)
        loc = (cs - [b.cx, b.cy]) @ np.array([[c, -s], [s, c]])
        polys.append((v, loc, MAT_FLAT_ROOF))
    else:
        # ridge between the midpoints of the two gable-end walls
        if ridge_along_x:
            r0, r1 = (cs[0] + cs[3]) / 2, (cs[1] + cs[2]) / 2
            sides = [(0, 1), (2, 3)]
            span = b.d / 2
        else:
            r0, r1 = (cs[0] + cs[1]) / 2, (cs[3] + cs[2]) / 2
            sides = [(1, 2), (3, 0)]
            span = b.w / 2
        slope = float(np.hypot(span, ridge_h))
        for i0, i1 in sides:
            a, bb = cs[i0], cs[i1]
            ra, rb = (r0, r1) if np.linalg.norm(a - r0) < np.linalg.norm(a - r1) else (r1, r0)
            L = float(np.hypot(*(bb - a)))
            v = np.array([[*a, top], [*bb, top], [*rb, top + ridge_h], [*ra, top + ridge_h]])
            uv = np.array([[0, 0], [L, 0], [L, slope], [0, slope]])
            polys.append((v, uv, MAT_TILE_ROOF))
    return polys


def _icosphere(subdiv: int):
    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    V = list(V / np.linalg.norm(V, axis=1, keepdims=True))
    for _ in range(subdiv):
        cache, newF = {}, []

        def mid(i, j):
            k = (min(i, j), max(i, j))
            if k not in cache:
                m = V[i] + V[j]
                V.append(m / np.linalg.norm(m))
                cache[k] = len(V) - 1
            return cache[k]
        for a, b, c in F:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            newF += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        F = np.array(newF)
    return np.array(V), np.asarray(F)


def tree_meshes(trees: np.ndarray, subdiv: int, rng: np.random.Generator | None = None, bumpy: float = 0.15):
    """Canopies as lumpy ellipsoids: (vertices, faces)."""
    V0, F0 = _icosphere(subdiv)
    Vs, Fs = [], []
    for k, (cx, cy, cz, rx, ry, rz) in enumerate(trees):
        bump = 1.0 + (rng.uniform(-bumpy, bumpy, len(V0)) if rng is not None else np.zeros(len(V0)))
        v = V0 * bump[:, None] * [rx, ry, rz] + [cx, cy, cz]
        Vs.append(v)
        Fs.append(F0 + k * len(V0))
    if not Vs:
        return np.zeros((0, 3)), np.zeros((0, 3), int)
    return np.concatenate(Vs), np.concatenate(Fs)


def gcp_quads(world: World):
    """Each GCP target: a flat square, uv = local metres from its centre."""
    h = world.gcp_size / 2
    Vs, UVs, Fs = [], [], []
    for k, (x, y, z) in enumerate(world.gcps):
        loc = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        Vs.append(np.column_stack([loc + [x, y], np.full(4, z)]))
        UVs.append(loc)
        Fs.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k)
    if not Vs:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 3), int)
    return np.concatenate(Vs), np.concatenate(UVs), np.concatenate(Fs)


def _triangulate_polys(polys):
    Vs, UVs, Ms, Fs, Cs = [], [], [], [], []
    off = 0
    for v, uv, mat, col in polys:
        k = len(v)
        Vs.append(v)
        UVs.append(uv)
        Ms.append(np.full(k, mat, np.float32))
        Cs.append(np.tile(np.asarray(col) * 255, (k, 1)))
        Fs.append(np.array([[0, i, i + 1] for i in range(1, k - 1)]) + off)
        off += k
    return (np.concatenate(Vs), np.concatenate(UVs), np.concatenate(Ms), np.concatenate(Fs),
            np.concatenate(Cs).round().astype(np.uint8))


def building_polys(world: World):
    return [(v, uv, m, b.color) for b in world.buildings for v, uv, m in building_faces(b)]


def true_mesh(world: World, s: SynthSettings, rng: np.random.Generator) -> Mesh:
    """The true world as one procedurally shaded mesh (terrain, buildings, trees, GCPs)."""
    parts = []
    V, F = terrain_grid(world, s.site.terrain_spacing_m)
    parts.append(MeshPart(V, F, uv=V[:, :2].copy(), colors=np.full((len(V), 3), 128, np.uint8),
                          material=np.full(len(V), MAT_TERRAIN, np.float32), name="terrain"))
    # surroundings: coarse land around the site (0.3 m lower, hidden under the site's terrain),
    # so oblique and low-pitch photos see ground instead of a void beyond the site edge
    V, F = surroundings_grid(world)
    parts.append(MeshPart(V, F, uv=V[:, :2].copy(), colors=np.full((len(V), 3), 128, np.uint8),
                          material=np.full(len(V), MAT_TERRAIN, np.float32), name="surroundings"))
    if world.buildings:
        V, UV, M, F, C = _triangulate_polys(building_polys(world))
        parts.append(MeshPart(V, F, uv=UV, colors=C, material=M, name="buildings"))
    if len(world.trees):
        V, F = tree_meshes(world.trees, 2, rng)
        parts.append(MeshPart(V, F, uv=V[:, :2].copy(), colors=np.full((len(V), 3), 128, np.uint8),
                              material=np.full(len(V), MAT_TREE, np.float32), name="trees"))
    if len(world.gcps):
        V, UV, F = gcp_quads(world)
        parts.append(MeshPart(V, F, uv=UV, colors=np.full((len(V), 3), 128, np.uint8),
                              material=np.full(len(V), MAT_GCP, np.float32), name="gcps"))
    return Mesh(parts)
