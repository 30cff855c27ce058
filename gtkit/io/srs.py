"""Spatial reference systems as photogrammetry packages write them, mapped into the project frame.

ContextCapture (``metadata.xml``, BlocksExchange ``<SRS><Definition>``) writes an SRS as
``EPSG:n``, WKT, a PROJ string, or ``ENU:lat,lon`` (a local east-north-up tangent plane at that
WGS84 point, height 0 on the ellipsoid). :class:`SrsToWorld` maps points given in such an SRS
(plus an origin added to them, ``SRSOrigin``) into the project's world frame
(:mod:`gtkit.conventions`), and gives the rotation that carries directions along, so that
world-to-camera rotations expressed against the SRS axes can be re-expressed against the
world axes.

When the SRS is the project's CRS the mapping is a pure translation, done in float64 with
no reprojection, so round trips are exact. Otherwise each point is reprojected through
pyproj; directions are rotated by the orthonormalised Jacobian of that map at the point
(meridian convergence, ENU-to-grid rotation). Heights pass through unchanged (no datum
change), as everywhere in gtkit.
"""
from __future__ import annotations

import re
from functools import cached_property

import numpy as np

from ..errors import GtkitError

_ENU = re.compile(r"^\s*ENU\s*:\s*([-+0-9.eE]+)\s*,\s*([-+0-9.eE]+)\s*$", re.IGNORECASE)


def parse_enu(spec: str) -> tuple[float, float] | None:
    """``ENU:lat,lon`` -> (lat, lon) degrees; None when ``spec`` is not an ENU definition."""
    m = _ENU.match(str(spec))
    if not m:
        return None
    lat, lon = float(m.group(1)), float(m.group(2))
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise GtkitError(f"ENU origin out of range: {spec!r}")
    return lat, lon


def srs_key(spec: str) -> str:
    """A canonical name for comparing two SRS definitions (EPSG code, ENU origin, or WKT)."""
    enu = parse_enu(spec)
    if enu is not None:
        return f"ENU:{enu[0]:.9f},{enu[1]:.9f}"
    from ..geo import crs_name, parse_crs

    return crs_name(parse_crs(spec))


def _orthonormal(J: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(J)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


class SrsToWorld:
    """Map ``srs`` coordinates (+ ``srs_origin``) into a project frame (:class:`gtkit.geo.GeoFrame`)."""

    def __init__(self, spec: str, frame, srs_origin=(0.0, 0.0, 0.0), source=None):
        self.spec = str(spec).strip()
        self.frame = frame
        self.source = source
        self.origin = np.asarray(srs_origin, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(self.origin)):
            raise GtkitError(f"SRS origin is not finite: {srs_origin!r}", source)
        self.enu = parse_enu(self.spec)
        self.crs = None
        if self.enu is None:
            from ..geo import parse_crs

            if not self.spec:
                raise GtkitError("empty SRS definition", source)
            try:
                self.crs = parse_crs(self.spec, source)
            except GtkitError:
                raise GtkitError(f"SRS cannot be understood: {self.spec[:120]!r} "
                                 "(expected EPSG:n, WKT, a PROJ string or ENU:lat,lon)", source) from None
            if self.crs.is_geographic:
                raise GtkitError(f"SRS {self.spec[:80]!r} is geographic (degrees); a Cartesian or "
                                 "projected SRS is needed for models and poses", source)

    # --- the map -----------------------------------------------------------------------
    @cached_property
    def is_translation(self) -> bool:
        """True when the SRS is the project's CRS (points only shift by origin differences)."""
        return self.crs is not None and self.crs.equals(self.frame.crs)

    @cached_property
    def shift(self) -> np.ndarray:
        """world = srs_xyz + shift, when :attr:`is_translation`."""
        return self.origin - np.asarray(self.frame.origin, dtype=np.float64)

    @cached_property
    def _enu_pipeline(self):
        from pyproj import Transformer

        lat, lon = self.enu
        return Transformer.from_pipeline(
            "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            "+step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat!r} +lon_0={lon!r} +h_0=0")

    def points(self, xyz) -> np.ndarray:
        """(..., 3) coordinates as stored (before adding the SRS origin) -> world frame."""
        p = np.asarray(xyz, dtype=np.float64)
        if self.is_translation:
            return p + self.shift
        q = p + self.origin
        shape = q.shape
        q = q.reshape(-1, 3)
        if self.enu is not None:
            lon, lat, h = self._enu_pipeline.transform(q[:, 0], q[:, 1], q[:, 2], direction="INVERSE")
            out = self.frame.from_crs("EPSG:4326", np.stack([lon, lat, h], -1))
        else:
            if self.crs.is_geocentric:
                from pyproj import Transformer

                t = Transformer.from_crs(self.crs, "EPSG:4979", always_xy=True)
                lon, lat, h = t.transform(q[:, 0], q[:, 1], q[:, 2])
                out = self.frame.from_crs("EPSG:4326", np.stack([lon, lat, h], -1))
            else:
                out = self.frame.from_crs(self.crs, q)
        return out.reshape(shape)

    def rotation_at(self, xyz, step: float = 1.0) -> np.ndarray:
        """3x3 rotation taking SRS directions to world directions near a point (as stored)."""
        if self.is_translation:
            return np.eye(3)
        p = np.asarray(xyz, dtype=np.float64).reshape(3)
        d = np.vstack([p + step * e for e in np.eye(3)] + [p - step * e for e in np.eye(3)])
        w = self.points(d)
        J = (w[:3] - w[3:]).T / (2 * step)  # columns: world image of each SRS axis
        return _orthonormal(J)

    # --- the inverse (for writers) --------------------------------------------------------
    def world_to_srs(self, xyz) -> np.ndarray:
        """World frame -> SRS coordinates minus the SRS origin (translation case only)."""
        if not self.is_translation:
            raise GtkitError("writing into an SRS other than the project CRS is not supported")
        return np.asarray(xyz, dtype=np.float64) - self.shift
