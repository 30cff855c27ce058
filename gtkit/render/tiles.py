"""Tile streaming over :class:`gtkit.render.renderer.Renderer`: upload only the tiles a view sees.

For a perspective view the tiles whose world bounding box meets the camera frustum are chosen
(each box's eight corners tested against the four side planes and the near plane; a box is
dropped only when all its corners are outside one plane, so the test never loses a visible
tile). For a top-down extent the tiles whose box meets the extent are chosen. Tiles are read
from disk when first needed and kept in least-recently-used order; after each view, tiles
beyond ``budget_mb`` (GPU bytes: vertices, indices, textures with mipmaps) that the view did not
use are evicted. A single view that needs more than the budget still renders (the budget is
then exceeded for that view only, with a warning).

All tiles are uploaded relative to one origin (the model's centre), so a view rendered from
tiles is bit-identical to the whole model uploaded with that origin (see
``Renderer.add_mesh(origin=...)``). Near and far planes come from the whole model's bounds,
as a renderer holding the whole model would choose them.
"""
from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.tiled import TiledModel, is_tiled
from ..pose import Pose
from .frustum import boxes_in_frustum, near_far
from .renderer import NO_LIGHT, Lighting, Renderer, RenderResult
from .texture_detail import TextureDetail, coarsen

log = logging.getLogger(__name__)


@dataclass
class _Resident:
    ids: list[int]
    nbytes: int


@dataclass
class StreamStats:
    tiles_drawn: int = 0
    tiles_loaded: int = 0        # read from disk for this view
    tiles_evicted: int = 0
    resident_tiles: int = 0
    resident_mb: float = 0.0
    load_s: float = 0.0
    render_s: float = 0.0


def _part_bytes(mesh) -> int:
    n = 0
    for p in mesh.parts:
        n += len(p.vertices) * 9 * 4 + p.faces.size * 4
        if p.texture is not None:
            n += int(p.texture.shape[0] * p.texture.shape[1] * 4 * 4 / 3)  # RGBA texels + mipmaps
    return n


class TileStreamer:
    """Render views of a :class:`TiledModel`, keeping only the tiles in use on the GPU."""

    def __init__(self, model: TiledModel, budget_mb: float = 512.0, renderer: Renderer | None = None,
                 procedural_glsl: str | None = None, detail: TextureDetail | None = None):
        self.model = model
        self.detail = detail
        self.budget = int(budget_mb * 2**20)
        self.renderer = renderer or Renderer()
        self.glsl = procedural_glsl
        self.origin = model.bounds().mean(0)
        self._names = model.names
        self._boxes = np.stack([model.tiles[n].bounds for n in self._names])
        self._resident: OrderedDict[str, _Resident] = OrderedDict()
        self.stats = StreamStats()

    # --- selection --------------------------------------------------------------------------
    def boxes(self) -> np.ndarray:
        """(N, 2, 3) world bounding boxes of the model's tiles."""
        return self._boxes

    def visible_tiles(self, camera: Camera, pose: Pose, margin: float = 0.05) -> list[str]:
        m = margin + (0.1 if camera.has_distortion else 0.0)
        keep = boxes_in_frustum(self._boxes, camera, pose, m)
        return [n for n, k in zip(self._names, keep) if k]

    def tiles_in_extent(self, xmin: float, ymin: float, xmax: float, ymax: float) -> list[str]:
        return self.model.tiles_in_box([xmin, ymin], [xmax, ymax])

    # --- residency --------------------------------------------------------------------------
    @property
    def resident(self) -> list[str]:
        return list(self._resident)

    @property
    def resident_bytes(self) -> int:
        return sum(r.nbytes for r in self._resident.values())

    def _ensure(self, names: list[str]) -> list[int]:
        ids = []
        for n in names:
            r = self._resident.get(n)
            if r is None:
                t0 = time.perf_counter()
                mesh = self.model.load_tile(n)
                mesh.parts = [coarsen(p, self.detail) for p in mesh.parts]
                r = _Resident(self.renderer.add_mesh(mesh, self.glsl, origin=self.origin), _part_bytes(mesh))
                del mesh
                self._resident[n] = r
                self.stats.tiles_loaded += 1
                self.stats.load_s += time.perf_counter() - t0
            self._resident.move_to_end(n)
            ids += r.ids
        return ids

    def _evict(self, keep: set[str]) -> None:
        total = self.resident_bytes
        for n in list(self._resident):
            if total <= self.budget:
                break
            if n in keep:
                continue
            r = self._resident.pop(n)
            self.renderer.remove_parts(r.ids)
            total -= r.nbytes
            self.stats.tiles_evicted += 1
        if total > self.budget:
            log.warning("view needs %.0f MB of tiles, above the %.0f MB budget", total / 2**20, self.budget / 2**20)

    def _begin(self) -> None:
        self.stats = StreamStats()

    def _end(self, names) -> None:
        self._evict(set(names))
        self.stats.tiles_drawn = len(names)
        self.stats.resident_tiles = len(self._resident)
        self.stats.resident_mb = self.resident_bytes / 2**20

    # --- views ------------------------------------------------------------------------------
    def render(self, camera: Camera, pose: Pose, *, lighting: Lighting = NO_LIGHT,
               with_rgb: bool = True) -> RenderResult:
        """RGB + depth of a perspective view, drawing only the tiles in the frustum."""
        self._begin()
        names = self.visible_tiles(camera, pose)
        ids = self._ensure(names)
        t0 = time.perf_counter()
        if ids:
            n, f = near_far(self.model.bounds(), pose)
            out = self.renderer.render(camera, pose, lighting=lighting, with_rgb=with_rgb, parts=ids, near=n, far=f)
        else:
            out = RenderResult(np.zeros((camera.height, camera.width, 3), np.uint8) if with_rgb else None,
                               np.full((camera.height, camera.width), np.nan, np.float32))
        self.stats.render_s = time.perf_counter() - t0
        self._end(names)
        return out

    def render_ortho(self, xmin: float, ymin: float, xmax: float, ymax: float, gsd: float, *,
                     lighting: Lighting = NO_LIGHT, with_rgb: bool = True, tile: int = 2048) -> RenderResult:
        """Top-down RGB + highest height of an extent, window by window (``tile`` pixels a side).

        Each window draws only the tiles that meet it, and tiles beyond the budget are evicted
        between windows, so a large DSM never needs the whole model resident. The windows are
        the ones :meth:`Renderer.render_ortho` uses for the same ``tile``, so the raster is
        bit-identical to rendering the whole model at once."""
        from ..errors import GtkitError

        self._begin()
        W, H = int(round((xmax - xmin) / gsd)), int(round((ymax - ymin) / gsd))
        if W <= 0 or H <= 0:
            raise GtkitError(f"empty orthographic extent {W}x{H} pixels")
        out_h = np.full((H, W), np.nan, np.float32)
        out_rgb = np.zeros((H, W, 3), np.uint8) if with_rgb else None
        used: set[str] = set()
        t_render = 0.0
        for r0 in range(0, H, tile):
            for c0 in range(0, W, tile):
                h, w = min(tile, H - r0), min(tile, W - c0)
                x0, x1 = xmin + c0 * gsd, xmin + (c0 + w) * gsd
                y1, y0 = ymax - r0 * gsd, ymax - (r0 + h) * gsd
                names = self.tiles_in_extent(x0, y0, x1, y1)
                if not names:
                    continue
                ids = self._ensure(names)
                t0 = time.perf_counter()
                res = self.renderer.render_ortho(x0, y0, x1, y1, gsd, lighting=lighting, with_rgb=with_rgb,
                                                 parts=ids, tile=tile)
                t_render += time.perf_counter() - t0
                out_h[r0:r0 + h, c0:c0 + w] = res.depth
                if with_rgb:
                    out_rgb[r0:r0 + h, c0:c0 + w] = res.rgb
                used.update(names)
                self._evict(set(names))
        self.stats.render_s = t_render
        self._end(sorted(used))
        return RenderResult(out_rgb, out_h)

    def release(self) -> None:
        self.renderer.remove_parts([i for r in self._resident.values() for i in r.ids])
        self._resident.clear()


def open_renderer(path, frame, tile_budget_mb: float = 512.0, anisotropy: float = 8.0,
                  detail: TextureDetail | None = None):
    """What draws a model: for a tiled model (its folder or ``metadata.xml``) a :class:`TileStreamer`
    that uploads only the tiles each view sees (resident tiles under ``tile_budget_mb``); for a mesh
    file a :class:`Renderer` holding all of it, an OBJ read by numpy and uploaded a material (one
    texture) at a time (:func:`gtkit.io.mesh.model_parts`). Both offer ``render``, ``render_ortho``,
    ``release``. ``detail``: textures finer than those views can show are halved as they are loaded
    (:mod:`gtkit.render.texture_detail`); None keeps them as stored."""
    from pathlib import Path

    path = Path(path)
    if is_tiled(path):
        from ..io.tiled import read_tiled

        return TileStreamer(read_tiled(path, frame), budget_mb=tile_budget_mb, renderer=Renderer(anisotropy=anisotropy),
                            detail=detail)
    if not path.is_file():
        raise GtkitError("reference model not found (expected model/reference.obj or a tiled model folder)", path)
    from ..io.mesh import model_parts

    r = Renderer(anisotropy=anisotropy)
    r.add_parts(coarsen(p, detail) for p in model_parts(path, frame))
    return r
