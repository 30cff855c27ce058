"""The tracking stage: detections in zoom photos -> 3D target positions on the DSM -> tracks.

Per detection: the zoom photo's wide twin (``<idx>_Z`` -> ``<idx>_W``) gives the localized wide
pose; the rig gives the zoom pose and camera; the foot-point pixel's ray is marched against the
DSM to its first crossing (:mod:`gtkit.track.raycast`); the pose covariance (or the default
sigmas) is propagated to the point by sampling (:mod:`gtkit.track.uncertainty`). A detection
that cannot be placed gets a status and a message and no coordinate (no wide pose, the ray
misses the DSM, ...). Per label and sequence, the placed points form a track, optionally RTS-smoothed
(:mod:`gtkit.track.smoothing`).

Outputs: ``exports/tracks.csv`` (one row per detection: CRS and WGS84 coordinates, height,
sigmas, status, message; smoothed coordinates when enabled; ``on_filled_dsm`` 1 when the target
landed on a DSM cell whose height was interpolated over a gap, not measured: see
:mod:`gtkit.export.gapfill`), ``exports/tracks.geojson``
(WGS84 points and one line per track), ``work/track/stage.json``.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_json, write_text
from ..io.exif import read_photo_meta
from ..io.poses import read_covariances, read_poses
from ..pose import Pose
from ..project import (Project, file_fingerprint, mark_stage_done, relative_paths, resolve_path, settings_dict,
                       stage_done, start_stage_clock)
from .calibrate import query_photos, wide_name_for
from .raycast import MESSAGES, cast_rays
from .rig import Rig
from .smoothing import SmoothingSettings, smooth_track
from .targets import Detection, read_detections, resolve_images
from .uncertainty import UncertaintySettings, ground_point_covariance

log = logging.getLogger(__name__)
STAGE = "track"


@dataclass
class TrackSettings:
    detections: str = ""           # CSV / labelme JSON / folder; "" = the project's detections.csv
    poses: str = ""                # wide poses (world-to-camera); "" = work/localize/poses.txt
    covariances: str = ""          # 6x6 pose covariances; "" = covariances.txt beside the poses, if any
    foot_point: str = "centre"     # for boxes: "centre" (lifted, below) or "bottom_centre" (see targets.py)
    centre_height: dict = field(default_factory=lambda: {"car": 1.5, "person": 1.7, "default": 1.5})
    # with foot_point="centre": a box's centre is the image of the target's body centre, half its
    # height (m, by label; "default" for other labels) above the ground, so its ray is cast on
    # DSM + height/2 and the ground point below is reported. Pixel detections are used as they are.
    smooth: bool = True            # RTS-smoothed track per label (sequences)
    step_m: float = 0.0            # ray-marching step; 0 = half a DSM cell
    tol_m: float = 0.01            # bisection tolerance along the ray
    rig_sigma_deg: float = 0.0     # extra rotation noise of the rig (0 = use the calibration's sigma)
    uncertainty: UncertaintySettings = field(default_factory=UncertaintySettings)
    smoothing: SmoothingSettings = field(default_factory=SmoothingSettings)


class _Lifted:
    """A DSM raised by ``dz`` metres (for rays aimed at a target's body centre)."""

    def __init__(self, dsm, dz: float):
        self.dsm, self.dz = dsm, float(dz)
        self.grid = dsm.grid
        self.heights = dsm.heights + self.dz
        self.path = getattr(dsm, "path", None)

    def height_at(self, x, y):
        return self.dsm.height_at(x, y) + self.dz


def resolve(project: Project, value: str, default: Path) -> Path:
    if not value:
        return default
    p = Path(value)
    return p if p.is_absolute() else (project.paths.root / p if (project.paths.root / p).exists() else p)


def exif_seconds(stamp: str | None) -> float | None:
    if not stamp:
        return None
    for fmt in ("%Y:%m:%d %H:%M:%S", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d %H:%M:%S"):
        try:
            return datetime.strptime(stamp.strip(), fmt).replace(tzinfo=timezone.utc).timestamp()
        except ValueError:
            continue
    return None


def load_inputs(project: Project, s: TrackSettings):
    from ..export.dsm import Dsm

    P = project.paths
    det_path = resolve(project, s.detections, P.detections)
    pose_path = resolve(project, s.poses, P.localized_poses)
    if not pose_path.is_file():
        raise GtkitError("wide poses not found (run `gtkit localize` first or give --poses FILE)", pose_path)
    cov_path = resolve(project, s.covariances, pose_path.parent / "covariances.txt")
    dets = read_detections(det_path, s.foot_point)
    resolve_images(dets, query_photos(project), det_path)
    poses = read_poses(pose_path)
    covs = read_covariances(cov_path) if cov_path.is_file() else {}
    rig = Rig.load(P.rig)
    dsm = Dsm.open(P.dsm, project.frame)
    return det_path, pose_path, cov_path, dets, poses, covs, rig, dsm


def locate(dets: list[Detection], poses: dict[str, Pose], covs: dict, rig: Rig, dsm, project: Project,
           s: TrackSettings) -> list[dict]:
    """Place every detection; one record per detection (in input order)."""
    P = project.paths
    recs: list[dict] = []
    metas: dict[str, object] = {}
    todo = []  # (record index, zoom pose, camera, uv, lift)
    for d in dets:
        rec = {"image": d.image, "label": d.label, "u": d.u, "v": d.v, "time": d.time, "status": "", "message": ""}
        recs.append(rec)
        if d.image not in metas:
            metas[d.image] = read_photo_meta(P.images / d.image)
        meta = metas[d.image]
        if rec["time"] is None:
            rec["time"] = exif_seconds(meta.timestamp)
        wide = wide_name_for(d.image)
        if wide is None:
            rec.update(status="not_zoom", message=f"{d.image} is not a zoom photo (<idx>_Z)")
            continue
        rec["wide_image"] = wide
        if wide not in poses:
            rec.update(status="no_pose", message=f"no wide pose for {wide} (not localized)")
            continue
        pose = poses[wide]
        if wide in covs:
            pose = Pose(pose.R, pose.t, covs[wide])
        cam = rig.zoom_camera(meta.width, meta.height, meta.focal_mm)
        if not cam.in_image(np.array([d.u, d.v])):
            rec.update(status="bad_pixel", message=f"pixel ({d.u:.1f}, {d.v:.1f}) is outside the "
                       f"{cam.width}x{cam.height} photo")
            continue
        lift = 0.0
        if s.foot_point == "centre" and d.box is not None:
            lift = 0.5 * float(s.centre_height.get(d.label, s.centre_height.get("default", 0.0)))
        todo.append((len(recs) - 1, pose, cam, (d.u, d.v), lift))
    # cast the main rays, grouped by lift (one vectorised call per group)
    for lift in sorted({t[4] for t in todo}):
        grp = [t for t in todo if t[4] == lift]
        surf = dsm if lift == 0 else _Lifted(dsm, lift)
        O, D = [], []
        for _i, pose, cam, uv, _l in grp:
            zp = rig.zoom_pose(pose)
            O.append(zp.center)
            D.append(zp.R.T @ cam.rays(np.asarray(uv, float)))
        hits = cast_rays(surf, np.array(O), np.array(D), step=s.step_m or None, tol=s.tol_m)
        rig_sigma = s.rig_sigma_deg or float(rig.info.get("sigma", {}).get("rotation_deg", 0.0) or 0.0)
        for k, (i, pose, cam, uv, _l) in enumerate(grp):
            rec = recs[i]
            st = str(hits.status[k])
            if st != "hit":
                rec.update(status=f"miss_{st}", message=MESSAGES[st])
                continue
            p = hits.points[k].copy()
            if lift:
                p[2] = float(dsm.height_at(p[0], p[1]))
            unc = ground_point_covariance(surf, pose, rig, cam, uv, s.uncertainty, rig_sigma)
            rec.update(status="ok", world=p, on_filled_dsm=bool(dsm.filled_at(p[0], p[1])),
                       range_m=float(hits.distance[k]), cov=unc["cov"],
                       sigma_h_m=unc["sigma_h_m"], sigma_z_m=unc["sigma_z_m"], hit_share=unc["hit_share"],
                       pose_covariance="given" if pose.covariance is not None else "default")
    return recs


def sequence_of(image: str) -> str:
    """The photo's sequence (its folder under images/): one track per label and sequence."""
    return image.rsplit("/", 1)[0] if "/" in image else ""


def add_smoothing(recs: list[dict], s: TrackSettings) -> None:
    by_track: dict[tuple[str, str], list[dict]] = {}
    for r in recs:
        if r["status"] == "ok" and r["time"] is not None:
            by_track.setdefault((r["label"], sequence_of(r["image"])), []).append(r)
    for _key, rs in by_track.items():
        if len(rs) < 2:
            continue
        sm = smooth_track([r["time"] for r in rs], np.array([r["world"] for r in rs]),
                          [r["cov"] for r in rs], s.smoothing)
        for r, p, c, out in zip(rs, sm["points"], sm["cov"], sm["outlier"]):
            r["smoothed"] = p
            r["smoothed_sigma_h_m"] = float(np.sqrt(c[0, 0] + c[1, 1]))
            r["outlier"] = bool(out)


COLUMNS = ["label", "time", "image", "u", "v", "status", "x", "y", "z", "lon", "lat", "h", "sigma_h_m",
           "sigma_z_m", "range_m", "smoothed_x", "smoothed_y", "smoothed_z", "smoothed_lon", "smoothed_lat",
           "outlier", "on_filled_dsm", "message"]


def _fmt(v, nd=3):
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not np.isfinite(v) else f"{v:.{nd}f}"
    return str(v)


def write_outputs(recs: list[dict], project: Project, out_csv: Path) -> tuple[Path, Path]:
    frame = project.frame
    for r in recs:
        if r["status"] == "ok":
            r["crs"] = frame.local_to_crs(r["world"])
            r["wgs84"] = frame.local_to_wgs84(r["world"])
            if "smoothed" in r:
                r["smoothed_crs"] = frame.local_to_crs(r["smoothed"])
                r["smoothed_wgs84"] = frame.local_to_wgs84(r["smoothed"])
    buf = io.StringIO()
    buf.write(f"# gtkit track: coordinates x,y,z in {frame.crs_spec} (metres), lon,lat (WGS84 degrees), "
              "h = height as the DSM states it; sigmas from the pose covariance; rows without coordinates "
              "failed (see status, message)\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in sorted(recs, key=lambda r: (r["label"], r["time"] if r["time"] is not None else np.inf, r["image"])):
        c, g = r.get("crs"), r.get("wgs84")
        sc, sg = r.get("smoothed_crs"), r.get("smoothed_wgs84")
        w.writerow([r["label"], _fmt(r["time"]), r["image"], _fmt(r["u"], 2), _fmt(r["v"], 2), r["status"],
                    *([_fmt(float(v)) for v in c] if c is not None else ["", "", ""]),
                    *([f"{g[0]:.8f}", f"{g[1]:.8f}", f"{g[2]:.3f}"] if g is not None else ["", "", ""]),
                    _fmt(r.get("sigma_h_m")), _fmt(r.get("sigma_z_m")), _fmt(r.get("range_m"), 2),
                    *([_fmt(float(v)) for v in sc] if sc is not None else ["", "", ""]),
                    *([f"{sg[0]:.8f}", f"{sg[1]:.8f}"] if sg is not None else ["", ""]),
                    "" if "outlier" not in r else int(r["outlier"]),
                    "" if "on_filled_dsm" not in r else int(r["on_filled_dsm"]), r["message"]])
    write_text(out_csv, buf.getvalue())
    feats = []
    for r in recs:
        if r["status"] != "ok":
            continue
        g = r["wgs84"]
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [g[0], g[1], g[2]]},
                      "properties": {"label": r["label"], "time": r["time"], "image": r["image"],
                                     "x": float(r["crs"][0]), "y": float(r["crs"][1]), "z": float(r["crs"][2]),
                                     "sigma_h_m": r["sigma_h_m"], "sigma_z_m": r["sigma_z_m"],
                                     "on_filled_dsm": bool(r.get("on_filled_dsm"))}})
    for label, seq in sorted({(r["label"], sequence_of(r["image"])) for r in recs}):
        rs = sorted([r for r in recs if r["label"] == label and sequence_of(r["image"]) == seq
                     and r["status"] == "ok" and r["time"] is not None], key=lambda r: r["time"])
        for kind, key in (("estimated", "wgs84"), ("smoothed", "smoothed_wgs84")):
            pts = [[float(v) for v in r[key]] for r in rs if key in r]
            if len(pts) >= 2:
                feats.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": pts},
                              "properties": {"label": label, "sequence": seq, "track": kind}})
    gj = out_csv.with_suffix(".geojson")
    write_json(gj, {"type": "FeatureCollection", "name": "gtkit tracks",
                    "crs_note": f"WGS84 lon/lat (RFC 7946); project CRS {frame.crs_spec} in properties",
                    "features": feats})
    return out_csv, gj


def run(project: Project | str | Path, settings: TrackSettings, force: bool = False) -> dict:
    """The tracking stage. Returns a summary (counts, output paths, per-status counts)."""
    project = project if isinstance(project, Project) else Project.load(project)
    s = settings
    P = project.paths
    det_path, pose_path, cov_path, dets, poses, covs, rig, dsm = load_inputs(project, s)
    inputs = {"detections": file_fingerprint(det_path), "poses": file_fingerprint(pose_path),
              "poses_path": str(pose_path), "covariances": file_fingerprint(cov_path),
              "rig": file_fingerprint(P.rig), "dsm": file_fingerprint(P.dsm)}
    stage_dir = P.stage(STAGE)
    summary_path = stage_dir / "summary.json"
    if not force and P.tracks.is_file() and summary_path.is_file() and stage_done(stage_dir, s, inputs):
        log.info("track: up to date (%s)", P.tracks)
        done = json.loads(summary_path.read_text())
        return {k: str(resolve_path(v, P.root)) if k in ("poses", "pose_covariances", "csv", "geojson") and v else v
                for k, v in done.items()}
    start_stage_clock(stage_dir)
    t0 = time.perf_counter()
    recs = locate(dets, poses, covs, rig, dsm, project, s)
    if s.smooth:
        add_smoothing(recs, s)
    csv_path, gj = write_outputs(recs, project, P.tracks)
    status: dict[str, int] = {}
    missed: dict[str, list[dict]] = {}
    for r in recs:
        status[r["status"]] = status.get(r["status"], 0) + 1
        if r["status"] != "ok":
            missed.setdefault(r["status"], []).append(r)
            log.debug("track: %s %s: %s", r["label"], r["image"], r["message"])
    for st, rs in missed.items():  # one line a reason; each detection's message is in the CSV
        names = [r["image"] for r in rs]
        log.warning("track: %d detection(s) not placed (%s), e.g. %s: %s%s", len(rs), st, names[0], rs[0]["message"],
                    f"; also {', '.join(names[1:4])}{' ...' if len(names) > 4 else ''}" if len(names) > 1 else "")
    sig = [r["sigma_h_m"] for r in recs if r.get("sigma_h_m") is not None]
    on_filled = [r for r in recs if r.get("on_filled_dsm")]
    if on_filled:
        log.warning("track: %d of %d placed targets landed on filled DSM cells (interpolated over a gap, no "
                    "measured surface; column on_filled_dsm = 1), e.g. %s", len(on_filled), status.get("ok", 0),
                    on_filled[0]["image"])
    summary = {"n_detections": len(recs), "n_located": status.get("ok", 0), "status": status,
               "n_on_filled_dsm": len(on_filled),
               "poses": str(pose_path), "pose_covariances": str(cov_path) if cov_path.is_file() else None,
               "median_sigma_h_m": float(np.median(sig)) if sig else None, "csv": str(csv_path),
               "geojson": str(gj), "seconds": round(time.perf_counter() - t0, 3), "settings": settings_dict(s)}
    write_json(summary_path, relative_paths(summary, P.root))  # portable: paths relative to the project
    mark_stage_done(stage_dir, s, inputs, n_located=summary["n_located"], n_detections=len(recs),
                    n_on_filled_dsm=len(on_filled))
    log.info("track: %d of %d detections located (%d on filled DSM cells) -> %s", summary["n_located"], len(recs),
             len(on_filled), csv_path)
    return summary
