"""Pose errors against truth and recall at (metres, degrees) thresholds."""
from __future__ import annotations

import numpy as np

from ..pose import Pose

THRESHOLDS = ((1.0, 1.0), (3.0, 3.0), (5.0, 5.0))


def pose_errors(estimated: dict[str, Pose], truth: dict[str, Pose], names=None) -> dict[str, dict]:
    """Per image: ``pos_err_m`` (camera-centre distance), ``rot_err_deg`` (geodesic), or
    ``missing: True`` when the estimate is absent (counted as a failure by :func:`recall`)."""
    out = {}
    for name in (names if names is not None else sorted(truth)):
        if name not in estimated:
            out[name] = {"missing": True}
            continue
        dp, dr = estimated[name].error_to(truth[name])
        out[name] = {"pos_err_m": dp, "rot_err_deg": dr}
    return out


def recall(errors: dict[str, dict], thresholds=THRESHOLDS) -> dict[str, float]:
    """Share of images (missing ones count as failures) within each (m, deg) threshold."""
    n = max(len(errors), 1)
    res = {}
    for m, d in thresholds:
        ok = sum(1 for e in errors.values()
                 if not e.get("missing") and e["pos_err_m"] <= m and e["rot_err_deg"] <= d)
        res[f"recall_{m:g}m{d:g}deg"] = ok / n
    return res


def medians(errors: dict[str, dict]) -> dict[str, float | None]:
    pe = [e["pos_err_m"] for e in errors.values() if not e.get("missing")]
    re = [e["rot_err_deg"] for e in errors.values() if not e.get("missing")]
    return {"median_pos_err_m": float(np.median(pe)) if pe else None,
            "median_rot_err_deg": float(np.median(re)) if re else None}


def block_frame_errors(estimated: dict[str, Pose], truth: dict[str, Pose]) -> dict[str, float] | None:
    """How a georegistered block's frame differs from the true world, split the way georegistration
    can fail: tilt (the block's up vs the true up), heading, and the camera centres' horizontal and
    vertical offsets (medians of |.|). None when no photo is in both."""
    from scipy.spatial.transform import Rotation

    names = [n for n in estimated if n in truth]
    if not names:
        return None
    Q = Rotation.from_matrix([estimated[n].R.T @ truth[n].R for n in names]).mean().as_matrix()
    d = np.array([estimated[n].center - truth[n].center for n in names])
    from ..sfm.similarity import umeyama

    E = np.array([estimated[n].center for n in names])
    T = np.array([truth[n].center for n in names])
    sim = umeyama(E, T) if len(names) >= 3 else None
    shape = float(np.median(np.linalg.norm(sim.apply(E) - T, axis=1))) if sim is not None else None
    return {"shape_m": shape,   # camera centres after the best similarity to the truth: the block's own geometry
            "tilt_deg": float(np.degrees(np.arccos(np.clip((Q @ np.array([0.0, 0.0, 1.0]))[2], -1, 1)))),
            "heading_deg": float(np.degrees(np.arctan2(Q[1, 0], Q[0, 0]))),
            "horizontal_m": float(np.median(np.linalg.norm(d[:, :2], axis=1))),
            "vertical_m": float(np.median(np.abs(d[:, 2])))}
