"""GCP clicks made on photos of another size, and the click threshold that the clicks' own
consistency and the photo size call for.

Web GCP editors and older pipelines resize the photos before they are clicked, and the GCP file
travels with the clicks in the resized pixels. Two signs give it away, both needed:
- **a box**: every click lies inside the top-left w/k x h/k of its photo (4 or more clicks: by
  chance 1 in k^(2n));
- **reprojection**: each GCP triangulated in the model from its clicks scaled by k reprojects
  better by about that factor than from the clicks as given (where 2 or more GCPs have 2 or more
  clicks in posed photos; otherwise the box alone is reported, not applied).

``detect_click_scale`` says what it found in one line; the georegistration applies the scale
(``[sfm.georegister] gcp_click_scale = "auto"``, the default, or a number) or refuses naming it and
that setting (``"off"``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..io.odm import GCP, GCPClick
from .geometry import triangulate_clicks

FACTORS = (4.0, 3.0, 2.0)


@dataclass
class ClickScale:
    factor: float          # the clicks' pixels times this are the photos' pixels
    confirmed: bool        # the reprojection drops by the factor (not the box alone)
    n_clicks: int
    box: str               # "2304 x 1728 of 4608 x 3456"
    before_px: float | None = None   # median reprojection of the GCPs' clicks as given
    after_px: float | None = None    # ... scaled by the factor

    def line(self) -> str:
        rep = (f"; reprojection {self.before_px:.1f} px as given, {self.after_px:.1f} px x {self.factor:g}"
               if self.before_px is not None else "; not confirmed: no 2 GCPs with 2 clicks in posed photos")
        return (f"GCP clicks look made on 1/{self.factor:g}-size photos (all {self.n_clicks} inside {self.box}{rep})")

    def record(self) -> dict:
        return {"factor": self.factor, "confirmed": self.confirmed, "n_clicks": self.n_clicks, "box": self.box,
                "reprojection_as_given_px": self.before_px, "reprojection_scaled_px": self.after_px, "line": self.line()}


def scaled(gcps: list[GCP], factor: float) -> list[GCP]:
    """Copies of ``gcps`` with every click's pixel coordinates times ``factor``."""
    return [replace(g, clicks=[GCPClick(c.image, c.x * factor, c.y * factor) for c in g.clicks]) for g in gcps]


def _median_reprojection(gcps: list[GCP], cams: dict, poses: dict, factor: float) -> tuple[float | None, int]:
    worst = []
    for g in gcps:
        clicks = [c for c in g.clicks if c.image in poses]
        if len(clicks) < 2:
            continue
        tri = triangulate_clicks([cams[c.image] for c in clicks], [poses[c.image] for c in clicks],
                                 factor * np.array([[c.x, c.y] for c in clicks]), max_px=np.inf, min_angle_deg=0.0)
        r = tri.residuals_px[np.isfinite(tri.residuals_px)]
        if tri.xyz is not None and len(r):
            worst.append(float(r.max()))
    return (float(np.median(worst)) if worst else None), len(worst)


def detect_click_scale(gcps: list[GCP], cams: dict, poses: dict, min_clicks: int = 4) -> ClickScale | None:
    """The scale of the GCP clicks (see the module docstring); ``cams`` / ``poses``: {photo: gtkit
    Camera / Pose} of the model's posed photos. None where the clicks fill their photos."""
    clicks = [c for g in gcps for c in g.clicks if c.image in cams]
    if len(clicks) < min_clicks:
        return None
    wh = np.array([[cams[c.image].width, cams[c.image].height] for c in clicks], float)
    xy = np.array([[c.x, c.y] for c in clicks], float)
    for k in FACTORS:
        if np.all(xy <= wh / k + 0.5):
            w, h = np.median(wh, axis=0)
            box = f"{w / k:.0f} x {h / k:.0f} of {w:.0f} x {h:.0f}"
            before, n = _median_reprojection(gcps, cams, poses, 1.0)
            after, _ = _median_reprojection(gcps, cams, poses, k)
            if before is None or after is None or n < 2:
                return ClickScale(k, False, len(clicks), box)
            return ClickScale(k, bool(after < before / (0.75 * k)), len(clicks), box, round(before, 2), round(after, 2))
    return None


def click_threshold_px(gcps: list[GCP], cams: dict, poses: dict, floor_px: float = 4.0) -> dict:
    """The click threshold from the clicks' own consistency and the photo size: 3 robust sigmas of
    the click residuals of GCPs with 3 or more clicks (each triangulated from all its clicks), never
    under ``floor_px`` per 2,000 px of photo diagonal (and never under ``floor_px``), never over
    0.5 % of the diagonal (where that is larger than the floor). Returns {"max_px", "diagonal_px", "click_sigma_px", "n_gcps"}."""
    diag = [float(np.hypot(cams[c.image].width, cams[c.image].height)) for g in gcps for c in g.clicks if c.image in cams]
    d = float(np.median(diag)) if diag else 2000.0
    lo, hi = floor_px * max(1.0, d / 2000.0), 0.005 * d
    res = []
    for g in gcps:
        cl = [c for c in g.clicks if c.image in poses]
        if len(cl) < 3:   # two rays meet a point that fits them both: only 3 or more tell a click's error
            continue
        tri = triangulate_clicks([cams[c.image] for c in cl], [poses[c.image] for c in cl],
                                 np.array([[c.x, c.y] for c in cl]), max_px=np.inf, min_angle_deg=0.0)
        if tri.xyz is not None:
            res += [float(r) for r in tri.residuals_px if np.isfinite(r)]
    sigma = float(1.4826 * np.median(res)) if len(res) >= 3 else None
    thr = lo if sigma is None else float(np.clip(3.0 * sigma, lo, max(hi, lo)))
    return {"max_px": round(thr, 2), "diagonal_px": round(d, 1), "click_sigma_px": None if sigma is None else round(sigma, 2),
            "n_gcps": len({g.name for g in gcps})}
