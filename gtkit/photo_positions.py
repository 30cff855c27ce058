"""Photo positions in the project frame, the one reader of where a photo was taken: the project's
``geo.txt`` first (a user's surveyed or corrected positions, ODM's format, with its accuracy where the
line states one), else the photo's EXIF GPS and altitude. A ``geo.txt`` line without a height, or a
photo with GPS but no altitude, gives no position (a height of 0 is not a position).
Below the stages: it reads the project's files through gtkit.io and gtkit.project only."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import GtkitError
from .geo import GeoFrame
from .io.exif import PhotoMeta, read_photo_meta
from .io.odm import GeoEntry, read_geo_txt
from .pose import Pose
from .project import Paths, Project


@dataclass(frozen=True)
class PhotoPosition:
    xyz: np.ndarray                  # camera centre, project frame (metres)
    source: str                      # "geo.txt" or "exif"
    accuracy_m: float | None = None  # geo.txt's stated accuracy (the larger of horizontal and vertical)
    accuracy_hv: tuple[float, float] | None = None   # ... and both: (horizontal, vertical), metres


class PhotoPositions:
    """The photos' positions of one project; ``geo.txt`` is read once, when first needed.
    ``PhotoPositions(project)``, or ``PhotoPositions.of(paths, frame)`` where only those are at hand."""

    def __init__(self, project: Project):
        self.paths, self.frame = project.paths, project.frame
        self._geo: dict[str, GeoEntry] | None = None

    @classmethod
    def of(cls, paths: Paths, frame: GeoFrame) -> "PhotoPositions":
        new = cls.__new__(cls)
        new.paths, new.frame, new._geo = paths, frame, None
        return new

    @property
    def geo(self) -> dict[str, GeoEntry]:
        """``geo.txt``'s lines by image name ({} without the file)."""
        if self._geo is None:
            P = self.paths
            self._geo = read_geo_txt(P.geo_txt, self.frame) if P.geo_txt.is_file() else {}
        return self._geo

    def from_geo_txt(self, name: str) -> PhotoPosition | None:
        """The photo's ``geo.txt`` position (its line named by its path under images/ or its file name)."""
        g = self.geo.get(name) or self.geo.get(Path(name).name)
        if g is None or not np.all(np.isfinite(g.xyz)):
            return None
        if g.accuracy and max(g.accuracy) > 0:
            h, v = (float(a) for a in g.accuracy)
            h, v = h if h > 0 else v, v if v > 0 else h     # one column stated: both
            return PhotoPosition(g.xyz, "geo.txt", max(h, v), (h, v))
        return PhotoPosition(g.xyz, "geo.txt")

    def get(self, name: str, meta: PhotoMeta | None = None) -> PhotoPosition | None:
        """The photo's position (``meta``: its metadata where already read); None without one. An
        unreadable photo that geo.txt does not place: GtkitError."""
        p = self.from_geo_txt(name)
        if p is not None:
            return p
        m = meta if meta is not None else read_photo_meta(self.paths.images / name, require=())
        if m.has_gps and m.altitude is not None:
            return PhotoPosition(self.frame.wgs84_to_local(m.lon, m.lat, m.altitude), "exif")
        return None

    def prior_pose(self, name: str) -> Pose | None:
        """The pose the photo's metadata claims: its position (geo.txt first, else EXIF GPS and
        altitude) with the DJI gimbal's attitude; None where the photo cannot say (unreadable, no
        gimbal angles, no position)."""
        try:
            m = read_photo_meta(self.paths.images / name)
        except GtkitError:
            return None
        if not m.has_gimbal:
            return None
        try:
            p = self.get(name, m)
        except GtkitError:
            return None
        if p is None:
            return None
        return Pose.from_dji(m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll, p.xyz)

    def centre(self, name: str) -> np.ndarray | None:
        """The photo's position, None without one or where geo.txt does not place it and the photo
        cannot be read (a malformed geo.txt is an error)."""
        p = self.from_geo_txt(name)
        if p is None:
            try:
                p = self.get(name)
            except GtkitError:
                return None
        return None if p is None else p.xyz


def positions_and_accuracy(project: Project, names: list[str], metas: dict | None = None, per_axis: bool = False
                           ) -> tuple[dict[str, np.ndarray], dict]:
    """Camera positions (geo.txt first, else EXIF GPS + altitude) and, where geo.txt states one, each
    position's accuracy (metres, the larger of horizontal and vertical; ``per_axis``: both, as
    (horizontal, vertical)). ``metas``: the photos' metadata already read; a photo missing there is read
    here (unreadable: GtkitError). The same as ``gtkit.sfm.blocks.gps_positions_and_accuracy``."""
    reader = PhotoPositions(project)
    out, acc = {}, {}
    for n in names:
        p = reader.get(n, (metas or {}).get(n))
        if p is None:
            continue
        out[n] = p.xyz
        if p.accuracy_m is not None:
            acc[n] = p.accuracy_hv if per_axis else p.accuracy_m
    return out, acc
