"""The surface: screened Poisson reconstruction of the fused points (Open3D), trimmed to where the
points support it, simplified to a triangle budget (pymeshlab quadric edge collapse).

Poisson keeps vertical facades (the oblique photos put points on them, with normals turned toward
the cameras that saw them) and closes small gaps; it also invents surface far from any point (a
closed bubble), which the trimming removes: every triangle with a vertex farther than ``trim_m``
from the nearest fused point goes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .settings import ModelSettings


def estimate_normals(xyz: np.ndarray, toward: np.ndarray, voxel: float) -> np.ndarray:
    """Unit normals from the neighbourhood (PCA), flipped to face ``toward`` (unit vectors to the cameras)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=24))
    n = np.asarray(pc.normals)
    flip = np.einsum("ij,ij->i", n, toward) < 0
    n[flip] *= -1
    return n


def poisson(xyz: np.ndarray, normals: np.ndarray, settings: ModelSettings) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the Poisson surface, trimmed to the points' support."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pc.normals = o3d.utility.Vector3dVector(normals)
    depth = settings.poisson_depth or poisson_depth_for(xyz, settings.voxel_m)
    # one thread: Open3D's multi-threaded Poisson crashes at random (SIGSEGV inside
    # CreateFromPointCloudPoisson; isl-org/Open3D#6828, mkazhdan/PoissonRecon#298; it killed a
    # resumed `gtkit model build` in CI, stop 28); with one thread it is reported stable
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=depth,
                                                                            linear_fit=True, n_threads=1)
    V = np.asarray(mesh.vertices)
    F = np.asarray(mesh.triangles)
    dist, _ = cKDTree(xyz).query(V, k=1, distance_upper_bound=settings.trim_m * 2)
    bad_v = dist > settings.trim_m
    keep = ~bad_v[F].any(1)
    return _compact(V, F[keep])


def poisson_depth_for(xyz: np.ndarray, voxel: float) -> int:
    """Octree depth whose cells are about two fusion voxels across the cloud's extent (8..12)."""
    extent = float(np.max(xyz.max(0) - xyz.min(0)))
    return int(np.clip(np.ceil(np.log2(extent / (2 * voxel))), 8, 12))


def _compact(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def tile_boxes(xyz: np.ndarray, tile_m: float) -> list[np.ndarray]:
    """(2, 2) min/max x, y of equal tiles covering the points (or their (2, 2+) min/max box), none
    wider than ``tile_m`` (one tile when the points fit in one)."""
    lo, hi = xyz[:, :2].min(0), xyz[:, :2].max(0)
    n = np.maximum(1, np.ceil((hi - lo) / tile_m - 1e-9)).astype(int)
    step = (hi - lo) / n
    boxes = []
    for i in range(n[0]):
        for j in range(n[1]):
            a = lo + step * (i, j)
            b = np.where((i, j) == n - 1, hi, a + step)
            boxes.append(np.stack([a, b]))
    return boxes


class ArrayCloud:
    """A fused cloud held in memory (xyz, unit directions toward the cameras), read like
    :class:`gtkit.model.fusion.FusedCells`."""

    def __init__(self, xyz: np.ndarray, toward: np.ndarray):
        self.xyz, self.toward = xyz, toward

    def __len__(self) -> int:
        return len(self.xyz)

    def bounds(self) -> np.ndarray:
        return np.stack([self.xyz.min(0), self.xyz.max(0)])

    def points(self, box=None, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        if box is None:
            return self.xyz, self.toward
        sel = np.all((self.xyz[:, :2] >= box[0] - margin) & (self.xyz[:, :2] <= box[1] + margin), axis=1)
        return self.xyz[sel], self.toward[sel]


def _points(cloud, box, margin):
    if hasattr(cloud, "points"):
        return cloud.points(box, margin)
    r = cloud.read(box, margin)                      # FusedCells: records from disk
    return r["xyz"].astype(np.float64), r["dir"].astype(np.float64)


def tiled_surface(cloud, settings: ModelSettings, keep_m: float = 1.0, log=None,
                  save: Path | None = None) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(vertices, faces, Poisson triangles before simplification, tiles) of the site's surface,
    reconstructed tile by tile (see the module docstring) from ``cloud`` (:class:`ArrayCloud` or
    the fused cells on disk: only a tile's points are read at a time). With ``save`` each finished
    tile is written there (``tile_<k>.npz``, atomically) and a tile already there is read back, so
    a killed build resumes at the next tile."""
    from ..io.atomic import atomic_path

    lo_hi = cloud.bounds()
    boxes = tile_boxes(lo_hi[:, :2], settings.tile_m)
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        for f in save.glob(".*.tmp*"):
            f.unlink(missing_ok=True)
    Vs, Fs, n_poisson, nv = [], [], 0, 0
    for k, box in enumerate(boxes):
        done = save / f"tile_{k}.npz" if save is not None else None
        if done is not None and done.is_file():
            with np.load(done) as z:
                V, F, npo, npts = z["V"], z["F"].astype(np.int64), int(z["poisson"]), int(z["points"])
            if log is not None and len(boxes) > 1:
                log.info("surface tile %d/%d: read back (%d triangles)", k + 1, len(boxes), len(F))
        else:
            xyz, toward = _points(cloud, None if len(boxes) == 1 else box, settings.tile_overlap_m)
            npts = len(xyz)
            if npts < 100:
                V, F, npo = np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0
            else:
                normals = estimate_normals(xyz, toward, settings.voxel_m)
                del toward
                V, F = poisson(xyz, normals, settings)
                del normals, xyz
                if len(boxes) > 1:
                    c = V[F].mean(1)[:, :2]
                    F = F[np.all((c >= box[0] - keep_m) & (c <= box[1] + keep_m), axis=1)]
                    V, F = _compact(V, F)
                npo = len(F)
                V, F = simplify(V, F, settings.max_triangles)
            if done is not None:
                with atomic_path(done) as tmp:
                    np.savez(tmp, V=V, F=F.astype(np.int32), poisson=npo, points=npts)
            if log is not None and len(boxes) > 1:
                log.info("surface tile %d/%d: %d points, %d triangles", k + 1, len(boxes), npts, len(F))
        if not len(F):
            continue
        n_poisson += npo
        Vs.append(V)
        Fs.append(F + nv)
        nv += len(V)
    if not Fs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0, len(boxes)
    return np.concatenate(Vs), np.concatenate(Fs), n_poisson, len(boxes)


def simplify(V: np.ndarray, F: np.ndarray, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge collapse to at most ``max_triangles`` (boundaries and planarity kept)."""
    import pymeshlab

    if len(F) <= max_triangles:
        return V, F
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=V, face_matrix=F.astype(np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(max_triangles), preserveboundary=True,
                                                boundaryweight=2.0, preservenormal=True, planarquadric=True,
                                                qualitythr=0.3, autoclean=True)
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), np.float64), np.asarray(m.face_matrix(), np.int64)
