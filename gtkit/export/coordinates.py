"""Coordinates out: camera positions/attitudes and targets as CSV and GeoJSON, in WGS84 and in
the project CRS, and camera positions in OpenDroneMap's ``geo.txt`` format.

Heights are never converted: they are the inputs' heights (for DJI/GPS data ellipsoidal
heights above WGS 84), and every file says so. Angles are DJI-style yaw/pitch/roll in degrees
(:func:`gtkit.conventions.rotation_to_dji`) with yaw measured from *grid* north (the CRS's
y axis), which differs from true north by the meridian convergence (< ~2 deg in a UTM zone).

Files written to ``exports/coordinates/`` (``<what>`` = ``cameras`` or ``targets``)::

    <what>.csv               name, easting, northing, height, lon, lat, [yaw, pitch, roll], extras
    <what>_wgs84.geojson     RFC 7946 (lon, lat, height), properties include the CRS coordinates
    <what>_crs.geojson       coordinates in the project CRS (named in a "crs" member)
    geo.txt                  ODM: first line the CRS, then ``image_name geo_x geo_y geo_z yaw pitch roll``

Targets come from a CSV given by the caller (a tracking result, surveyed marks) whose header
names the coordinate columns: ``x,y,z`` or ``easting,northing,height`` (project CRS),
``lon,lat,height`` (WGS84) or ``world_x,world_y,world_z`` (world frame); rows without
coordinates are skipped; other columns (label, time, ...) are carried along. By default the
tracking stage's ``exports/tracks.csv`` is used when present.
The ground control points of ``gcp_list.txt`` are exported as targets ``gcp_<name>`` too.
"""
from __future__ import annotations

import csv
import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..conventions import rotation_to_dji
from ..errors import GtkitError
from ..geo import GeoFrame, crs_name, parse_crs
from ..io.atomic import write_text
from ..io.poses import read_poses
from ..project import Project, file_fingerprint, mark_stage_done, stage_done

log = logging.getLogger(__name__)

STAGE = "export_coordinates"
HEIGHT_NOTE = "heights in metres as given by the inputs (GPS/DJI: ellipsoidal, WGS 84); not converted"
# where the pose stages write their results: the pseudo-GT of the query photos (gtkit register)
# and the georegistered reference block; all that exist are exported, the first wins a name clash
POSE_STAGES = ("register", "sfm_reference")


@dataclass
class CoordinatesSettings:
    poses: str | None = None      # pose file (name qw qx qy qz tx ty tz); None = the pseudo-GT + reference poses
    targets: str | None = None    # targets CSV (see module doc); None = exports/tracks.csv (gtkit track) if present
    include_gcps: bool = True     # also export gcp_list.txt's points as targets


@dataclass
class GeoPoint:
    name: str
    xyz: np.ndarray                     # world frame
    angles: tuple[float, float, float] | None = None  # yaw, pitch, roll (deg)
    extra: dict | None = None


def default_pose_files(project: Project) -> list[Path]:
    return [f for f in map(project.paths.poses, POSE_STAGES) if f.is_file()]


def cameras_from_poses(paths: list[Path]) -> list[GeoPoint]:
    poses = {}
    for path in paths:
        for name, pose in read_poses(path).items():
            poses.setdefault(name, pose)
    return [GeoPoint(name, pose.center, rotation_to_dji(pose.R)) for name, pose in sorted(poses.items())]


def targets_from_csv(path: Path, frame: GeoFrame) -> list[GeoPoint]:
    """Targets from a CSV with a header naming x,y,z or easting,northing,height or lon,lat,height."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("targets file not found", path)
    rows = list(csv.DictReader(line for line in path.read_text(encoding="utf-8").splitlines()
                               if line.strip() and not line.startswith("#")))
    if not rows:
        return []
    cols = {c.strip().lower(): c for c in rows[0].keys() if c is not None}
    h_col = next((cols[c] for c in ("height", "h", "z", "alt", "altitude") if c in cols), None)
    name_col = next((cols[c] for c in ("name", "id", "label", "target") if c in cols), None)
    if {"world_x", "world_y", "world_z"} <= cols.keys():
        kind, keys = "world", (cols["world_x"], cols["world_y"], cols["world_z"])
    elif {"x", "y", "z"} <= cols.keys():
        kind, keys = "crs", (cols["x"], cols["y"], cols["z"])
    elif {"easting", "northing"} <= cols.keys() and h_col:
        kind, keys = "crs", (cols["easting"], cols["northing"], h_col)
    elif {"lon", "lat"} <= cols.keys() and h_col:
        kind, keys = "wgs84", (cols["lon"], cols["lat"], h_col)
    else:
        raise GtkitError("header must name x,y,z or easting,northing,height (project CRS), lon,lat,height "
                         "(WGS84) or world_x,world_y,world_z columns", path)
    derived = {cols[c] for c in ("lon", "lat", "h", "easting", "northing", "height", "x", "y", "z") if c in cols}
    out = []
    for n, r in enumerate(rows, 2):
        if all(not (r.get(k) or "").strip() for k in keys):
            continue  # a row without coordinates (e.g. a detection that was not located)
        try:
            v = np.array([float(r[k]) for k in keys])
        except (TypeError, ValueError):
            raise GtkitError(f"line {n}: coordinates are not numbers", path) from None
        xyz = v if kind == "world" else frame.crs_to_local(v) if kind == "crs" else frame.wgs84_to_local(*v)
        extra = {k: r[k] for k in r if k is not None and k not in keys and k != name_col and k not in derived}
        out.append(GeoPoint(str(r[name_col]) if name_col else f"target_{n - 1}", np.asarray(xyz, float), None, extra))
    return out


def targets_from_gcp_list(path: Path, frame: GeoFrame) -> list[GeoPoint]:
    """The distinct ground control points of an ODM gcp_list.txt (first line CRS)."""
    lines = [s for s in Path(path).read_text(encoding="utf-8").splitlines() if s.strip() and not s.startswith("#")]
    if not lines:
        return []
    gcp_crs = parse_crs(lines[0].strip(), path)
    seen: dict[str, np.ndarray] = {}
    for n, s in enumerate(lines[1:], 2):
        f = s.split()
        if len(f) < 6:
            raise GtkitError(f"line {n}: expected 'geo_x geo_y geo_z px py image [name]'", path)
        xyz = np.array([float(v) for v in f[:3]])
        name = f[6] if len(f) > 6 else "%.3f_%.3f_%.3f" % tuple(xyz)
        seen.setdefault(name, xyz)
    names = sorted(seen)
    if not names:
        return []
    world = frame.from_crs(gcp_crs.to_wkt(), np.stack([seen[k] for k in names]))
    return [GeoPoint(f"gcp_{k}", w, None, {"source": "gcp_list.txt"}) for k, w in zip(names, world)]


def _table(points: list[GeoPoint], frame: GeoFrame) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.stack([p.xyz for p in points])
    return frame.local_to_crs(xyz), frame.local_to_wgs84(xyz)


def write_csv(path: Path, points: list[GeoPoint], frame: GeoFrame) -> Path:
    crs, wgs = _table(points, frame)
    with_angles = any(p.angles is not None for p in points)
    extra_keys = sorted({k for p in points for k in (p.extra or {})})
    buf = io.StringIO()
    buf.write(f"# easting/northing: {crs_name(frame.crs)} (metres); lon/lat: WGS84 degrees; {HEIGHT_NOTE}"
              + ("; yaw/pitch/roll: DJI convention in degrees, yaw from grid north" if with_angles else "") + "\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["name", "easting", "northing", "height", "lon", "lat"]
               + (["yaw", "pitch", "roll"] if with_angles else []) + extra_keys)
    for p, c, g in zip(points, crs, wgs):
        row = [p.name, f"{c[0]:.4f}", f"{c[1]:.4f}", f"{c[2]:.4f}", f"{g[0]:.9f}", f"{g[1]:.9f}"]
        if with_angles:
            row += [f"{a:.4f}" for a in p.angles] if p.angles is not None else ["", "", ""]
        row += [(p.extra or {}).get(k, "") for k in extra_keys]
        w.writerow(row)
    return write_text(path, buf.getvalue())


def write_geojson(path: Path, points: list[GeoPoint], frame: GeoFrame, in_crs: bool) -> Path:
    crs, wgs = _table(points, frame)
    feats = []
    for p, c, g in zip(points, crs, wgs):
        props = {"name": p.name, "easting": round(float(c[0]), 4), "northing": round(float(c[1]), 4),
                 "height": round(float(c[2]), 4), "lon": round(float(g[0]), 9), "lat": round(float(g[1]), 9)}
        if p.angles is not None:
            props.update(yaw=round(p.angles[0], 4), pitch=round(p.angles[1], 4), roll=round(p.angles[2], 4))
        props.update(p.extra or {})
        coords = [round(float(c[0]), 4), round(float(c[1]), 4), round(float(c[2]), 4)] if in_crs else \
            [round(float(g[0]), 9), round(float(g[1]), 9), round(float(g[2]), 4)]
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": coords}, "properties": props})
    doc = {"type": "FeatureCollection", "name": path.stem,
           "gtkit": {"crs": crs_name(frame.crs), "coordinates": "project CRS" if in_crs else "WGS84 lon/lat",
                     "heights": HEIGHT_NOTE,
                     "angles": "DJI yaw/pitch/roll in degrees, yaw from grid north"},
           "features": feats}
    if in_crs:
        code = frame.crs.to_epsg()
        doc["crs"] = {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{code}" if code
                                                     else frame.crs.to_wkt()}}
    return write_text(path, json.dumps(doc, indent=1) + "\n")


def write_geo_txt(path: Path, cameras: list[GeoPoint], frame: GeoFrame) -> Path:
    """OpenDroneMap's image geolocation file: the CRS, then one image a line. Image names are
    file names (ODM's images folder is flat) unless two share a name, then paths under images/."""
    crs, _ = _table(cameras, frame)
    base = [Path(p.name).name for p in cameras]
    names = base if len(set(base)) == len(base) else [p.name for p in cameras]
    lines = [crs_name(frame.crs)]
    for n, p, c in zip(names, cameras, crs):
        a = p.angles or (0.0, 0.0, 0.0)
        lines.append(f"{n} {c[0]:.4f} {c[1]:.4f} {c[2]:.4f} {a[0]:.4f} {a[1]:.4f} {a[2]:.4f}")
    return write_text(path, "\n".join(lines) + "\n")


def run(project: Project | str | Path, settings: CoordinatesSettings,
        out_dir: str | Path | None = None) -> dict[str, Path]:
    """Write camera and target coordinates; returns {file kind: path}."""
    proj = project if isinstance(project, Project) else Project.load(project)
    frame = proj.frame
    out_dir = Path(out_dir) if out_dir is not None else proj.paths.coordinates
    pose_files = [Path(settings.poses)] if settings.poses else default_pose_files(proj)
    targets_file = Path(settings.targets) if settings.targets else (
        proj.paths.tracks if proj.paths.tracks.is_file() else None)
    gcp = proj.paths.gcp_list if settings.include_gcps and proj.paths.gcp_list.is_file() else None
    inputs = {str(p): file_fingerprint(p) for p in (*pose_files, targets_file, gcp) if p}
    inputs.update(crs=frame.crs_spec, origin=list(frame.origin), out=str(out_dir))
    stage_dir = proj.paths.stage(STAGE)
    if stage_done(stage_dir, settings, inputs) and out_dir.is_dir():  # stage_done first: it starts the clock and the log
        log.info("coordinates in %s are up to date; skipping", out_dir)
        return {p.name: p for p in sorted(out_dir.iterdir()) if p.is_file()}
    written: dict[str, Path] = {}
    if not pose_files:
        log.warning("no pose file (give --poses; looked for %s)",
                    ", ".join(str(proj.paths.poses(s).relative_to(proj.paths.root)) for s in POSE_STAGES))
    else:
        cams = cameras_from_poses(pose_files)
        if cams:
            written["cameras.csv"] = write_csv(out_dir / "cameras.csv", cams, frame)
            written["cameras_wgs84.geojson"] = write_geojson(out_dir / "cameras_wgs84.geojson", cams, frame, False)
            written["cameras_crs.geojson"] = write_geojson(out_dir / "cameras_crs.geojson", cams, frame, True)
            written["geo.txt"] = write_geo_txt(out_dir / "geo.txt", cams, frame)
    targets: list[GeoPoint] = []
    if targets_file is not None:
        targets += targets_from_csv(targets_file, frame)
    if gcp is not None:
        targets += targets_from_gcp_list(gcp, frame)
    if targets:
        written["targets.csv"] = write_csv(out_dir / "targets.csv", targets, frame)
        written["targets_wgs84.geojson"] = write_geojson(out_dir / "targets_wgs84.geojson", targets, frame, False)
        written["targets_crs.geojson"] = write_geojson(out_dir / "targets_crs.geojson", targets, frame, True)
    if not written:
        raise GtkitError("nothing to export: no pose file (give --poses) and no targets (give --targets)",
                         proj.paths.root)
    mark_stage_done(stage_dir, settings, inputs, files=sorted(written), pose_files=[str(p) for p in pose_files],
                    targets_file=str(targets_file) if targets_file else None)
    log.info("coordinates: %s in %s", ", ".join(written), out_dir)
    return written
