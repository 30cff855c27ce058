"""Is a georegistered block physically plausible? Checked after every georegistration, so
that a block placed upside down, tilted or at a wrong scale is refused with its cause instead of
being reported as success (and built upon by every later stage).

- **cameras above what they see**: in (nearly) every photo the camera is above the median of the
  3D points it observes;
- **photos look down**: aerial photos are taken 15-90 deg below the horizon;
- **directions agree with the metadata**: where photos carry gimbal attitude, the block's camera
  rotations agree with it (a consumer compass and gimbal: within tens of degrees, never a flip);
- **level**: the block's up agrees with gravity as the photos tell it (gtkit.sfm.gravity: gimbal
  attitude, else the aerial prior) within 10 deg (+ 3 x the photos' own spread);
- **scale**: the cameras' height above what they see agrees with the DJI relative altitude (above
  the take-off point) where photos carry it, and is a drone's height (2 m - 3 km) anyway.

The aerial checks (cameras above what they see, photos looking down, level by the aerial prior,
a drone's height) hold for aerial blocks only. A block whose photos look level (a terrestrial or
facade capture) is plausible where the positions or GCPs it was fitted to hold its tilt
(``held_by``: what holds it, as the georegistration found); where nothing holds it, it is refused
naming that. Gimbal attitude and the DJI relative altitude are measurements: checked on every block.

``check_block(rec, metas, held_by=...)`` returns the figures, and raises :class:`RegistrationError`
with one line naming the first check that fails.
"""
from __future__ import annotations

import numpy as np
import pycolmap

from ..conventions import dji_to_rotation
from .geometry import RegistrationError
from .gravity import block_up


def _rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1.0) / 2.0, -1.0, 1.0))))


def block_figures(rec: pycolmap.Reconstruction, metas: dict | None = None, max_points: int = 500) -> dict:
    """Per-block plausibility figures (see the module docstring) in ``rec``'s current frame (z up)."""
    metas = metas or {}
    heights, views, rot_err, rel = [], [], [], []
    for im in rec.images.values():
        if not im.has_pose:
            continue
        Rcw = im.cam_from_world().rotation.matrix()
        C = im.projection_center()
        views.append(float(Rcw[2] @ np.array([0.0, 0.0, 1.0])))   # optical axis' z
        ids = [p.point3D_id for p in im.get_observation_points2D()]   # the observed ones (twice as fast on medium)
        if len(ids) >= 10:
            Z = np.array([rec.points3D[i].xyz[2] for i in ids[:: max(1, len(ids) // max_points)]])
            h = float(C[2] - np.median(Z))
            heights.append(h)
            m = metas.get(im.name)
            if m is not None and m.rel_alt is not None and m.rel_alt > 1.0:
                rel.append(h / m.rel_alt)
        m = metas.get(im.name)
        if m is not None and m.has_gimbal:
            rot_err.append(_rotation_angle_deg(Rcw, dji_to_rotation(m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll)))
    h = np.array(heights)
    up = block_up(rec, metas)
    return {"n_photos": len(views),
            "tilt_from_gravity_deg": (float(np.degrees(np.arccos(np.clip(up.vector[2], -1, 1)))) if up else None),
            "gravity_from": up.source if up else None, "gravity_spread_deg": up.spread_deg if up else None,
            "share_above_their_points": float(np.mean(h > 0)) if len(h) else None,
            "median_height_above_points_m": float(np.median(h)) if len(h) else None,
            "median_view_z": float(np.median(views)) if views else None,
            "n_with_attitude": len(rot_err),
            "median_attitude_disagreement_deg": float(np.median(rot_err)) if rot_err else None,
            "height_over_relative_altitude": float(np.median(rel)) if rel else None}


def check_block(rec: pycolmap.Reconstruction, metas: dict | None = None, *, held_by: str | None = None,
                evidence: str | None = None,
                min_share_above: float = 0.8, max_view_z: float = -0.1, max_attitude_deg: float = 30.0,
                max_tilt_deg: float = 10.0, rel_alt_ratio: float = 3.0,
                height_range_m: tuple[float, float] = (2.0, 3000.0)) -> dict:
    """The figures of :func:`block_figures`; raises RegistrationError naming the first failed check.
    ``held_by``: what holds the block's tilt where positions or GCPs do ("8 GPS positions"), else None;
    ``evidence``: what the positions or GCPs say where they do not (named in a refusal)."""
    f = block_figures(rec, metas)
    level = f["median_view_z"] is not None and f["median_view_z"] > max_view_z
    f["capture"] = "level" if level else "aerial"
    f["held_by"] = held_by
    if level and held_by:
        # a terrestrial / facade capture placed by its positions or GCPs: the aerial checks do not apply
        f["aerial_checks"] = f"not applied: the photos look level (z = {f['median_view_z']:+.2f}), the tilt held by {held_by}"
        if f["median_attitude_disagreement_deg"] is not None and f["median_attitude_disagreement_deg"] > max_attitude_deg:
            raise RegistrationError(
                f"implausible result: the camera rotations disagree with the photos' gimbal attitude by "
                f"{f['median_attitude_disagreement_deg']:.0f} deg (median over {f['n_with_attitude']} photos)")
        return f
    if level and f["median_view_z"] < 0.3:
        # level photos, nothing holding their tilt: that, not "below the ground", is the cause
        raise RegistrationError(
            f"implausible result: the photos look level (median viewing direction z = {f['median_view_z']:+.2f}) and "
            f"no positions or GCPs hold the block's tilt{f' ({evidence})' if evidence else ''} (aerial photos look "
            "down; a level capture needs surveyed positions or GCPs)")
    if f["share_above_their_points"] is not None and f["share_above_their_points"] < min_share_above:
        raise RegistrationError(
            f"implausible result: the cameras sit below the ground they see in "
            f"{100 * (1 - f['share_above_their_points']):.0f} % of the photos (block upside down or tilted)")
    if f["median_view_z"] is not None and f["median_view_z"] > max_view_z:
        raise RegistrationError(
            f"implausible result: the photos look {'up' if f['median_view_z'] > 0 else 'level'} "
            f"(median viewing direction z = {f['median_view_z']:+.2f}) and no positions or GCPs hold the block's tilt "
            "(aerial photos look down; a level capture needs surveyed positions or GCPs)")
    t = f["tilt_from_gravity_deg"]
    if t is not None and t > max_tilt_deg + 3.0 * f["gravity_spread_deg"]:
        raise RegistrationError(
            f"implausible result: the block is tilted {t:.0f} deg from gravity ({f['gravity_from']}): the positions "
            "or GCPs it was fitted to disagree in height (inconsistent altitudes)")
    if f["median_attitude_disagreement_deg"] is not None and f["median_attitude_disagreement_deg"] > max_attitude_deg:
        raise RegistrationError(
            f"implausible result: the camera rotations disagree with the photos' gimbal attitude by "
            f"{f['median_attitude_disagreement_deg']:.0f} deg (median over {f['n_with_attitude']} photos)")
    r = f["height_over_relative_altitude"]
    if r is not None and not (1.0 / rel_alt_ratio <= r <= rel_alt_ratio):
        raise RegistrationError(
            f"implausible scale: the cameras are {f['median_height_above_points_m']:.1f} m above the ground they see, "
            f"{r:.2f} x the photos' relative altitude")
    h = f["median_height_above_points_m"]
    if h is not None and not (height_range_m[0] <= h <= height_range_m[1]):
        raise RegistrationError(f"implausible scale: the cameras are {h:.1f} m above the ground they see")
    return f
