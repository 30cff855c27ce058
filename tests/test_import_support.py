"""Small synthetic textured models and poses for the import tests (no sample site needed)."""
from __future__ import annotations

import numpy as np

from gtkit.io.mesh import Mesh, MeshPart
from gtkit.pose import Pose

FRAME_CRS = "EPSG:32650"
FRAME_ORIGIN = (500000.0, 4000000.0, 0.0)


def noise_texture(px: int, seed: int) -> np.ndarray:
    """Multi-scale value noise (structure at every mip level), RGB uint8."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((px, px, 3), np.float32)
    for cells, w in ((4, 0.4), (16, 0.3), (64, 0.2), (px, 0.1)):
        small = rng.random((cells, cells, 3)).astype(np.float32)
        img += w * cv2.resize(small, (px, px), interpolation=cv2.INTER_LINEAR)
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def terrain_part(x0, y0, size, n, tex_px=512, seed=0, amp=4.0) -> MeshPart:
    """A height-field grid of n x n cells over [x0, x0+size]^2, planar uv, noise texture."""
    xs = np.linspace(x0, x0 + size, n + 1)
    ys = np.linspace(y0, y0 + size, n + 1)
    X, Y = np.meshgrid(xs, ys)
    Z = amp * np.sin(X / 23.0) * np.cos(Y / 31.0) + 0.02 * (X - x0)
    v = np.stack([X, Y, Z], -1).reshape(-1, 3)
    uv = np.stack([(X - x0) / size, (Y - y0) / size], -1).reshape(-1, 2)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return MeshPart(v, f, uv=uv, texture=noise_texture(tex_px, seed), name=f"terrain_{seed}")


def box_part(lo, hi, color, name="box") -> MeshPart:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return MeshPart(v, f, colors=np.tile(np.asarray(color, np.uint8), (8, 1)), name=name)


def small_site() -> Mesh:
    """200 m x 200 m terrain (one texture) with three coloured boxes, world frame centred at 0."""
    parts = [terrain_part(-100.0, -100.0, 200.0, 48, tex_px=512, seed=1)]
    parts.append(box_part([-30.3, -20.1, -1.0], [-10.2, 5.7, 18.0], (200, 60, 40), "box_a"))
    parts.append(box_part([12.0, 21.5, -1.0], [38.8, 30.9, 9.5], (40, 90, 210), "box_b"))
    parts.append(box_part([45.0, -60.0, -1.0], [52.0, -35.0, 25.0], (230, 220, 70), "box_c"))
    return Mesh(parts)


def grid_site(n_tiles_side: int = 10, tile_m: float = 50.0, cells: int = 12, tex_px: int = 256) -> Mesh:
    """A terrain made of n x n textured patches (each its own texture, like a photogrammetry
    delivery), for tiling benchmarks."""
    parts = []
    half = n_tiles_side * tile_m / 2
    for i in range(n_tiles_side):
        for j in range(n_tiles_side):
            parts.append(terrain_part(-half + i * tile_m, -half + j * tile_m, tile_m, cells, tex_px,
                                      seed=i * n_tiles_side + j))
    return Mesh(parts)


def oblique_poses(n: int = 6, seed: int = 3, height=(60.0, 120.0)) -> list[Pose]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        C = np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(*height)])
        out.append(Pose.from_dji(rng.uniform(-180, 180), rng.uniform(-90, -35), rng.uniform(-5, 5), C))
    return out
