"""Coordinate reference systems: the project CRS, its local origin, and WGS84 conversions.

The world frame (see :mod:`gtkit.conventions`) is the projected CRS minus ``origin``.
Heights pass through unchanged: gtkit does not convert vertical datums.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from .errors import GtkitError

WGS84 = "EPSG:4326"


def utm_epsg(lon_deg: float, lat_deg: float) -> int:
    """EPSG code of the WGS 84 / UTM zone containing (lon, lat)."""
    if not (-180.0 <= lon_deg <= 180.0 and -90.0 <= lat_deg <= 90.0):
        raise GtkitError(f"longitude/latitude out of range: ({lon_deg}, {lat_deg})")
    zone = min(int((lon_deg + 180.0) // 6.0) + 1, 60)
    return (32600 if lat_deg >= 0 else 32700) + zone


def parse_crs(spec, source=None) -> CRS:
    """A CRS from an EPSG code (int or 'EPSG:n'), WKT or PROJ string; a clear error otherwise."""
    try:
        crs = CRS.from_epsg(spec) if isinstance(spec, int) else CRS.from_user_input(str(spec).strip())
    except CRSError as e:
        raise GtkitError(f"unknown or invalid CRS {spec!r} ({str(e).splitlines()[0]})", source) from None
    return crs


def crs_name(crs: CRS) -> str:
    """'EPSG:32650' where an EPSG code exists, otherwise the WKT."""
    code = crs.to_epsg()
    return f"EPSG:{code}" if code else crs.to_wkt()


@dataclass(frozen=True)
class GeoFrame:
    """A projected CRS plus the local origin subtracted from it to give world coordinates."""

    crs_spec: str
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: str | None = field(default=None, compare=False)

    def __post_init__(self):
        crs = parse_crs(self.crs_spec, self.source)
        if not crs.is_projected:
            raise GtkitError(f"CRS {self.crs_spec!r} is not projected (metres are needed)", self.source)
        if len(self.origin) != 3 or not np.all(np.isfinite(self.origin)):
            raise GtkitError(f"origin must be three finite numbers, got {self.origin!r}", self.source)

    @classmethod
    def for_lonlat(cls, lon: float, lat: float, height: float = 0.0, epsg: int | None = None) -> "GeoFrame":
        """A frame in the UTM zone of (lon, lat) (or ``epsg``), origin at that point rounded to 1 m."""
        code = epsg or utm_epsg(lon, lat)
        e, n = Transformer.from_crs(WGS84, f"EPSG:{code}", always_xy=True).transform(lon, lat)
        return cls(f"EPSG:{code}", (float(round(e)), float(round(n)), float(round(height))))

    @cached_property
    def crs(self) -> CRS:
        return parse_crs(self.crs_spec, self.source)

    @cached_property
    def _to_wgs84(self) -> Transformer:
        return Transformer.from_crs(self.crs, WGS84, always_xy=True)

    @cached_property
    def _from_wgs84(self) -> Transformer:
        return Transformer.from_crs(WGS84, self.crs, always_xy=True)

    def crs_to_local(self, xyz) -> np.ndarray:
        return np.asarray(xyz, dtype=np.float64) - np.asarray(self.origin)

    def local_to_crs(self, xyz) -> np.ndarray:
        return np.asarray(xyz, dtype=np.float64) + np.asarray(self.origin)

    def wgs84_to_local(self, lon, lat, h) -> np.ndarray:
        """(lon, lat, h) degrees/metres (scalars or arrays) -> local (..., 3)."""
        e, n = self._from_wgs84.transform(np.asarray(lon, float), np.asarray(lat, float))
        return self.crs_to_local(np.stack([e, n, np.asarray(h, float) * np.ones_like(e)], axis=-1))

    def local_to_wgs84(self, xyz) -> np.ndarray:
        """local (..., 3) -> (..., 3) of (lon, lat, h)."""
        p = self.local_to_crs(xyz)
        lon, lat = self._to_wgs84.transform(p[..., 0], p[..., 1])
        return np.stack([lon, lat, p[..., 2]], axis=-1)

    def from_crs(self, other_spec, xyz) -> np.ndarray:
        """Coordinates in another CRS (x, y, z) -> local."""
        t = Transformer.from_crs(parse_crs(other_spec), self.crs, always_xy=True)
        p = np.asarray(xyz, dtype=np.float64)
        e, n = t.transform(p[..., 0], p[..., 1])
        return self.crs_to_local(np.stack([e, n, p[..., 2]], axis=-1))

    def to_crs(self, other_spec, xyz) -> np.ndarray:
        """local -> coordinates (x, y, z) in another CRS."""
        t = Transformer.from_crs(self.crs, parse_crs(other_spec), always_xy=True)
        p = self.local_to_crs(xyz)
        e, n = t.transform(p[..., 0], p[..., 1])
        return np.stack([e, n, p[..., 2]], axis=-1)
