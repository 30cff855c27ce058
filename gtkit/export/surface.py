"""Surface samples -> a height (and colour) grid: the one rasteriser behind the DSM and ortho.

Two kinds of source give "the highest surface per cell":

* :class:`MeshSurface`: a (textured) mesh, rendered top-down by the shared orthographic renderer
  (:meth:`gtkit.render.renderer.Renderer.render_ortho`); each cell holds the highest surface at
  its centre, and its colour there.
* :class:`PointSurface`: a point cloud (LAS/LAZ or PLY); each cell holds its highest point
  (and that point's colour).

:func:`rasterize_surface` takes either and returns a :class:`SurfaceRaster` on a
:class:`gtkit.export.grid.Grid`; :func:`fill_small_holes` closes isolated empty cells.
Everything here is in the world frame (CRS minus the project origin).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import GtkitError
from ..io.mesh import Mesh, MeshPart
from ..io.obj_geometry import triangle_texel_sizes
from .grid import Grid


@dataclass
class SurfaceRaster:
    height: np.ndarray          # (H, W) float32 world z, NaN = no surface
    rgb: np.ndarray | None      # (H, W, 3) uint8 or None
    grid: Grid


class MeshSurface:
    """A mesh in the world frame as a surface source."""

    kind = "mesh"

    def __init__(self, mesh: Mesh):
        if not mesh.parts:
            raise GtkitError("mesh has no parts")
        self.mesh = mesh

    def bounds(self) -> np.ndarray:
        return self.mesh.bounds()

    def edge_length(self) -> float:
        """Median 3-D triangle edge length (metres)."""
        e = []
        for p in self.mesh.parts:
            v = p.vertices[p.faces]
            e.append(np.linalg.norm(v[:, [1, 2, 0]] - v, axis=2).ravel())
        return float(np.median(np.concatenate(e)))

    def texel_size(self) -> float | None:
        """Median ground size of one texel (metres) over textured, non-degenerate triangles."""
        sizes = []
        for p in self.mesh.parts:
            if p.texture is None or p.uv is None:
                continue
            th, tw = p.texture.shape[:2]
            sizes.append(triangle_texel_sizes(p.vertices[p.faces], p.uv[p.faces] * np.array([tw, th])))
        sizes = np.concatenate(sizes) if sizes else np.zeros(0)
        return float(np.median(sizes)) if len(sizes) else None

    def detail(self) -> float:
        """The finest ground detail the model carries: its texel size when textured (what the
        photogrammetry resolved), otherwise half its median edge length."""
        t = self.texel_size()
        return t if t is not None else 0.5 * self.edge_length()

    def rasterize(self, grid: Grid, with_rgb: bool) -> SurfaceRaster:
        # one upload origin for every part, the model's centre: the same raster as the model
        # delivered as tiles (gtkit.render.tiles uses that origin), bit for bit
        return _ortho_raster(lambda r: r.add_mesh(self.mesh, origin=self.mesh.bounds().mean(0)), grid, with_rgb)


class ObjMeshSurface:
    """An OBJ's triangles without its textures (:mod:`gtkit.io.obj_geometry`) as a height source:
    what the DSM and ``gtkit model compare`` need. Its raster is drawn a piece of
    ``piece_triangles`` at a time (:func:`render_heights_in_pieces`) with the origin and depth range
    :class:`MeshSurface` uses for the whole model, so the heights are those of the textured model
    loaded whole; memory is the geometry (24 B a vertex, 12 B a triangle) and one piece."""

    kind = "mesh"

    def __init__(self, geometry, piece_triangles: int = 1_000_000):
        if not geometry.n_triangles:
            raise GtkitError("mesh has no triangles", geometry.path)
        self.geometry = geometry
        self.piece_triangles = piece_triangles
        self._bounds = None

    def bounds(self) -> np.ndarray:
        if self._bounds is None:
            self._bounds = self.geometry.bounds()
        return self._bounds

    def detail(self) -> float:
        """As :meth:`MeshSurface.detail`: the texel size when textured, else half the median edge."""
        t = self.geometry.texel_size
        return t if t is not None else 0.5 * self.geometry.edge_length()

    def rasterize(self, grid: Grid, with_rgb: bool) -> SurfaceRaster:
        if with_rgb:
            raise GtkitError("colours need the textures: load the model as a MeshSurface", self.geometry.path)
        b = self.bounds()
        pieces = (Mesh([MeshPart(v, f)]) for v, f in self.geometry.pieces(self.piece_triangles))
        height = render_heights_in_pieces(pieces, grid, origin=b.mean(0), zrange=(b[0, 2], b[1, 2]))
        return SurfaceRaster(height, None, grid)


class ObjTexturedSurface(ObjMeshSurface):
    """An OBJ read by :mod:`gtkit.io.obj_geometry` with its corners' uv and materials: the
    orthophoto's source. Its raster is :class:`MeshSurface`'s (the same parts, the same upload
    origin and depth range), but the parts are uploaded one material at a time, each texture
    decoded once and dropped after its upload, so memory is the geometry, the renderer's copy of
    the uploaded model, one decoded texture and the raster, not trimesh's parse of the file."""

    def rasterize(self, grid: Grid, with_rgb: bool) -> SurfaceRaster:
        return _ortho_raster(lambda r: r.add_parts(self.geometry.parts(), origin=self.bounds().mean(0)), grid, with_rgb)


def _ortho_raster(upload, grid: Grid, with_rgb: bool) -> SurfaceRaster:
    """``upload(renderer)`` puts the model in a fresh renderer; the grid drawn straight down."""
    from ..render.renderer import Renderer

    r = Renderer()
    try:
        upload(r)
        res = r.render_ortho(grid.xmin, grid.ymin, grid.xmax, grid.ymax, grid.res, with_rgb=with_rgb)
    finally:
        r.release()
    if res.depth.shape != grid.shape:  # render_ortho rounds the extent; the grid is whole cells
        raise GtkitError(f"orthographic render gave {res.depth.shape}, expected {grid.shape}")
    return SurfaceRaster(res.depth.astype(np.float32), res.rgb, grid)


def render_heights_in_pieces(pieces, grid: Grid, origin, zrange) -> np.ndarray:
    """The highest surface per cell of ``grid`` from meshes drawn one after another (each
    uploaded, drawn over the windows it reaches, released): the cell keeps the highest of the
    pieces' heights. With the whole model's ``origin`` and ``zrange`` every piece's float32
    heights are the ones the whole model drawn at once gives, so only a piece is ever resident."""
    from ..render.renderer import Renderer

    height = np.full(grid.shape, np.nan, np.float32)
    r = Renderer()
    try:
        for mesh in pieces:
            ids = r.add_mesh(mesh, origin=origin)
            del mesh
            res = r.render_ortho(grid.xmin, grid.ymin, grid.xmax, grid.ymax, grid.res, with_rgb=False,
                                 parts=ids, zrange=zrange)
            r.remove_parts(ids)
            if res.depth.shape != grid.shape:  # render_ortho rounds the extent; the grid is whole cells
                raise GtkitError(f"orthographic render gave {res.depth.shape}, expected {grid.shape}")
            np.fmax(height, res.depth, out=height)
    finally:
        r.release()
    return height


class TiledSurface:
    """A tiled model (ContextCapture layout, :mod:`gtkit.io.tiled`) as a surface source: the
    raster is rendered window by window with only the tiles each window meets resident, and is
    identical to rendering the same model loaded as one mesh. Heights alone (the DSM) are drawn
    one tile at a time from the tiles' triangles, their textures not read."""

    kind = "tiled mesh"

    def __init__(self, model, budget_mb: float = 512.0):
        self.model = model
        self.budget_mb = budget_mb

    def bounds(self) -> np.ndarray:
        return self.model.bounds()

    def detail(self) -> float:
        """The detail of the smallest tile (one tile read; tiles of one delivery share a detail)."""
        smallest = min(self.model.tiles.values(), key=lambda t: t.size)
        return MeshSurface(self.model.load_tile(smallest.name)).detail()

    def rasterize(self, grid: Grid, with_rgb: bool) -> SurfaceRaster:
        if not with_rgb:
            # heights only: one tile's triangles at a time, without their textures
            b = self.bounds()
            names = self.model.tiles_in_box([grid.xmin, grid.ymin], [grid.xmax, grid.ymax])
            pieces = (self.model.load_tile(n, textures=False) for n in names)
            height = render_heights_in_pieces(pieces, grid, origin=b.mean(0), zrange=(b[0, 2], b[1, 2]))
            return SurfaceRaster(height, None, grid)
        from ..render.tiles import TileStreamer

        streamer = TileStreamer(self.model, budget_mb=self.budget_mb)
        try:
            res = streamer.render_ortho(grid.xmin, grid.ymin, grid.xmax, grid.ymax, grid.res, with_rgb=with_rgb)
        finally:
            streamer.renderer.release()
        if res.depth.shape != grid.shape:
            raise GtkitError(f"orthographic render gave {res.depth.shape}, expected {grid.shape}")
        return SurfaceRaster(res.depth.astype(np.float32), res.rgb, grid)


class PointSurface:
    """A point cloud in the world frame as a surface source."""

    kind = "points"

    def __init__(self, xyz: np.ndarray, rgb: np.ndarray | None = None):
        xyz = np.asarray(xyz, dtype=np.float64)
        ok = np.all(np.isfinite(xyz), axis=1)
        if ok.sum() == 0:
            raise GtkitError("point cloud has no finite points")
        self.xyz = xyz[ok]
        self.rgb = None if rgb is None else np.asarray(rgb, np.uint8)[ok]

    def bounds(self) -> np.ndarray:
        return np.stack([self.xyz.min(0), self.xyz.max(0)])

    def spacing(self) -> float:
        """Mean horizontal point spacing over the occupied area (metres)."""
        b = self.bounds()
        n = len(self.xyz)
        area = max((b[1, 0] - b[0, 0]) * (b[1, 1] - b[0, 1]), 1e-6)
        cell = 4.0 * np.sqrt(area / n)
        g = Grid.covering(b[0, 0], b[0, 1], b[1, 0], b[1, 1], cell)
        i, j, _ = g.cell_of(self.xyz[:, 0], self.xyz[:, 1])
        occupied = len(np.unique(np.clip(i, 0, g.height - 1) * g.width + np.clip(j, 0, g.width - 1)))
        return float(np.sqrt(occupied * cell * cell / n))

    def detail(self) -> float:
        return self.spacing()

    def rasterize(self, grid: Grid, with_rgb: bool) -> SurfaceRaster:
        i, j, inside = grid.cell_of(self.xyz[:, 0], self.xyz[:, 1])
        cell = (i * grid.width + j)[inside]
        z = self.xyz[inside, 2]
        order = np.lexsort((z, cell))                         # by cell, then by height
        cell_sorted = cell[order]
        last = np.flatnonzero(np.r_[cell_sorted[1:] != cell_sorted[:-1], True])  # highest of each cell
        top = order[last]
        height = np.full(grid.width * grid.height, np.nan, np.float32)
        height[cell[top]] = z[top]
        rgb = None
        if with_rgb:
            rgb = np.zeros((grid.width * grid.height, 3), np.uint8)
            if self.rgb is not None:
                rgb[cell[top]] = self.rgb[inside][top]
            else:
                rgb[cell[top]] = 180
            rgb = rgb.reshape(grid.height, grid.width, 3)
        return SurfaceRaster(height.reshape(grid.shape), rgb, grid)


def rasterize_surface(source: MeshSurface | PointSurface, grid: Grid, *, with_rgb: bool = False,
                      fill_passes: int = 0) -> SurfaceRaster:
    """The highest surface per cell of ``grid`` from a mesh or a point cloud (NaN where empty),
    optionally with small holes filled (see :func:`fill_small_holes`)."""
    out = source.rasterize(grid, with_rgb)
    if fill_passes > 0:
        out.height, out.rgb = fill_small_holes(out.height, out.rgb, fill_passes)
    return out


def fill_small_holes(height: np.ndarray, rgb: np.ndarray | None, passes: int,
                     min_neighbours: int = 5) -> tuple[np.ndarray, np.ndarray | None]:
    """Fill empty cells that have at least ``min_neighbours`` of their 8 neighbours filled with
    the mean of those neighbours, ``passes`` times. With 5 of 8 a hole up to about 2*passes cells
    across closes, while the outer border of the data (at most 3 filled neighbours along a
    straight edge) does not grow."""
    from scipy.ndimage import convolve

    h = height.astype(np.float32, copy=True)
    c = None if rgb is None else rgb.astype(np.float32)
    k = np.ones((3, 3), np.float32)
    k[1, 1] = 0
    for _ in range(passes):
        empty = ~np.isfinite(h)
        if not empty.any():
            break
        valid = (~empty).astype(np.float32)
        n = convolve(valid, k, mode="constant")
        s = convolve(np.where(empty, 0, h), k, mode="constant")
        fill = empty & (n >= min_neighbours)
        if not fill.any():
            break
        if c is not None:
            for b in range(3):
                sb = convolve(c[..., b] * valid, k, mode="constant")
                c[..., b][fill] = sb[fill] / n[fill]
        h[fill] = s[fill] / n[fill]
    return h, (None if c is None else np.clip(np.rint(c), 0, 255).astype(np.uint8))


