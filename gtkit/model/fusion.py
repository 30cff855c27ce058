"""Fusion of the per-photo depth maps into one point cloud.

Every (``fusion_stride``-th) pixel with a depth is lifted to the world and kept only where at least
``min_view_agree`` of its photo's neighbours' depth maps see the same surface there (their depth at
the projected pixel within ``pair_agree`` of the point's depth in that photo: geometric consistency).
Kept points are averaged per voxel (position, colour, the direction to the cameras that saw them,
so normals can be oriented toward the photos).

Memory is bounded by a cell, not by the site (:class:`CellSpill`): the lifted points are appended
to one file per ``fusion_cell_m`` square cell (cells are whole numbers of voxels, so a voxel never
straddles two), and once every photo is lifted each cell is reduced to its voxels on its own and
written beside the others (``FusedCells``). The surface then reads a tile's cells (tile + overlap)
from disk and the LAZ is written cell by cell. The voxel means are the same as one accumulator over
the whole site (the same voxels, the same points in them; sums in float64, stored as float32:
local metres, ~0.1 mm at 1 km).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path, write_json
from .views import View

_OFF = 1 << 20          # voxel index offset (keys need non-negative indices; +-262 km at 0.25 m)


def voxel_index(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """(n, 3) int64 voxel indices (offset to be non-negative) of world points."""
    return np.floor(xyz / voxel).astype(np.int64) + _OFF


def voxel_key(q: np.ndarray) -> np.ndarray:
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


class VoxelAccumulator:
    """Sums per voxel, reduced whenever the buffer grows (bounded memory)."""

    def __init__(self, voxel: float, flush_at: int = 4_000_000):
        self.voxel, self.flush_at = voxel, flush_at
        self.keys = np.zeros(0, np.int64)
        self.data = np.zeros((0, 10), np.float64)   # xyz, rgb, view dir, count
        self._buf: list[tuple[np.ndarray, np.ndarray]] = []
        self._n = 0

    def _key(self, xyz: np.ndarray) -> np.ndarray:
        return voxel_key(voxel_index(xyz, self.voxel))

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


SPILL = np.dtype([("key", "<i8"), ("xyz", "<f4", 3), ("rgb", "u1", 3), ("dir", "<f4", 3)])   # 35 bytes a point
CELL = np.dtype([("key", "<i8"), ("xyz", "<f4", 3), ("rgb", "u1", 3), ("dir", "<f4", 3), ("n", "<u4")])


class CellSpill:
    """Lifted points appended to one file per cell of ``cell_m`` (rounded to whole voxels) under
    ``folder``; :meth:`reduce` averages each cell's voxels on its own (memory: one cell) into a
    :class:`FusedCells`. Peak memory while adding: the photo being added."""

    def __init__(self, folder: Path, voxel: float, cell_m: float):
        self.folder, self.voxel = Path(folder), voxel
        self.cell = max(1, int(round(cell_m / voxel)))       # voxels a cell side
        if self.folder.exists():
            shutil.rmtree(self.folder)                       # a killed run's half-filled cells
        self.folder.mkdir(parents=True)
        self.n = 0

    def _file(self, cx: int, cy: int) -> Path:
        return self.folder / f"c{cx}_{cy}.bin"

    def add(self, xyz: np.ndarray, rgb: np.ndarray, view_dir: np.ndarray) -> None:
        if not len(xyz):
            return
        q = voxel_index(xyz, self.voxel)
        rec = np.empty(len(xyz), SPILL)
        rec["key"], rec["xyz"], rec["rgb"], rec["dir"] = voxel_key(q), xyz, rgb, view_dir
        c = (q[:, :2] - _OFF) // self.cell
        cid = (c[:, 0] + _OFF) * (1 << 22) + (c[:, 1] + _OFF)
        order = np.argsort(cid, kind="stable")
        cid, rec, c = cid[order], rec[order], c[order]
        starts = np.flatnonzero(np.r_[True, cid[1:] != cid[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(cid)]):
            with open(self._file(int(c[a, 0]), int(c[a, 1])), "ab") as f:
                rec[a:b].tofile(f)
        self.n += len(xyz)

    def reduce(self, out: Path, info: dict | None = None, progress=None) -> "FusedCells":
        """Average each cell's voxels (xyz, rgb, unit direction to the cameras, count) into
        ``out/<cell>.npy`` (atomic), write ``out/index.json`` last (the fusion is done when it is
        there) and remove the spill files."""
        out = Path(out)
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        cells = []
        for f in sorted(self.folder.glob("c*.bin")):
            rec = np.fromfile(f, SPILL)
            uk, inv = np.unique(rec["key"], return_inverse=True)
            m = len(uk)
            res = np.empty(m, CELL)
            res["key"] = uk
            n = np.bincount(inv, minlength=m).astype(np.float64)
            res["n"] = n
            for name, cols in (("xyz", 3), ("rgb", 3), ("dir", 3)):
                col = rec[name]
                sums = np.stack([np.bincount(inv, weights=col[:, c].astype(np.float64), minlength=m)
                                 for c in range(cols)], 1)
                if name == "xyz":
                    res["xyz"] = sums / n[:, None]
                elif name == "rgb":
                    res["rgb"] = np.clip(sums / n[:, None] + 0.5, 0, 255).astype(np.uint8)
                else:
                    res["dir"] = sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)
                del sums, col
            del rec, inv
            name = f.stem
            with atomic_path(out / f"{name}.npy") as tmp:
                np.save(tmp, res)
            xy = res["xyz"][:, :2]
            cells.append({"cell": name, "points": m, "lo": xy.min(0).tolist(), "hi": xy.max(0).tolist(),
                          "zlo": float(res["xyz"][:, 2].min()), "zhi": float(res["xyz"][:, 2].max())})
            del res, xy
            f.unlink()
            if progress is not None:
                progress(len(cells))
        write_json(out / "index.json", {"cells": cells, **(info or {})})
        shutil.rmtree(self.folder, ignore_errors=True)
        return FusedCells(out)


class FusedCells:
    """The fused cloud on disk, one file per cell (:meth:`CellSpill.reduce`); read a box at a time."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.index = json.loads((self.folder / "index.json").read_text())
        self.cells = self.index["cells"]

    @staticmethod
    def done(folder: Path) -> bool:
        return (Path(folder) / "index.json").is_file()

    def __len__(self) -> int:
        return int(sum(c["points"] for c in self.cells))

    def bounds(self) -> np.ndarray:
        """(2, 3) min / max of the points."""
        if not self.cells:
            return np.zeros((2, 3))
        lo = np.min([c["lo"] + [c["zlo"]] for c in self.cells], 0)
        hi = np.max([c["hi"] + [c["zhi"]] for c in self.cells], 0)
        return np.stack([lo, hi])

    def read(self, box: np.ndarray | None = None, margin: float = 0.0) -> np.ndarray:
        """The voxels (``CELL`` records) whose xy is inside ``box`` grown by ``margin`` (all when None),
        ordered by voxel key (the order of one accumulator over the site)."""
        parts = []
        for c in self.cells:
            if box is not None and (np.any(np.asarray(c["hi"]) < box[0] - margin) or np.any(np.asarray(c["lo"]) > box[1] + margin)):
                continue
            r = np.load(self.folder / f"{c['cell']}.npy")
            if box is not None:
                xy = r["xyz"][:, :2]
                r = r[np.all((xy >= box[0] - margin) & (xy <= box[1] + margin), axis=1)]
            parts.append(r)
        if not parts:
            return np.zeros(0, CELL)
        r = np.concatenate(parts)
        return r[np.argsort(r["key"], kind="stable")]

    def iter_cells(self):
        for c in self.cells:
            yield np.load(self.folder / f"{c['cell']}.npy")


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


def write_laz_cells(path: Path, cloud: FusedCells, origin: np.ndarray, crs: str, chunk: int = 2_000_000) -> Path:
    """The fused cloud as LAZ (CRS coordinates = local + ``origin``, colours, the CRS in the header),
    written cell by cell (laspy's chunked writer: memory is one cell, not the cloud)."""
    import laspy
    from pyproj import CRS

    origin = np.asarray(origin, np.float64)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.offsets = np.floor(cloud.bounds()[0] + origin)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.add_crs(CRS.from_user_input(crs))
    laz = str(path).endswith(".laz")
    with atomic_path(path) as tmp:
        with laspy.open(str(tmp), mode="w", header=header, do_compress=laz,
                        laz_backend=laspy.LazBackend.Lazrs if laz else None) as w:
            for r in cloud.iter_cells():
                for a in range(0, len(r), chunk):
                    c = r[a:a + chunk]
                    pts = laspy.ScaleAwarePointRecord.zeros(len(c), header=header)
                    xyz = c["xyz"].astype(np.float64) + origin
                    pts.x, pts.y, pts.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
                    rgb = c["rgb"].astype(np.uint16) * 257
                    pts.red, pts.green, pts.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
                    w.write_points(pts)
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
