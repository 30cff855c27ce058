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


def make_views(extent: tuple[float, float, float, float], ground_z: float, heights, intervals,
               paper_pitches, yaw_step: float) -> list[View]:
    """All viewpoints, ordered level by level, position by position."""
    xmin, ymin, xmax, ymax = extent
    yaws = np.arange(0.0, 360.0 - 1e-9, yaw_step)
    views = []
    for H, a in zip(heights, intervals):
        for k, (x, y) in enumerate(grid_positions(xmin, ymin, xmax, ymax, a)):
            for pp in paper_pitches:
                for yaw in yaws:
                    name = f"h{H:g}/p{k:04d}_t{pp:g}_y{yaw:03.0f}"
                    views.append(View(name, float(H), float(pp), float(yaw), paper_to_dji_pitch(pp), 0.0,
                                      (float(x), float(y), float(ground_z + H))))
    return views
