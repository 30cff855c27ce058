"""Fusion of the per-photo depth maps into one point cloud.

Every (``fusion_stride``-th) pixel with a depth is lifted to the world and kept only where at least
``min_view_agree`` of its photo's neighbours' depth maps see the same surface there (their depth at
the projected pixel within ``pair_agree`` of the point's depth in that photo: geometric consistency).
Kept points are averaged per voxel (position, colour, the direction to the cameras that saw them,
so normals can be oriented toward the photos).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path
from .views import View


class VoxelAccumulator:
    """Sums per voxel, reduced whenever the buffer grows (bounded memory)."""

    def __init__(self, voxel: float, flush_at: int = 4_000_000):
        self.voxel, self.flush_at = voxel, flush_at
        self.keys = np.zeros(0, np.int64)
        self.data = np.zeros((0, 10), np.float64)   # xyz, rgb, view dir, count
        self._buf: list[tuple[np.ndarray, np.ndarray]] = []
        self._n = 0

    def _key(self, xyz: np.ndarray) -> np.ndarray:
        q = np.floor(xyz / self.voxel).astype(np.int64) + (1 << 20)
        return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]

    def add(self, xyz: np.ndarray, rgb: np.ndarray, view_dir: np.ndarray) -> None:
        d = np.concatenate([xyz, rgb, view_dir, np.ones((len(xyz), 1))], axis=1)
        self._buf.append((self._key(xyz), d))
        self._n += len(xyz)
        if self._n > self.flush_at:
            self._reduce()

    def _reduce(self) -> None:
        if not self._buf:
            return
        keys = np.concatenate([self.keys] + [k for k, _ in self._buf])
        data = np.concatenate([self.data] + [d for _, d in self._buf])
        self._buf, self._n = [], 0
        uk, inv = np.unique(keys, return_inverse=True)
        out = np.zeros((len(uk), data.shape[1]))
        for c in range(data.shape[1]):
            out[:, c] = np.bincount(inv, weights=data[:, c], minlength=len(uk))
        self.keys, self.data = uk, out

    def result(self, min_count: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(xyz, rgb uint8, unit direction toward the cameras, count) per voxel."""
        self._reduce()
        n = self.data[:, 9]
        keep = n >= min_count
        d, n = self.data[keep], n[keep][:, None]
        vd = d[:, 6:9]
        vd = vd / np.maximum(np.linalg.norm(vd, axis=1, keepdims=True), 1e-12)
        return d[:, :3] / n, np.clip(d[:, 3:6] / n + 0.5, 0, 255).astype(np.uint8), vd, n[:, 0]


def lift(view: View, depth: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """World points of the valid pixels (every ``stride``-th) and their (row, col)."""
    ii, jj = np.mgrid[0:view.height:stride, 0:view.width:stride]
    z = depth[ii, jj]
    ok = np.isfinite(z) & (z > 0)
    ii, jj, z = ii[ok], jj[ok], z[ok].astype(np.float64)
    xc = np.stack([(jj - view.K[0, 2]) / view.K[0, 0] * z, (ii - view.K[1, 2]) / view.K[1, 1] * z, z], 1)
    xw = (xc - view.pose.t) @ view.pose.R          # R^T (x - t)
    return xw, np.stack([ii, jj], 1)


def consistent_count(xw: np.ndarray, others: list[tuple[View, np.ndarray]], rel: float) -> np.ndarray:
    """How many of the other depth maps agree with each world point."""
    cnt = np.zeros(len(xw), np.int32)
    for v, D in others:
        xc = xw @ v.pose.R.T + v.pose.t
        z = xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(v.K[0, 0] * xc[:, 0] / z + v.K[0, 2]).astype(np.int64)
            r = np.round(v.K[1, 1] * xc[:, 1] / z + v.K[1, 2]).astype(np.int64)
        inside = (z > 0) & (u >= 0) & (u < v.width) & (r >= 0) & (r < v.height)
        dz = np.full(len(xw), np.nan, np.float32)
        dz[inside] = D[r[inside], u[inside]]
        with np.errstate(invalid="ignore"):
            cnt += (np.abs(dz - z) <= rel * z).astype(np.int32)
    return cnt


def write_laz(path: Path, xyz_crs: np.ndarray, rgb: np.ndarray, crs: str) -> Path:
    """A LAZ point cloud (CRS coordinates, colours, the CRS in the header)."""
    import laspy
    from pyproj import CRS

    header = laspy.LasHeader(point_format=7, version="1.4")
    header.offsets = np.floor(xyz_crs.min(0))
    header.scales = np.array([0.001, 0.001, 0.001])
    header.add_crs(CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz_crs[:, 0], xyz_crs[:, 1], xyz_crs[:, 2]
    las.red, las.green, las.blue = (rgb[:, c].astype(np.uint16) * 257 for c in range(3))
    with atomic_path(path) as tmp:
        las.write(str(tmp), laz_backend=laspy.LazBackend.Lazrs) if str(path).endswith(".laz") else las.write(str(tmp))
    return path


def write_ply_points(path: Path, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray | None = None) -> Path:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pc.colors = o3d.utility.Vector3dVector(rgb / 255.0)
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(normals)
    with atomic_path(path) as tmp:
        o3d.io.write_point_cloud(str(tmp.with_suffix(".ply")) if tmp.suffix != ".ply" else str(tmp), pc)
    return path
