"""Which reference photos probably overlap a query photo.

With intrinsics (``cameras.txt``): a 12 x 9 grid of the query's pixel rays is intersected with
the ground (a plane at the site's ground height) and projected into every reference; the
references are ranked by the share of those ground points they see (ties: nearer first).
Without intrinsics: by the distance between the points where the optical axes meet the ground.

Poses come from the registration (pseudo-GT poses) when available, else from the photos'
priors (EXIF GPS + DJI gimbal angles). No Qt here.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from gtkit.errors import GtkitError
from gtkit.photo_positions import PhotoPositions
from gtkit.pose import Pose

log = logging.getLogger(__name__)


def ground_height(paths, frame) -> float:
    """A rough ground height (world z): the 5th percentile of the reference model's vertex
    heights read from the first few MB of the OBJ; 0 when there is no model."""
    obj = paths.model / "reference.obj"
    if not obj.is_file():
        return 0.0
    zs = []
    with open(obj, "rb") as f:
        for line in f.read(4 << 20).splitlines():
            if line.startswith(b"v "):
                parts = line.split()
                if len(parts) >= 4:
                    zs.append(float(parts[3]))
    if not zs:
        return 0.0
    z = float(np.percentile(zs, 5))
    side = Path(str(obj) + ".offset.json")
    if side.is_file():
        try:
            z += float(json.loads(side.read_text())["offset"][2])
        except (KeyError, ValueError, IndexError, json.JSONDecodeError):
            pass
    return z - float(frame.origin[2])


def axis_ground_point(pose: Pose, z_ground: float, max_range: float = 2000.0) -> np.ndarray:
    """Where the optical axis meets the plane z = z_ground (capped at ``max_range`` metres)."""
    C = pose.center
    d = pose.R.T @ np.array([0.0, 0.0, 1.0])
    if d[2] < -1e-3:
        t = min((z_ground - C[2]) / d[2], max_range)
    else:
        t = max_range
    return C + max(t, 0.0) * d


class OverlapRanker:
    """Ground points of every photo, computed once; ranks references for a query."""

    def __init__(self, paths, frame, poses: dict[str, Pose] | None = None, cache_file: Path | None = None):
        self.paths, self.frame = paths, frame
        self.positions = PhotoPositions.of(paths, frame)   # geo.txt first, else EXIF GPS
        self.poses = dict(poses or {})
        self.z_ground = ground_height(paths, frame)
        self._points: dict[str, np.ndarray | None] = {}
        # prior ground points keyed by file size + mtime, so big projects open fast the second time
        self.cache_file = cache_file
        self._disk: dict = {}
        if cache_file is not None and Path(cache_file).is_file():
            try:
                d = json.loads(Path(cache_file).read_text())
                if d.get("z_ground") == self.z_ground:
                    self._disk = d.get("points", {})
            except (OSError, json.JSONDecodeError):
                self._disk = {}
        self._dirty = False

    def pose(self, name: str) -> Pose | None:
        if name in self.poses:
            return self.poses[name]
        return self.positions.prior_pose(name)

    def _stamp(self, name: str) -> str:
        try:
            st = (self.paths.images / name).stat()
            return f"{st.st_size}-{st.st_mtime_ns}"
        except OSError:
            return ""

    def point(self, name: str) -> np.ndarray | None:
        if name not in self._points:
            if name not in self.poses and name in self._disk and self._disk[name][0] == self._stamp(name):
                v = self._disk[name][1]
                self._points[name] = None if v is None else np.array(v)
            else:
                p = self.pose(name)
                self._points[name] = None if p is None else axis_ground_point(p, self.z_ground)
                if name not in self.poses:
                    v = self._points[name]
                    self._disk[name] = [self._stamp(name), None if v is None else [float(x) for x in v]]
                    self._dirty = True
        return self._points[name]

    def save_cache(self) -> None:
        if self.cache_file is not None and self._dirty:
            from gtkit.io.atomic import write_json

            write_json(self.cache_file, {"z_ground": self.z_ground, "points": self._disk})
            self._dirty = False

    @property
    def cameras(self) -> dict:
        if not hasattr(self, "_cameras"):
            from gtkit.io.poses import read_intrinsics

            try:
                self._cameras = read_intrinsics(self.paths.cameras) if self.paths.cameras.is_file() else {}
            except GtkitError as e:
                log.warning("%s", e)
                self._cameras = {}
        return self._cameras

    def footprint(self, name: str, n=(12, 9)) -> np.ndarray | None:
        """Ground points (N, 3) seen by a grid of the photo's pixel rays (None without a pose/camera)."""
        pose, cam = self.pose(name), self.cameras.get(name)
        if pose is None or cam is None:
            return None
        u, v = np.meshgrid((np.arange(n[0]) + 0.5) / n[0] * cam.width, (np.arange(n[1]) + 0.5) / n[1] * cam.height)
        d = cam.rays(np.stack([u.ravel(), v.ravel()], 1)) @ pose.R  # world directions
        C = pose.center
        down = d[:, 2] < -1e-3
        t = np.where(down, (self.z_ground - C[2]) / np.where(down, d[:, 2], -1.0), np.nan)
        t = np.where((t > 0) & (t < 2000.0), t, np.nan)
        pts = C + t[:, None] * d
        pts = pts[np.isfinite(pts).all(1)]
        return pts if len(pts) else None

    def predictor(self, query: str, ref: str):
        """A function: query pixels (N, 2) -> where they should be in ``ref`` (N, 2), through the
        ground plane with the two photos' poses (prior or registered); None without poses/cameras.
        Buildings and pose errors make it approximate: used as a wide gate for suggestions."""
        pq, cq, pr, cr = self.pose(query), self.cameras.get(query), self.pose(ref), self.cameras.get(ref)
        if None in (pq, cq, pr, cr):
            return None
        zg = self.z_ground

        def predict(uv: np.ndarray) -> np.ndarray:
            d = cq.rays(np.asarray(uv, float)) @ pq.R
            C = pq.center
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(d[:, 2] < -1e-3, (zg - C[2]) / d[:, 2], np.nan)
            X = C + t[:, None] * d
            out, front = cr.project(pr.transform(X))
            out[~front | ~np.isfinite(t)] = np.nan
            return out

        return predict

    def overlap(self, query_points: np.ndarray, ref: str) -> float | None:
        pose, cam = self.pose(ref), self.cameras.get(ref)
        if pose is None or cam is None:
            return None
        uv, front = cam.project(pose.transform(query_points))
        return float(np.mean(front & cam.in_image(uv)))

    def rank(self, query: str, references: list[str]) -> list[tuple[str, float, float | None]]:
        """(reference, distance in metres between axis ground points, overlap share or None),
        most overlap first (then nearest); references without a pose last, in name order."""
        q = self.point(query)
        fp = self.footprint(query)
        out = []
        for r in references:
            p = self.point(r)
            d = float(np.linalg.norm((p - q)[:2])) if (p is not None and q is not None) else float("inf")
            ov = self.overlap(fp, r) if fp is not None else None
            out.append((r, d, ov))
        self.save_cache()
        return sorted(out, key=lambda x: (-(x[2] or 0.0), x[1], x[0]))
