"""The tie-bias test (``[register.smooth_surface]``): automatic tie points on rough model surface
(tree canopies, lit by another sun in the query and the reference photos) are kept for a sequence
only where the solution with them and the one with smooth-surface ties alone agree within what
their uncertainties allow (:func:`choose_smooth`, a Hausman test)."""
from __future__ import annotations

import logging

import numpy as np

from ...pose import Pose
from .joint import Joint, _adjust, _median_depth
from .settings import RegisterSettings
from .uncertainty import _ba_pose, position_sigma

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


def _without(clicks: dict, ties: set[str], seqs: set[str]) -> dict:
    """``clicks`` with the given ties' clicks in photos of ``seqs`` removed (a tie left with no query
    click is dropped)."""
    prefixes = tuple(f"queries/{q}/" for q in seqs)
    out = {}
    for tid, obs in clicks.items():
        if tid in ties:
            obs = {n: xy for n, xy in obs.items() if not n.startswith(prefixes)}
            if not any(n.startswith("queries/") for n in obs):
                continue
        out[tid] = obs
    return out


def _solution(j: Joint, cov) -> dict[str, tuple[Pose, float]]:
    """Query photo -> (its pose with the BA's covariance, the median depth of the points it sees)."""
    out = {}
    for iid in j.rec.reg_image_ids():
        if iid in j.ref_ids:
            continue
        out[j.rec.images[iid].name] = (_ba_pose(j.rec, cov, iid), _median_depth(j.rec, j.rec.images[iid]))
    return out


def solution_shift(a: tuple[Pose, float], s: tuple[Pose, float], on: str) -> tuple[float, float | None, float | None]:
    """How far one photo moved between two solutions ``a`` and ``s`` (each: pose with covariance,
    median depth), and each solution's 1-sigma of that quantity (None without a covariance):
    - ``"centre"``: the camera centre;
    - ``"footprint"``: what the camera sees, the ground point on its optical axis at its median
      depth (fixed in the world by solution ``a``) in the camera's frame. A camera that swings about
      the ground it sees (rotation and position trading off, a mode the photo's own rays barely
      hold) moves its centre but not this; biased ties, which shift the image, move both."""
    (pa, depth), (ps, _) = a, s
    if on == "centre":
        return float(np.linalg.norm(pa.center - ps.center)), position_sigma(pa), position_sigma(ps)
    X = pa.center + pa.R.T @ np.array([0.0, 0.0, depth])

    def sigma(p: Pose) -> float | None:
        if p.covariance is None:
            return None
        J = p.point_jacobian(X)
        return float(np.sqrt(np.trace(J @ p.covariance @ J.T)))

    return float(np.linalg.norm(pa.transform(X[None])[0] - ps.transform(X[None])[0])), sigma(pa), sigma(ps)


def choose_smooth(all_ties: dict, smooth_only: dict, factor: float, on: str = "both") -> dict[str, dict]:
    """Per sequence, whether its rough-surface automatic ties are biased: the two solutions (all ties,
    smooth-surface ties only) differ by more than ``factor`` x the spread their difference would have
    if both were unbiased, sqrt(sigma_smooth^2 - sigma_all^2) (a Hausman test; medians over the
    sequence's photos) in what ``on`` measures (:func:`solution_shift`: "centre" or "footprint"), or
    in both (``"both"``: biased ties move the camera and its view; a camera swinging about its view
    moves only the first). Inputs: photo -> (pose with covariance, median depth) of each solution."""
    if on == "both":
        c, f = choose_smooth(all_ties, smooth_only, factor, "centre"), choose_smooth(all_ties, smooth_only, factor, "footprint")
        return {q: {**c[q], **f[q], "smooth_only": c[q]["smooth_only"] and f[q]["smooth_only"], "on": "both",
                    "centre_shift_m": c[q]["shift_m"], "centre_limit_m": c[q]["limit_m"]} for q in f}
    seqs: dict[str, list[str]] = {}
    for n in all_ties:
        if n in smooth_only:
            seqs.setdefault(n.split("/")[1], []).append(n)
    out = {}
    for q, names in sorted(seqs.items()):
        shifts = [solution_shift(all_ties[n], smooth_only[n], on) for n in names]
        d = float(np.median([x[0] for x in shifts]))
        sa = [x[1] for x in shifts if x[1] is not None]
        ss = [x[2] for x in shifts if x[2] is not None]
        if not sa or not ss:   # a solution without covariance: the test cannot say, so every tie is kept
            out[q] = {"smooth_only": False, "shift_m": d, "limit_m": None, "on": on,
                      "undecided": "no covariance to test by"}
            continue
        spread = float(np.sqrt(max(np.median(ss) ** 2 - np.median(sa) ** 2, 0.0)))
        out[q] = {"smooth_only": bool(d > factor * spread), "shift_m": d, "limit_m": factor * spread, "on": on}
    return out


def tie_test_words(c: dict) -> str:
    """One sequence's smooth-surface test (a record of ``choose_smooth``, as in registration.json;
    records without ``on`` predate the footprint test and compared centres) in words."""
    def lim(v):
        return "-" if v is None else f"{v:.3f}"
    if c.get("shift_m") is None:   # not tested (its smooth ties alone do not hold it)
        return c.get("undecided", "not tested")
    what = "centres" if c.get("on", "centre") == "centre" else "footprints"
    words = f"the two solutions' {what} {c['shift_m']:.3f} m apart, limit {lim(c['limit_m'])} m"
    if "centre_shift_m" in c:
        words += f"; centres {c['centre_shift_m']:.3f} m apart, limit {lim(c['centre_limit_m'])} m"
    return words


def _smooth_ties_per_photo(clicks: dict, auto: set[str], rough: set[str], seqs) -> dict[str, int]:
    """Per sequence, the median number of automatic ties not off smooth surface its photos hold."""
    per_photo: dict[str, int] = {}
    for tid, obs in clicks.items():
        if tid in auto and tid not in rough:
            for n in obs:
                if n.startswith("queries/"):
                    per_photo[n] = per_photo.get(n, 0) + 1
    out = {}
    for q in seqs:
        counts = [c for n, c in per_photo.items() if n.split("/")[1] == q]
        out[q] = int(np.median(counts)) if counts else 0
    return out


def _adjust_choosing_ties(ref_rec, blocks, statuses, clicks: dict, auto: set[str], rough: set[str],
                          settings: RegisterSettings, calibrate: dict[str, str] | None = None):
    """The joint adjustment, with the automatic ties on rough model surface (``rough``) kept only for
    the sequences where they are not biased (``choose_smooth``); ``rough`` empty: one adjustment.
    A sequence whose smooth-surface ties alone cannot hold it (fewer than ``min_smooth`` a photo)
    keeps all of its ties untested: no test can say the others are biased, and dropping them would
    leave it tied by too little (issue 55: 0 of 178-1622 ties kept on walls and statues)."""
    if not rough:
        return (*_adjust(ref_rec, blocks, statuses, clicks, auto, settings, calibrate), {})
    ss = settings.smooth_surface
    n_smooth = _smooth_ties_per_photo(clicks, auto, rough, blocks)
    held = {q for q, n in n_smooth.items() if n >= ss.min_smooth}
    choice = {q: {"smooth_only": False, "shift_m": None, "limit_m": None, "smooth_ties_per_photo": n,
                  "undecided": f"all automatic ties kept: {n} on smooth surface a photo (median), "
                               f"{ss.min_smooth} needed to test the others"}
              for q, n in n_smooth.items() if q not in held}
    for q in sorted(choice):
        log.info("sequence %s: %s", q, choice[q]["undecided"])
    if not held:
        return (*_adjust(ref_rec, blocks, statuses, clicks, auto, settings, calibrate), choice)
    smooth_clicks = _without(clicks, rough, held)
    if ss.choose == "smooth":
        choice.update({q: {"smooth_only": True, "shift_m": None, "limit_m": None, "smooth_ties_per_photo": n_smooth[q],
                           "undecided": 'smooth-surface ties only ([register.smooth_surface] choose = "smooth")'}
                       for q in held})
        return (*_adjust(ref_rec, blocks, statuses, smooth_clicks, auto, settings, calibrate), choice)
    a = _adjust(ref_rec, blocks, statuses, clicks, auto, settings, calibrate)
    s = _adjust(ref_rec, blocks, statuses, smooth_clicks, auto, settings, calibrate)
    tested = choose_smooth(_solution(a[0], a[2]), _solution(s[0], s[2]), ss.test_factor, ss.test_on)
    tested = {q: {**c, "smooth_ties_per_photo": n_smooth[q]} for q, c in tested.items() if q in held}
    choice.update(tested)
    picked = {q for q, c in tested.items() if c["smooth_only"]}
    for q, c in sorted(tested.items()):
        log.info("sequence %s: %s (%s)", q, "automatic ties on smooth surface only" if c["smooth_only"]
                 else "all automatic ties", tie_test_words(c))
    if not picked:
        return (*a, choice)
    if picked == held:
        return (*s, choice)
    return (*_adjust(ref_rec, blocks, statuses, _without(clicks, rough, picked), auto, settings, calibrate), choice)
