"""The one GeoTIFF writer for gtkit's rasters (DSM, orthophoto).

What a GIS user expects from it: the CRS embedded, a north-up geotransform in CRS coordinates
(the grid's world coordinates plus the project origin), a nodata value (float rasters) or an
alpha band (RGB), 256 x 256 tiles, DEFLATE compression with a predictor, and on request a
cloud-optimised GeoTIFF (GDAL's COG driver: internal overviews, tiles in order). The file
appears atomically: readers see the old file or the complete new one.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import atomic_path
from .grid import Grid

BLOCK = 256


def write_geotiff(path: str | Path, data: np.ndarray, grid: Grid, crs, origin=(0.0, 0.0, 0.0), *,
                  nodata: float | None = None, alpha: np.ndarray | None = None, cog: bool = False,
                  tags: dict | None = None, band_names: list[str] | None = None,
                  resampling: str = "bilinear") -> Path:
    """Write ``data`` ((H, W) or (H, W, B); float32 or uint8) on ``grid`` as a GeoTIFF.

    ``crs``: anything rasterio/pyproj accept (pyproj CRS, 'EPSG:32615', WKT). ``origin``: the
    project origin, added to the grid's world x/y for the geotransform (values are written as
    given: callers add the origin's z to heights). ``alpha``: optional (H, W) bool, True = data
    (written as a fourth, alpha band). ``tags``: text metadata (settings, units, height datum).
    """
    import rasterio
    from rasterio.crs import CRS as RioCRS
    from rasterio.enums import ColorInterp

    path = Path(path)
    arr = np.asarray(data)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.shape[:2] != grid.shape:
        raise GtkitError(f"raster {arr.shape[:2]} does not match its grid {grid.shape}", path)
    bands = [arr[..., b] for b in range(arr.shape[2])]
    if alpha is not None:
        bands.append(np.where(alpha, 255, 0).astype(arr.dtype))
    is_float = np.issubdtype(arr.dtype, np.floating)
    profile = dict(driver="GTiff", width=grid.width, height=grid.height, count=len(bands),
                   dtype=arr.dtype.name, crs=RioCRS.from_user_input(_crs_input(crs)),
                   transform=grid.transform(origin), nodata=nodata,
                   tiled=True, blockxsize=BLOCK, blockysize=BLOCK, compress="deflate",
                   predictor=3 if is_float else 2, bigtiff="if_safer")
    if alpha is not None and arr.shape[2] == 3:
        profile["photometric"] = "RGB"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as final_tmp:
        plain = final_tmp.with_name(final_tmp.name + ".plain.tif") if cog else final_tmp
        try:
            with rasterio.open(plain, "w", **profile) as dst:
                for b, band in enumerate(bands, 1):
                    dst.write(band, b)
                if alpha is not None and arr.shape[2] == 3:
                    dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
                elif alpha is not None:
                    dst.colorinterp = [ColorInterp.gray] * arr.shape[2] + [ColorInterp.alpha]
                if band_names:
                    for b, name in enumerate(band_names, 1):
                        dst.set_band_description(b, name)
                dst.update_tags(AREA_OR_POINT="Area", **{k: str(v) for k, v in (tags or {}).items()})
            if cog:
                from rasterio.shutil import copy as rio_copy

                rio_copy(plain, final_tmp, driver="COG", compress="DEFLATE",
                         predictor="FLOATING_POINT" if is_float else "HORIZONTAL", blocksize=BLOCK,
                         overview_resampling=resampling.upper(),
                         bigtiff="IF_SAFER")
        finally:
            if cog:
                plain.unlink(missing_ok=True)
    return path


def _crs_input(crs):
    if hasattr(crs, "to_wkt"):
        return crs.to_wkt()
    return str(crs)
