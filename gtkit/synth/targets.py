"""Moving ground targets: a car driving a loop around a town block and a person walking in
the rural part. Tracks are exact functions of time; meshes are coloured boxes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.mesh import MeshPart
from .world import World


@dataclass
class Track:
    name: str
    path: np.ndarray        # (K, 2) polyline vertices (closed for the car)
    speed: float
    closed: bool
    size: tuple             # (length, width, height) of the box
    color: tuple            # body colour (0..255)
    z_offset: float = 0.0

    def _xy_heading(self, t: float):
        seg = np.diff(self.path, axis=0)
        L = np.hypot(seg[:, 0], seg[:, 1])
        total = L.sum()
        s = self.speed * t
        if self.closed:
            s = s % total
        else:  # back and forth
            s = s % (2 * total)
            if s > total:
                s = 2 * total - s
                seg, L = -seg[::-1], L[::-1]
                path = self.path[::-1]
            else:
                path = self.path
        path = self.path if self.closed else path
        cum = np.concatenate([[0], np.cumsum(L)])
        i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(L) - 1))
        u = (s - cum[i]) / L[i]
        xy = path[i] + u * seg[i]
        return xy, float(np.arctan2(seg[i][1], seg[i][0]))

    def position(self, t: float, world: World) -> np.ndarray:
        """Centre of the target's footprint on the ground (x, y, terrain z) at time t."""
        xy, _ = self._xy_heading(t)
        return np.array([xy[0], xy[1], float(world.terrain_height(xy[0], xy[1])) + self.z_offset])

    def mesh_at(self, t: float, world: World) -> MeshPart:
        xy, heading = self._xy_heading(t)
        z0 = float(world.terrain_height(xy[0], xy[1])) + self.z_offset
        Lg, W, H = self.size
        c, s = np.cos(heading), np.sin(heading)
        Rm = np.array([[c, -s], [s, c]])
        V, F, C = [], [], []
        # body box + (for the car) a smaller cabin on top
        boxes = [((-Lg / 2, Lg / 2), (-W / 2, W / 2), (0.25 if self.name == "car" else 0.0, H * 0.6 if self.name == "car" else H),
                  self.color)]
        if self.name == "car":
            boxes.append(((-Lg * 0.3, Lg * 0.2), (-W * 0.45, W * 0.45), (H * 0.6, H), (40, 50, 60)))
        else:
            boxes.append(((-0.12, 0.12), (-0.12, 0.12), (H, H + 0.25), (220, 180, 150)))  # head
        for (x0, x1), (y0, y1), (zb, zt), col in boxes:
            corners = np.array([[x, y, z] for z in (zb, zt) for y in (y0, y1) for x in (x0, x1)], float)
            corners[:, :2] = corners[:, :2] @ Rm.T + xy
            corners[:, 2] += z0
            quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
            for k, q in enumerate(quads):
                base = len(V)
                V.extend(corners[list(q)])
                shade = 1.0 if k == 1 else (0.75 if k in (2, 3) else 0.6)
                C.extend([np.array(col) * shade] * 4)
                F += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        return MeshPart(np.array(V), np.array(F), colors=np.clip(np.array(C), 0, 255).astype(np.uint8),
                        name=self.name)


def make_tracks(world: World, speeds: tuple[float, float], rng: np.random.Generator) -> dict[str, Track]:
    """A car looping around the town block nearest the centre (right lane) and a person
    walking back and forth across a field in the west."""
    xs = sorted({r[0] for r in world.roads if r[0] == r[2]} | {world.size / 2})
    ys = sorted({r[1] for r in world.roads if r[1] == r[3]})
    # town block nearest the site centre
    xs_town = [x for x in xs if x >= world.town_x0 - 1]
    best = None
    for i in range(len(xs_town) - 1):
        for j in range(len(ys) - 1):
            c = np.array([(xs_town[i] + xs_town[i + 1]) / 2, (ys[j] + ys[j + 1]) / 2])
            d = np.hypot(*c)
            if best is None or d < best[0]:
                best = (d, xs_town[i], xs_town[i + 1], ys[j], ys[j + 1])
    _, x0, x1, y0, y1 = best
    x1 = min(x1, world.size / 2 - 6)
    lane = 1.6  # drive on the right: a counter-clockwise loop inside the block's roads
    car_path = np.array([[x0 + lane, y0 + lane], [x1 - lane, y0 + lane], [x1 - lane, y1 - lane],
                         [x0 + lane, y1 - lane], [x0 + lane, y0 + lane]])
    half = world.size / 2
    px = world.town_x0 - 0.3 * world.size
    py = 0.06 * world.size + 12
    person_path = np.array([[px - 30, py + 5], [px, py + 25], [px + 25, py + 40]])
    person_path[:, 0] = np.clip(person_path[:, 0], -half + 10, half - 10)
    person_path[:, 1] = np.clip(person_path[:, 1], -half + 10, half - 10)
    return {"car": Track("car", car_path, speeds[0], True, (4.6, 1.9, 1.5), (200, 30, 30)),
            "person": Track("person", person_path, speeds[1], False, (0.45, 0.35, 1.5), (40, 90, 210))}
