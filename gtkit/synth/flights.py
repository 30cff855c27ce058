"""Camera poses of the reference flight (five-eye oblique grid) and the query flights
(wide + zoom camera on one gimbal following a target or looking at the site)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..conventions import dji_to_rotation
from ..pose import Pose
from .settings import SynthSettings
from .targets import Track
from .world import World

EYES = (("N", 0.0, -90.0), ("F", 0.0, None), ("B", 180.0, None), ("L", -90.0, None), ("R", 90.0, None))


@dataclass
class Shot:
    name: str               # relative to images/
    camera: Camera
    pose: Pose
    time_s: float           # seconds after the flight's date
    flight_yaw: float       # aircraft heading, degrees
    kind: str               # reference | wide | zoom
    sequence: str = ""
    manual: bool = False
    follow: str = ""        # which target the gimbal aimed at ("" = none)


def reference_camera(s: SynthSettings) -> Camera:
    r = s.reference
    return Camera.from_hfov(r.width, r.height, r.hfov_deg)


def wide_camera(s: SynthSettings) -> Camera:
    q = s.queries
    f = q.wide_width / 2.0 / np.tan(np.radians(q.wide_hfov_deg) / 2.0)
    if q.wide_k1 or q.wide_k2:
        return Camera("RADIAL", q.wide_width, q.wide_height, (f, q.wide_width / 2, q.wide_height / 2, q.wide_k1, q.wide_k2))
    return Camera.pinhole(q.wide_width, q.wide_height, f)


def zoom_camera(s: SynthSettings) -> Camera:
    q = s.queries
    return Camera.from_hfov(q.zoom_width, q.zoom_height, q.zoom_hfov_deg)


def zoom_from_wide(s: SynthSettings) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with x_zoom = R @ x_wide + t (camera frames, metres)."""
    q = s.queries
    return (Rotation.from_rotvec(np.radians(q.zoom_rotation_deg)).as_matrix(), np.asarray(q.zoom_offset_m, float))


def reference_shots(world: World, s: SynthSettings) -> list[Shot]:
    """A serpentine grid of stations; five photos per station."""
    r = s.reference
    cam = reference_camera(s)
    z = world.base_height + r.altitude_agl
    foot_w = 2 * r.altitude_agl * np.tan(np.radians(r.hfov_deg) / 2)      # across track (image width)
    foot_h = foot_w * r.height / r.width                                   # along track
    step_along = foot_h * (1 - r.overlap_forward)
    step_across = foot_w * (1 - r.overlap_side)
    half = 0.5 * r.coverage_share * world.size
    n_strips = int(np.ceil(2 * half / step_across)) + 1
    n_stations = int(np.ceil(2 * half / step_along)) + 1
    xs = np.linspace(-half, half, n_strips)
    ys = np.linspace(-half, half, n_stations)
    shots, t = [], 0.0
    for i, x in enumerate(xs):
        north = i % 2 == 0
        heading = 0.0 if north else 180.0
        for j, y in enumerate(ys if north else ys[::-1]):
            C = np.array([x, y, z])
            for code, dyaw, pitch in EYES:
                yaw = heading + dyaw
                R = dji_to_rotation(yaw, pitch if pitch is not None else r.oblique_pitch_deg, 0.0)
                shots.append(Shot(f"reference/R{i + 1:02d}_{j + 1:03d}_{code}.jpg", cam, Pose.from_center(R, C),
                                  t, heading, "reference"))
            t += r.seconds_per_station
    return shots


def _look(C: np.ndarray, aim: np.ndarray, roll: float) -> np.ndarray:
    d = aim - C
    yaw = np.degrees(np.arctan2(d[0], d[1]))
    pitch = np.degrees(np.arctan2(d[2], np.hypot(d[0], d[1])))
    return dji_to_rotation(yaw, float(np.clip(pitch, -70.0, -15.0)), roll)


def query_shots(world: World, tracks: dict[str, Track], s: SynthSettings, rng: np.random.Generator) -> list[Shot]:
    """Wide and zoom shots of every sequence, ordered by time; names <seq>/<idx>_W|Z.jpg."""
    q = s.queries
    wide, zoom = wide_camera(s), zoom_camera(s)
    Rzw, tzw = zoom_from_wide(s)
    half = world.size / 2
    out = []
    for seq in q.sequences:
        dur = seq.n_continuous * seq.interval_s
        times = [(seq.start_s + k * seq.interval_s, False) for k in range(seq.n_continuous)]
        times += [(seq.start_s + float(rng.uniform(0, dur)), True) for _ in range(seq.n_manual)]
        times.sort()
        d = seq.height_agl / np.tan(np.radians(-seq.pitch_deg))   # horizontal stand-off
        phi0 = rng.uniform(0, 2 * np.pi)
        # an 'area' sequence orbits a point of the site
        area_c = np.array([rng.uniform(-0.2, 0.2) * half, rng.uniform(-0.2, 0.2) * half])
        for idx, (t, manual) in enumerate(times):
            if seq.follow == "area":
                P = np.array([*area_c, float(world.terrain_height(*area_c))])
            else:
                P = tracks[seq.follow].position(t, world)
            phi = phi0 + np.radians(seq.orbit_deg_per_s) * (t - seq.start_s)
            C = P + [d * np.cos(phi), d * np.sin(phi), seq.height_agl]
            C[2] = max(C[2], world.obstacle_top(C[0], C[1], q.clearance_radius_m) + q.clearance_m)
            if manual:
                # a manual shot: the pilot looks somewhere else on the site
                aim = np.array([*(C[:2] + rng.uniform(-0.5, 0.5, 2) * 2 * d), 0.0])
                aim[:2] = np.clip(aim[:2], -half + 5, half - 5)
                aim[2] = float(world.terrain_height(aim[0], aim[1]))
                follow = ""
            else:
                aim = P + [*rng.normal(0, q.aim_jitter_m, 2), 0.0]
                follow = "" if seq.follow == "area" else seq.follow
            Rw = _look(C, aim, float(rng.normal(0, q.roll_sigma_true_deg)))
            pw = Pose.from_center(Rw, C)
            pz = Pose(Rzw @ pw.R, Rzw @ pw.t + tzw)
            heading = float(np.degrees(phi + np.pi / 2)) % 360.0  # tangent of the orbit
            heading = 90.0 - heading                             # math angle -> compass
            base = f"queries/{seq.name}/{idx + 1:04d}"
            out.append(Shot(base + "_W.jpg", wide, pw, t, heading, "wide", seq.name, manual, follow))
            out.append(Shot(base + "_Z.jpg", zoom, pz, t, heading, "zoom", seq.name, manual, follow))
    return out
