"""The database grid that follows the queries (``render-db``'s heights, pitches, field of view and
intervals left open in the settings): what the query photos say about where they were taken.

Each photo's height and pitch come from its sensors first: its GPS altitude above the model's
ground and its gimbal pitch (a UAV's photos: the database does not depend on the pseudo-GT it
validates; a consumer camera's GPS photo without gimbal angles keeps the default pitches, as
before). A photo without a GPS altitude (a terrestrial or phone set, photos with positions in
``geo.txt`` only) takes its height from what else the project knows of it: its ``geo.txt``
position, then its pseudo-GT pose (``work/register/poses.txt``, written before render-db runs),
and, without gimbal angles, its pitch from that pose (the optical axis's angle off nadir). What no
photo tells comes from :data:`PAPER_GRID`.

Issue 58: the fountain set held out (queries 2.8 m above the ground, looking horizontally, no GPS
altitude) got the paper's 100-150 m nadir / oblique grid, kept 0 of its 48 views, and localization
stopped the run; planned from the queries' pseudo-GT poses it gets one level at their height, 85
degrees off nadir (:mod:`gtkit.localize.grid`: views within 10 degrees of the horizon stand at their
grid position).
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from ..errors import GtkitError
from ..project import Project, file_fingerprint

# The grid when the queries say nothing (no GPS altitude / no gimbal angles / no intrinsics): the
# paper's heights and intervals, its pitches plus 70 deg from nadir (= DJI -20: queries flown 15-70
# deg below the horizon are then within 15 deg of a level; +50 % views; ablation 'render-paper'), 60 deg.
PAPER_PITCHES = (0.0, 45.0)   # the UAVD4L paper's database pitches, from nadir
PAPER_GRID = {"heights": (100.0, 150.0), "intervals": (50.0, 75.0), "paper_pitches": (*PAPER_PITCHES, 70.0),
              "hfov_deg": 60.0}
GRID_FIELDS = tuple(PAPER_GRID)
GPS_FLOOR_M = 5.0    # a GPS altitude this close above the ground is its error more often than a real height
POSE_FLOOR_M = 0.3   # a surveyed or pseudo-GT camera centre at least this far above the ground under it

# ``s`` below: a gtkit.localize.database.RenderDbSettings (not imported: the database imports this module)


def grid_given(s) -> bool:
    return all(getattr(s, k) is not None for k in GRID_FIELDS)


def grid_hfov(hfovs) -> float:
    """The database views' field of view for queries of these fields of view: their median, 30-90
    deg, in whole degrees (a calibration that moves it by a fraction of a degree keeps the views)."""
    return float(round(float(np.clip(np.median(list(hfovs)), 30.0, 90.0))))


def flight_inputs(project: Project, names: list[str]) -> dict:
    """The files besides the photos the grid may follow (render-db's inputs): ``geo.txt`` and the
    pseudo-GT poses, only where some query photo has no GPS altitude (a UAV project's database does
    not wait on its pseudo-GT)."""
    from ..io.exif import read_photo_meta

    def no_altitude(n: str) -> bool:
        try:
            m = read_photo_meta(project.paths.images / n)
        except GtkitError:
            return True
        return not (m.has_gps and m.altitude is not None)

    P = project.paths
    if not any(no_altitude(n) for n in names):
        return {}
    return {"geo_txt": file_fingerprint(P.geo_txt), "pseudo_gt_poses": file_fingerprint(P.pseudo_gt_poses)}


def _pseudo_gt(project: Project) -> dict:
    from ..io.poses import read_poses

    try:
        return read_poses(project.paths.pseudo_gt_poses) if project.paths.pseudo_gt_poses.is_file() else {}
    except GtkitError:
        return {}


def query_flight(project: Project, renderer, extent, ground_z: float, cells: int = 128,
                 radius_m: float = 15.0) -> dict:
    """What the query photos say about where they were taken (see the module doc): per photo its
    height above the model's ground under it (the median top-surface height within ``radius_m`` of
    its position, from an orthographic height render; the ground level ``ground_z`` off the model)
    and where that came from, its pitch off nadir and where that came from, and the field of view of
    each photo whose intrinsics resolve (:func:`gtkit.queries.query_cameras`)."""
    from ..altitude_drift import altitude_drift_at
    from ..io.exif import capture_seconds, read_photo_meta
    from ..photo_positions import PhotoPositions
    from ..queries import query_cameras, query_photos

    names = query_photos(project)
    out = {"n_queries": len(names), "agl_m": {}, "off_nadir_deg": {}, "hfov_deg": {}, "notes": [],
           "from": {"agl_m": {}, "off_nadir_deg": {}}}
    if not names:
        return out
    # photos of the reference flight itself (held out of it): their GPS altitude drifts as the
    # reference photos' did, and the georegistration measured that drift (consumer GPS: tens of m)
    ref_report = project.paths.reports / "reference.json"
    fit = None
    if ref_report.is_file():
        fit = (json.loads(ref_report.read_text()).get("georegistration") or {}).get("fit")
    n_drift = 0
    xmin, ymin, xmax, ymax = extent
    gsd = max(xmax - xmin, ymax - ymin) / cells
    hmap = renderer.render_ortho(xmin, ymin, xmax, ymax, gsd, with_rgb=False).depth  # row 0 = ymax
    k = max(1, int(round(radius_m / gsd)))

    def ground_under(x: float, y: float) -> float:
        r_, c_ = int((ymax - y) / gsd), int((x - xmin) / gsd)
        win = hmap[max(0, r_ - k):max(0, r_ + k + 1), max(0, c_ - k):max(0, c_ + k + 1)]
        return float(np.nanmedian(win)) if win.size and np.isfinite(win).any() else ground_z

    positions, pgt = PhotoPositions(project), None
    for n in names:
        m = read_photo_meta(project.paths.images / n)
        if m.has_gimbal:
            out["off_nadir_deg"][n], out["from"]["off_nadir_deg"][n] = 90.0 + float(m.gimbal_pitch), "gimbal"
        if m.has_gps and m.altitude is not None:
            x, y, z = (float(v) for v in np.ravel(project.frame.wgs84_to_local(m.lon, m.lat, m.altitude))[:3])
            drift = altitude_drift_at(fit, capture_seconds(m.timestamp))
            if drift is not None:
                z -= drift
                n_drift += 1
            ground = ground_under(x, y)
            if z - ground < GPS_FLOOR_M:
                out["notes"].append(f"{n}: GPS altitude {m.altitude:g} m is {z - ground:.1f} m above the model's "
                                    "ground under it: left out of the height envelope")
                continue
            out["agl_m"][n], out["from"]["agl_m"][n] = z - ground, "GPS altitude"
            continue
        # no GPS altitude: what else the project knows of the photo (geo.txt, its pseudo-GT pose)
        if pgt is None:
            pgt = _pseudo_gt(project)
        pose = pgt.get(n)
        if n not in out["off_nadir_deg"] and pose is not None:
            axis_z = float(np.asarray(pose.R)[2, 2])        # the optical axis's up component, world frame
            out["off_nadir_deg"][n] = float(np.degrees(np.arccos(np.clip(-axis_z, -1.0, 1.0))))
            out["from"]["off_nadir_deg"][n] = "pseudo-GT pose"
        geo = positions.from_geo_txt(n)
        c, src = (geo.xyz, "geo.txt") if geo is not None else (None if pose is None else pose.center, "pseudo-GT pose")
        if c is None:
            continue
        agl = float(c[2]) - ground_under(float(c[0]), float(c[1]))
        if agl < POSE_FLOOR_M:
            out["notes"].append(f"{n}: its {src} centre is {agl:.1f} m above the model's ground under it: left out "
                                "of the height envelope")
            continue
        out["agl_m"][n], out["from"]["agl_m"][n] = agl, src
    if n_drift:
        out["notes"].append(f"{n_drift} photos taken during the reference flight: GPS altitude corrected by the "
                            f"drift its georegistration measured ({fit['altitude_drift_m']:.1f} m over the flight)")
    try:
        cams = query_cameras(project, names)
        out["hfov_deg"] = {n: float(c.camera.hfov_deg()) for n, c in cams.items()}
    except GtkitError as e:
        out["notes"].append(f"query field of view unknown ({e})")
    return out


def _what(sources: dict[str, str], sensor: str, label: str, mixed: str) -> str:
    """Where a grid value's photo figures came from: ``photos' <label>`` when all from the sensor,
    else ``photos' <mixed>: 3 from geo.txt, 1 from pseudo-GT pose``."""
    kinds: dict[str, int] = {}
    for v in sources.values():
        kinds[v] = kinds.get(v, 0) + 1
    if set(kinds) == {sensor}:
        return f"photos' {label}"
    return f"photos' {mixed}: " + ", ".join(f"{k} from {v}" for v, k in kinds.items())


def resolve_grid(project: Project, s, renderer, extent, ground_z: float):
    """``s`` with every grid field left None filled in (see ``RenderDbSettings``), and a record
    of where each came from. Heights, pitches and field of view follow the query photos' envelope
    (:func:`gtkit.localize.grid.height_levels`, :func:`pitch_levels`; the median field of view,
    30-90 deg), intervals the heights and field of view (:func:`level_interval`); what the queries
    do not tell comes from :data:`PAPER_GRID`."""
    from .grid import height_levels, level_interval, pitch_levels

    src = {k: "settings" for k in GRID_FIELDS if getattr(s, k) is not None}
    if grid_given(s):
        return s, {"source": src}
    fl = query_flight(project, renderer, extent, ground_z)
    ch: dict = {}
    # each grid value the settings leave open: (its flight figures, how they make it, what they are, else why not)
    follows = {"hfov_deg": ("hfov_deg", grid_hfov, "photos' intrinsics, median", "no query intrinsics"),
               "heights": ("agl_m", lambda v: height_levels(list(v)),
                           _what(fl["from"]["agl_m"], "GPS altitude", "GPS altitude above the model's ground",
                                 "height above the model's ground"),
                           "no query GPS altitude"),
               "paper_pitches": ("off_nadir_deg", lambda v: pitch_levels(list(v)),
                                 _what(fl["from"]["off_nadir_deg"], "gimbal", "gimbal pitch", "pitch off nadir"),
                                 "no gimbal angles")}
    for name, (key, make, what, missing) in follows.items():
        if getattr(s, name) is not None:
            continue
        if fl[key]:
            ch[name], src[name] = make(fl[key].values()), f"queries ({len(fl[key])} {what})"
        else:
            ch[name], src[name] = PAPER_GRID[name], f"default ({missing})"
    heights = ch.get("heights", s.heights)
    if s.intervals is None:
        hfov = ch.get("hfov_deg", s.hfov_deg)
        ch["intervals"] = tuple(level_interval(h, hfov) for h in heights)
        src["intervals"] = "heights x field of view"
    elif len(s.intervals) != len(heights):
        raise GtkitError(f"[render_db] intervals {tuple(s.intervals)} need one value per height, and the "
                         f"heights {heights} come from the queries: give heights too, or leave intervals out",
                         project.paths.project_toml)
    info = {"source": src, "queries": {"n": fl["n_queries"], "with_altitude": len(fl["agl_m"]),
                                       "with_gimbal": len(fl["off_nadir_deg"]), "with_intrinsics": len(fl["hfov_deg"])},
            "notes": fl["notes"]}
    for key, vals in (("agl_m", fl["agl_m"]), ("off_nadir_deg", fl["off_nadir_deg"]), ("hfov_deg", fl["hfov_deg"])):
        if vals:
            v = np.array(list(vals.values()))
            info["queries"][key + "_min_median_max"] = [round(float(x), 1) for x in (v.min(), np.median(v), v.max())]
    return replace(s, **ch), info
