"""The dataset's kapture folders, written by the ``kapture`` package's own writers
(``kapture.io.csv.kapture_to_dir``, ``kapture.io.records.depth_map_to_file``,
``kapture.io.binary.transfer_files_from_dir``), so kapture's loader and kapture-localization read them.

``kapture/query/``
    sensors: one camera per distinct intrinsics of the published query photos (``wide``,
    ``wide_01`` ...), the zoom cameras of the rig (``zoom`` ...), a GNSS sensor ``gnss`` (EPSG:4326);
    ``rigs``: ``uav`` = the wide cameras (identity) and the zoom cameras (the calibrated
    zoom-from-wide rotation and offset, ``work/rig/rig.json``); ``trajectories``: the published
    pseudo-GT (world-to-camera, project frame); ``records_camera``: the published wide photos and
    their zoom twins; ``records_gnss``: each wide photo's EXIF GPS (x = longitude, y = latitude,
    z = altitude, utc = the EXIF capture time read as UTC, dop = 0: not stated).
``kapture/query_priors/``
    the same photos' sensor priors as poses: the GPS position (geo.txt first) with the gimbal's
    attitude, as trajectories in the same frame (kapture has no attitude record).
``kapture/mapping/``
    the reference photos (``ref``, ``ref_01`` ...) with their SfM poses, and the rendered database
    views (``render`` camera; ``render_depth``: their depth maps as kapture ``.depth`` float32 files,
    metres along the optical axis, 0 where the view sees no surface; ``--no-depth``: none), with the
    views' poses.

Timestamps: microseconds of the EXIF capture time (read as UTC) where every photo states one
(a photo sharing its camera and second with another is moved by 1 us), else the photo's index in
name order; a zoom photo has its wide twin's timestamp; rendered views are numbered 0, 1, ...
"""
from __future__ import annotations

import calendar
import datetime as dt
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..io.exif import read_photo_meta
from ..io.poses import read_intrinsics, read_poses
from ..pose import Pose
from ..project import Project
from .gt import PublishedGT

KAPTURE = "kapture"
GNSS = "gnss"
RIG = "uav"


def _kapture():
    import kapture
    import kapture.io.csv  # noqa: F401 (the writers)
    import kapture.io.records  # noqa: F401

    return kapture


def capture_utc_seconds(stamp: str | None) -> int | None:
    """EXIF ``YYYY:MM:DD HH:MM:SS`` as seconds since 1970 read as UTC (EXIF states no zone), or None."""
    if not stamp:
        return None
    try:
        return calendar.timegm(dt.datetime.strptime(stamp.strip()[:19], "%Y:%m:%d %H:%M:%S").timetuple())
    except ValueError:
        return None


def timestamps(names: list[str], sensor_of: dict[str, str], metas: dict) -> tuple[dict[str, int], str]:
    """Each photo's kapture timestamp and how they were made (see the module doc)."""
    secs = {n: capture_utc_seconds(metas[n].timestamp) if metas.get(n) else None for n in names}
    if not names or any(v is None for v in secs.values()):
        return {n: i for i, n in enumerate(sorted(names))}, "photo index in name order (not every photo states a capture time)"
    out, used = {}, set()
    for n in sorted(names, key=lambda n: (secs[n], n)):
        t = secs[n] * 1_000_000
        while (t, sensor_of[n]) in used:
            t += 1
        used.add((t, sensor_of[n]))
        out[n] = t
    return out, "microseconds of the EXIF capture time, read as UTC"


def sensor_ids(cams: dict[str, Camera], prefix: str) -> tuple[dict[Camera, str], dict[str, str]]:
    """One sensor id per distinct camera (``prefix``, ``prefix_01`` ...), and each photo's."""
    ids: dict[Camera, str] = {}
    for n in sorted(cams):
        if cams[n] not in ids:
            ids[cams[n]] = prefix if not ids else f"{prefix}_{len(ids):02d}"
    return ids, {n: ids[c] for n, c in cams.items()}


def _camera_sensor(kapture, cam: Camera, name: str, sensor_type: str = "camera"):
    return kapture.Camera(cam.model, [cam.width, cam.height, *cam.params], name=name, sensor_type=sensor_type)


def _pose(kapture, p: Pose):
    return kapture.PoseTransform(r=np.asarray(p.q, dtype=np.float64), t=np.asarray(p.t, dtype=np.float64))


def transfer(src_dst: list[tuple[Path, Path]], copy: bool) -> None:
    from kapture.io.binary import TransferAction, transfer_files_from_dir

    if src_dst:
        transfer_files_from_dir([str(Path(s).resolve()) for s, _ in src_dst], [str(d) for _, d in src_dst],
                                TransferAction.copy if copy else TransferAction.link_absolute)


def _records_dir(part: Path) -> Path:
    from kapture.io.records import get_record_fullpath

    return Path(get_record_fullpath(str(part)))


def zoom_twins(project: Project, wide: list[str]) -> dict[str, str]:
    from ..track.calibrate import photo_pairs

    keep = set(wide)
    return {w: z for w, z in photo_pairs(project) if w in keep}


def write_query(out: Path, project: Project, gt: PublishedGT, metas: dict, copy: bool) -> dict:
    """``kapture/query`` and ``kapture/query_priors`` (see the module doc); returns what was written."""
    kapture = _kapture()
    from ..track.rig import Rig

    P = project.paths
    names = sorted(gt.poses)
    cam_ids, sensor_of = sensor_ids(gt.cameras, "wide")
    rig = Rig.load(P.rig) if P.rig.is_file() else None
    zooms = zoom_twins(project, names) if rig is not None else {}
    zoom_cams = {}
    for w, z in zooms.items():
        m = metas.get(z) or read_photo_meta(P.images / z)
        metas[z] = m
        zoom_cams[z] = rig.zoom_camera(m.width, m.height, m.focal_mm)
    zoom_ids, zoom_of = sensor_ids(zoom_cams, "zoom")
    stamps, stamp_rule = timestamps(names, sensor_of, metas)
    sensors, rigs = kapture.Sensors(), kapture.Rigs()
    for cam, sid in cam_ids.items():
        sensors[sid] = _camera_sensor(kapture, cam, "query wide camera")
    for cam, sid in zoom_ids.items():
        sensors[sid] = _camera_sensor(kapture, cam, "query zoom camera")
    if zoom_ids:
        for sid in cam_ids.values():
            rigs[RIG, sid] = kapture.PoseTransform()
        zoom_from_wide = Pose(rig.R_zw, -rig.R_zw @ rig.offset)
        for sid in zoom_ids.values():
            rigs[RIG, sid] = _pose(kapture, zoom_from_wide)
    traj, records, gnss = kapture.Trajectories(), kapture.RecordsCamera(), kapture.RecordsGnss()
    files = []
    part = out / KAPTURE / "query"
    for n in names:
        ts = stamps[n]
        traj[ts, sensor_of[n]] = _pose(kapture, gt.poses[n])
        records[ts, sensor_of[n]] = n
        files.append((P.images / n, _records_dir(part) / n))
        if n in zooms:
            records[ts, zoom_of[zooms[n]]] = zooms[n]
            files.append((P.images / zooms[n], _records_dir(part) / zooms[n]))
        m = metas.get(n)
        if m is not None and m.has_gps and m.altitude is not None:
            gnss[ts, GNSS] = kapture.RecordGnss(float(m.lon), float(m.lat), float(m.altitude),
                                                int(capture_utc_seconds(m.timestamp) or 0), 0.0)
    if len(gnss):
        sensors[GNSS] = kapture.Sensor("gnss", ["EPSG:4326"], name="query photos' EXIF GPS")
    kapture.io.csv.kapture_to_dir(str(part), kapture.Kapture(
        sensors=sensors, rigs=rigs if len(rigs) else None, trajectories=traj, records_camera=records,
        records_gnss=gnss if len(gnss) else None))
    transfer(files, copy)
    info = {"folder": str(part.relative_to(out)), "n_photos": len(names), "n_zoom_photos": len(zooms),
            "n_gnss_records": sum(len(v) for v in gnss.values()), "cameras": sorted(cam_ids.values()),
            "zoom_cameras": sorted(zoom_ids.values()), "rig": bool(zoom_ids), "timestamps": stamp_rule}
    info["priors"] = _write_priors(out, project, names, sensors, cam_ids, sensor_of, stamps, copy)
    return info


def _write_priors(out: Path, project: Project, names: list[str], sensors, cam_ids, sensor_of, stamps, copy) -> dict:
    from ..photo_positions import PhotoPositions

    kapture = _kapture()
    pos = PhotoPositions(project)
    priors = {n: p for n in names if (p := pos.prior_pose(n)) is not None}
    if not priors:
        return {"n_photos": 0, "note": "no photo states both a position and a gimbal attitude"}
    part = out / KAPTURE / "query_priors"
    psens = kapture.Sensors()
    for sid in sorted({sensor_of[n] for n in priors}):
        psens[sid] = sensors[sid]
    traj, records = kapture.Trajectories(), kapture.RecordsCamera()
    for n, p in priors.items():
        traj[stamps[n], sensor_of[n]] = _pose(kapture, p)
        records[stamps[n], sensor_of[n]] = n
    kapture.io.csv.kapture_to_dir(str(part), kapture.Kapture(sensors=psens, trajectories=traj, records_camera=records))
    transfer([(project.paths.images / n, _records_dir(part) / n) for n in priors], copy)
    return {"folder": str(part.relative_to(out)), "n_photos": len(priors)}


def write_mapping(out: Path, project: Project, copy: bool, depth: bool = True) -> dict:
    """``kapture/mapping``: the reference photos and the rendered database (see the module doc);
    without ``depth``, the views without their depth maps."""
    kapture = _kapture()
    P = project.paths
    part = out / KAPTURE / "mapping"
    sensors, traj = kapture.Sensors(), kapture.Trajectories()
    records, depths = kapture.RecordsCamera(), kapture.RecordsDepth()
    files, info = [], {"folder": str(part.relative_to(out)), "n_reference_photos": 0, "n_rendered_views": 0}
    if P.reference_poses.is_file() and P.reference_intrinsics.is_file():
        poses, cams = read_poses(P.reference_poses), read_intrinsics(P.reference_intrinsics)
        cams = {n: cams[n] for n in poses if n in cams}
        ids, sensor_of = sensor_ids(cams, "ref")
        for cam, sid in ids.items():
            sensors[sid] = _camera_sensor(kapture, cam, "reference camera")
        metas = {n: _meta(P.images / n) for n in cams}
        stamps, rule = timestamps(sorted(cams), sensor_of, metas)
        for n in sorted(cams):
            traj[stamps[n], sensor_of[n]] = _pose(kapture, poses[n])
            records[stamps[n], sensor_of[n]] = n
            files.append((P.images / n, _records_dir(part) / n))
        info.update(n_reference_photos=len(cams), reference_cameras=sorted(ids.values()), reference_timestamps=rule)
    views = _database(project)
    if views is not None:
        from ..localize.database import read_depth

        cam, dbviews = views
        sensors["render"] = _camera_sensor(kapture, cam, "render-db view")
        if depth:
            sensors["render_depth"] = _camera_sensor(kapture, cam, "render-db depth", sensor_type="depth")
        for i, v in enumerate(dbviews):
            rgb, dep = f"render_db/{v.name}.jpg", f"render_db/{v.name}.depth"
            traj[i, "render"] = _pose(kapture, v.pose)
            records[i, "render"] = rgb
            files.append((v.image, _records_dir(part) / rgb))
            if not depth:
                continue
            traj[i, "render_depth"] = _pose(kapture, v.pose)
            depths[i, "render_depth"] = dep
            d = read_depth(v.depth_path)
            d = np.zeros((cam.height, cam.width), np.float32) if d is None else np.nan_to_num(d.astype(np.float32), nan=0.0)
            kapture.io.records.depth_map_to_file(str(_records_dir(part) / dep), d)
        info.update(n_rendered_views=len(dbviews), n_depth_maps=len(dbviews) if depth else 0, render_camera=cam.to_line())
    if not len(sensors):
        return {}
    kapture.io.csv.kapture_to_dir(str(part), kapture.Kapture(
        sensors=sensors, trajectories=traj, records_camera=records, records_depth=depths if len(depths) else None))
    transfer(files, copy)
    return info


def _meta(path: Path):
    from ..errors import GtkitError

    try:
        return read_photo_meta(path)
    except GtkitError:
        return None


def _database(project: Project):
    """(camera, kept views) of the rendered database, or None where there is none."""
    from ..errors import GtkitError
    from ..localize.database import load_database

    try:
        db = load_database(project)
    except GtkitError:
        return None
    return (db.camera, db.views) if db.views else None


def image_root(out: Path) -> Path:
    return _records_dir(out / KAPTURE / "query")

