"""Virtual viewpoints for the rendered database (UAVD4L §3.1).

For each level (absolute height ``H`` above the model's ground level, horizontal interval
``alpha_t``) a square grid covers the model's extent; at every position the camera takes every
paper pitch x every yaw.

Angles. The paper's database pitch is measured from *nadir*: paper pitch 0 = looking straight
down = DJI gimbal pitch -90; paper pitch 45 = DJI pitch -45. So ``dji_pitch = paper_pitch - 90``.
Yaw is DJI's (clockwise from north); roll is 0. Rotations come from
:func:`gtkit.conventions.dji_to_rotation`.

Ground level. ``H`` is measured from the model's ground level, defined as the 5th percentile
of the model's top-surface height (an orthographic height render over the extent), so a few
deep pits or the tops of buildings do not move it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..pose import Pose


@dataclass(frozen=True)
class View:
    """One virtual viewpoint: its name, level and DJI angles, and camera centre (world)."""

    name: str
    height: float          # H above the ground level (m)
    paper_pitch: float     # 0 = nadir, 45 = 45 deg off nadir
    yaw: float             # DJI yaw (deg)
    pitch: float           # DJI pitch (deg) = paper_pitch - 90
    roll: float
    center: tuple[float, float, float]

    def pose(self) -> Pose:
        return Pose.from_dji(self.yaw, self.pitch, self.roll, np.asarray(self.center))

    def as_dict(self) -> dict:
        return asdict(self)


def paper_to_dji_pitch(paper_pitch: float) -> float:
    return float(paper_pitch) - 90.0


def ground_level(renderer, xmin: float, ymin: float, xmax: float, ymax: float, cells: int = 256,
                 percentile: float = 5.0) -> float:
    """The model's ground level: a low percentile of its top-surface height over the extent."""
    gsd = max(xmax - xmin, ymax - ymin) / cells
    h = renderer.render_ortho(xmin, ymin, xmax, ymax, gsd, with_rgb=False).depth
    if not np.isfinite(h).any():
        b = renderer.model.bounds() if hasattr(renderer, "model") else renderer.bounds()
        return float(b[0, 2])
    return float(np.nanpercentile(h, percentile))


def grid_positions(xmin: float, ymin: float, xmax: float, ymax: float, interval: float) -> np.ndarray:
    """(N, 2) positions every ``interval`` metres, centred on the extent and covering it."""
    out = []
    for lo, hi in ((xmin, xmax), (ymin, ymax)):
        n = int(np.floor((hi - lo) / interval)) + 1
        out.append((lo + hi) / 2 + (np.arange(n) - (n - 1) / 2) * interval)
    xx, yy = np.meshgrid(out[0], out[1])
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


ANCHORS = ("camera", "look_at")
# A view this far off nadir or more looks at no ground point near it (at 80 deg the ray meets the
# ground level 5.7 H away, at 85 deg 11.4 H): the look_at anchor stands it at its grid position. On
# the fountain set held out (queries 2.8 m up, looking horizontally) the look_at grid kept 0 of 432
# views (its cameras 32 m back from the model), standing at the positions 164.
HORIZON_PITCH = 80.0


def make_views(extent: tuple[float, float, float, float], ground_z: float, heights, intervals,
               paper_pitches, yaw_step: float, anchor: str = "camera") -> list[View]:
    """All viewpoints, ordered level by level, position by position. ``anchor``: what the grid
    positions are: ``"camera"`` the camera centres (the paper), ``"look_at"`` the points on the
    ground level the views look at (each camera stands ``H tan(pitch)`` back from its position along
    its yaw), so oblique views look at the model from around it instead of off its edges; a pitch of
    :data:`HORIZON_PITCH` or more stands at its position either way."""
    if anchor not in ANCHORS:
        raise ValueError(f"anchor must be one of {ANCHORS}, got {anchor!r}")
    xmin, ymin, xmax, ymax = extent
    yaws = np.arange(0.0, 360.0 - 1e-9, yaw_step)
    views = []
    for H, a in zip(heights, intervals):
        for k, (x, y) in enumerate(grid_positions(xmin, ymin, xmax, ymax, a)):
            for pp in paper_pitches:
                back = H * np.tan(np.radians(pp)) if anchor == "look_at" and pp < HORIZON_PITCH else 0.0
                for yaw in yaws:
                    name = f"h{H:g}/p{k:04d}_t{pp:g}_y{yaw:03.0f}"
                    # DJI yaw: clockwise from north (+y); the view looks along (sin yaw, cos yaw)
                    cx = x - back * np.sin(np.radians(yaw))
                    cy = y - back * np.cos(np.radians(yaw))
                    views.append(View(name, float(H), float(pp), float(yaw), paper_to_dji_pitch(pp), 0.0,
                                      (round(float(cx), 3), round(float(cy), 3), float(ground_z + H))))
    return views


# --- a grid that follows the queries (gtkit.localize.flight.resolve_grid) --------------------------

def height_levels(agl, max_ratio: float = 2.0, max_levels: int = 4) -> tuple[float, ...]:
    """Database heights spanning the queries' heights above ground ``agl`` (5th-95th percentile):
    as few levels as keep every height within ``sqrt(max_ratio)`` of one (a factor 2 between levels:
    a query sees the ground at most 1.41x finer or coarser than its nearest level), geometric, whole
    metres. A 45 m flight gets one level at 45 m; 50-200 m gets 71 and 141 m. The lowest level stays
    at or above the median height / 2.5: photos far below the others by their GPS altitude are that
    altitude's error more often than a real dive (consumer GPS, each flight its own offset: small seed
    15 made consumer had photos 5 m above the ground by their GPS, levels from 10 m, and 43,624
    database views where its sister seeds had 700-3,700)."""
    h = np.asarray(agl, float)
    lo, hi = (float(v) for v in np.percentile(h, [5, 95]))
    lo = min(max(lo, float(np.median(h)) / 2.5), hi)
    n = int(min(max_levels, max(1, np.ceil(np.log(hi / lo) / np.log(max_ratio) - 1e-9))))
    return tuple(sorted({float(round(lo * (hi / lo) ** ((k + 0.5) / n))) for k in range(n)}))


def pitch_levels(off_nadir, max_step: float = 30.0) -> tuple[float, ...]:
    """Database pitches (paper convention: degrees off nadir) spanning the queries' gimbal pitches
    (5th-95th percentile) every ``max_step`` at most, so every query is within ``max_step / 2`` of a
    level; a spread under 10 deg gets one level. Whole degrees, 0-85."""
    p = np.clip(np.asarray(off_nadir, float), 0.0, 85.0)
    lo, hi = (float(v) for v in np.percentile(p, [5, 95]))
    if hi - lo < 10.0:
        return (float(round((lo + hi) / 2)),)
    n = int(np.ceil((hi - lo) / max_step - 1e-9)) + 1
    return tuple(sorted({float(round(lo + k * (hi - lo) / (n - 1))) for k in range(n)}))


def level_interval(height: float, hfov_deg: float) -> float:
    """Grid interval of a level: the paper's H / 2 at its 60 deg field of view, scaled with the
    footprint's width (``H tan(hfov / 2)``): 100 -> 50 m and 150 -> 75 m at 60 deg."""
    return float(round(0.5 * height * np.tan(np.radians(hfov_deg) / 2) / np.tan(np.radians(30.0)), 1))
