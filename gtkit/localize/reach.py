"""Which database views a query can reach from its sensor priors alone, before any feature exists:
the rotation prior, the GPS radius and the position prior (predicted overlap from GPS + gimbal, the
look-at footprint, or the views near a photo without attitude) that :mod:`gtkit.localize.localize`
ranks the views by, and the bound that says which views can never enter a query's matched views
(:func:`reachable_views`). render-db renders, and localize describes, only those (plus the VLAD
codebook's views, :func:`codebook_views`), and the ranking is the same as over every view."""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..conventions import dji_to_rotation
from ..project import Project, settings_dict, settings_key
from .settings import LocalizeSettings

# ``db`` below: a gtkit.localize.database.Database (not imported: the database imports this module)


def codebook_views(planned: list[str], s: LocalizeSettings) -> list[str]:
    """Views spread evenly over the sorted names of the database's planned views (level by level,
    position by position; ``codebook_views`` at most, and ``codebook_share`` of them): the views the
    VLAD codebook is trained on (those of them kept), the same whichever queries run and however much
    of the grid is rendered."""
    names = sorted(planned)
    n = max(1, min(s.codebook_views, int(np.ceil(s.codebook_share * len(names)))))
    if len(names) <= n:
        return names
    return [names[i] for i in np.unique(np.round(np.linspace(0, len(names) - 1, n)).astype(int))]


def select_views(db, s: LocalizeSettings):
    """The database subset a run uses (render ablations: ``db_heights``, ``db_paper_pitches``,
    ``db_highest_only``)."""
    sub = db.subset(s.db_heights, s.db_paper_pitches)
    if s.db_highest_only and sub.views:
        top = max(v.height for v in sub.views)
        sub = sub.subset((top,), None)
    return sub


def view_arrays(db) -> dict:
    """What the sensor priors read of the database views, as arrays (one row a view)."""
    return dict(ypr=np.array([[v.yaw, v.pitch, v.roll] for v in db.views]).reshape(-1, 3),
                centers=np.array([v.pose.center for v in db.views]).reshape(-1, 3),
                look_at=_view_look_at(db), ground=db_ground_level(db), level_interval=_level_intervals(db),
                view_R=np.array([np.asarray(v.pose.R) for v in db.views]).reshape(-1, 3, 3),
                view_t=np.array([np.asarray(v.pose.t) for v in db.views]).reshape(-1, 3))


def _view_look_at(db) -> np.ndarray:
    """(N, 2) look-at points of the database views on their ground level (centre z minus height)."""
    from .prior import look_at_points

    if not db.views:
        return np.zeros((0, 2))
    centers = np.array([v.pose.center for v in db.views])
    axes = np.array([np.asarray(v.pose.R)[2] for v in db.views])  # camera +z in the world
    return look_at_points(centers, axes, db_ground_level(db))


def _level_intervals(db) -> np.ndarray:
    """(N,) the grid interval of each view's level: the smallest spacing of its level's positions."""
    out = np.zeros(len(db.views))
    hs = np.array([v.height for v in db.views])
    for h in np.unique(hs):
        idx = np.flatnonzero(hs == h)
        xy = np.unique(np.round([db.views[i].pose.center[:2] for i in idx], 3), axis=0)
        gaps = [np.diff(np.unique(xy[:, k])) for k in (0, 1)]
        gaps = np.concatenate([g[g > 1e-3] for g in gaps])
        out[idx] = gaps.min() if len(gaps) else 0.0
    return out


def db_ground_level(db) -> float:
    return float(np.median([v.pose.center[2] - v.height for v in db.views])) if db.views else 0.0


def sensor_priors(V: dict, s: LocalizeSettings, proj: Project, db, meta, cam: Camera, prior_R):
    """What the photo's sensors alone say of each database view (``V``: :func:`_view_arrays`):
    ``keep`` (rotation prior, GPS radius), ``near`` (the position prior's first views, or None),
    ``pred`` (the predicted overlap the ranking adds to the descriptor score, or None) and the
    position prior's record for the status (or None)."""
    from .prior import footprint_filter, gps_filter, look_at_points, predicted_overlap, rotation_filter

    keep = np.ones(len(db.views), bool)
    if s.rotation_prior and prior_R is not None:
        keep &= rotation_filter([meta.gimbal_yaw, meta.gimbal_pitch, meta.gimbal_roll], V["ypr"], s.gamma_o)
    if s.gps_radius_m is not None and meta.has_gps:
        xy = proj.frame.wgs84_to_local(meta.lon, meta.lat, meta.altitude or 0.0)
        keep &= gps_filter(np.ravel(xy)[:2], V["centers"], s.gps_radius_m)
    near = pred = prior_rec = None
    if not keep.any():
        return keep, near, pred, prior_rec
    if s.position_prior is not None and meta.has_gps and meta.altitude is not None and prior_R is not None:
        c = np.ravel(proj.frame.wgs84_to_local(meta.lon, meta.lat, meta.altitude))[:3]
        if s.position_prior == "footprint":
            la = look_at_points(c[None], np.asarray(prior_R)[2][None], V["ground"])[0]
            near = footprint_filter(la, V["look_at"], s.gps_footprint_radius_m)
            prior_rec = {"mode": "footprint", "look_at_xy": [round(float(x), 2) for x in la],
                         "n_near": int((near & keep).sum()), "radius_m": s.gps_footprint_radius_m}
        else:
            idx = np.flatnonzero(keep)
            pred = np.zeros(len(db.views))
            pred[idx] = predicted_overlap(c, prior_R, cam.pinhole_part(), V["view_R"][idx], V["view_t"][idx],
                                          db.camera, V["ground"], angle_deg=s.prior_angle_deg)
            near = pred > 0
            prior_rec = {"mode": "overlap", "n_overlapping": int((near & keep).sum()),
                         "best_predicted": round(float(pred.max()), 3)}
    elif (s.position_prior is not None and s.no_attitude_radius_m is not None and meta.has_gps
          and prior_R is None and len(db.views)):
        xy = np.ravel(proj.frame.wgs84_to_local(meta.lon, meta.lat, meta.altitude or 0.0))[:2]
        dist = np.linalg.norm(V["centers"][:, :2] - xy, axis=1)
        near = dist <= 0.75 * V["level_interval"] + s.no_attitude_radius_m
        prior_rec = {"mode": "near (no attitude)", "n_near": int((near & keep).sum()),
                     "margin_m": s.no_attitude_radius_m}
    return keep, near, pred, prior_rec


PRIOR_FIELDS = ("rotation_prior", "gamma_o", "gps_radius_m", "position_prior", "prior_vlad_weight", "prior_angle_deg",
                "gps_footprint_radius_m", "no_attitude_radius_m", "top_k", "fallback_rounds", "query_subset",
                "codebook_views", "codebook_share", "db_heights", "db_paper_pitches", "db_highest_only")


def prior_settings_key(s: LocalizeSettings) -> str:
    """What decides which database views the queries reach (:func:`reachable_views`)."""
    d = settings_dict(s)
    return settings_key({k: d[k] for k in PRIOR_FIELDS})


def reachable_views(project: Project, db, s: LocalizeSettings, names: list[str],
                    cameras: dict[str, Camera]) -> np.ndarray:
    """(N,) bool: the database views some query's retrieval can rank among the views it matches
    (its top_k x (1 + fallback_rounds)), from the sensor priors alone, before any feature exists.

    A query's ranking key is its predicted overlap + ``prior_vlad_weight`` x the descriptor score, a
    cosine of unit vectors (-1..1); views its position prior puts first come before all others. So
    where at least n views are put first, a view whose overlap is below the n-th best minus 2 x the
    weight can never be ranked within n (a view the footprint or no-attitude prior puts first is
    ranked by its descriptor score alone: every one of them is reachable); with fewer than n put
    first, or no position prior (GPS-denied, no attitude and no GPS), every view the query's rotation
    prior keeps is. A photo whose metadata cannot be read reaches every view."""
    from ..io.exif import read_photo_meta

    V = view_arrays(db)
    n = s.top_k * (1 + max(0, s.fallback_rounds))
    need = np.zeros(len(db.views), bool)
    for name in names:
        try:
            meta = read_photo_meta(project.paths.images / name)
        except Exception:  # noqa: BLE001 - the query reports its own error later; it may need any view
            need[:] = True
            break
        prior_R = dji_to_rotation(meta.gimbal_yaw, meta.gimbal_pitch, meta.gimbal_roll) if meta.has_gimbal else None
        keep, near, pred, _rec = sensor_priors(V, s, project, db, meta, cameras[name], prior_R)
        first = keep & near if near is not None else None
        if first is None or first.sum() < n:
            need |= keep
        elif pred is None:
            need |= first
        else:
            nth = np.sort(pred[first])[-n]
            need |= first & (pred >= nth - 2.0 * s.prior_vlad_weight)
    return need


def query_names(project: Project, s: LocalizeSettings) -> list[str]:
    """The query photos ([sfm] query_pattern, :func:`gtkit.queries.query_photos`), narrowed to
    ``s.query_subset`` when given."""
    from fnmatch import fnmatchcase

    from ..queries import query_photos

    names = query_photos(project)
    return [n for n in names if fnmatchcase(n, s.query_subset)] if s.query_subset else names
