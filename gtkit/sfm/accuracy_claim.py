"""The absolute accuracy a georegistered block can claim (issue 57), from the evidence: the points'
stated accuracy, else the fit's leave-one-out error, its jackknife spread at the cameras and check
points, else the source's typical accuracy; and which evidence it rests on. Computed once, in
:func:`gtkit.sfm.georegister.georegister` (``report["claimed_accuracy"]``); every report and printout
reads that record. The fitted transform is never changed here."""
from __future__ import annotations

import numpy as np


def fitted_to(kinds: np.ndarray, inliers: np.ndarray) -> str:
    """What the fit rests on, in words: "12 GCPs", "118 GPS positions", "4 GCPs + 120 GPS positions"."""
    parts = []
    for k, label in (("gcp", "GCPs"), ("gps", "GPS positions")):
        n = int((inliers & (kinds == k)).sum())
        if n:
            parts.append(f"{n} {label}")
    return " + ".join(parts) or "nothing"


SURVEY_GRADE_M = 0.3        # positions scattering more than this (per axis, horizontal) are GPS-grade:
                            # a common bias as large as a GPS's (gps_fit.UNSTATED_BIAS_*) is assumed
MIN_STRONG_POINTS = 6       # fewer points in the fit: leave-one-out says little (the claim is weak)
CONTRADICTS = 1.5           # evidence this many times the stated accuracy overrules it
TYPICAL_GCP_M = (0.05, 0.10)  # surveyed GCPs (h, v), said only where nothing measures them


def weak_inflation(n: int) -> float:
    """How much larger a scatter measured on ``n`` points of a Sim(3) fit (3n - 7 degrees of freedom)
    may be at 95 % confidence: sqrt(dof / chi2_0.05(dof)) (4 points: 2.1; 5 points: 1.7)."""
    from scipy.stats import chi2

    dof = max(3 * n - 7, 1)
    return float(np.sqrt(dof / chi2.ppf(0.05, dof)))


def _axes(d: np.ndarray) -> tuple[float, float]:
    """1-sigma per horizontal axis (RMS of the 2-D error over sqrt 2) and vertical RMS of errors ``d`` (n, 3)."""
    d = np.asarray(d, float).reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)) / 2.0)), float(np.sqrt(np.mean(d[:, 2] ** 2)))


def leave_one_out(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray | None = None, at: np.ndarray | None = None,
                  max_points: int = 200, seed: int = 0) -> tuple[np.ndarray, tuple[float, float] | None]:
    """Each point's error when the Sim(3) is fitted without it (n, 3: predicted - target), and the
    jackknife spread of the transform at points ``at`` (block frame; the cameras), 1 sigma per
    horizontal axis and vertical, RMS over ``at``. Over ``max_points`` points: a seeded sample."""
    from .similarity import umeyama

    src, tgt = np.asarray(src, float), np.asarray(tgt, float)
    n = len(src)
    idx = np.arange(n) if n <= max_points else np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))
    errs, moved = [], []
    for i in idx:
        keep = np.arange(n) != i
        s = umeyama(src[keep], tgt[keep], None if weights is None else np.asarray(weights)[keep])
        if s is None:
            continue
        errs.append(s.apply(src[i][None])[0] - tgt[i])
        if at is not None and len(at):
            moved.append(s.apply(at))
    jack = None
    if len(moved) >= 2:
        m = np.array(moved)                       # (k, n_at, 3)
        dev = m - m.mean(axis=0)
        var = (n - 1) / len(moved) * np.sum(dev ** 2, axis=0)   # jackknife variance per point and axis
        jack = (float(np.sqrt(np.mean(var[:, :2]) )), float(np.sqrt(np.mean(var[:, 2]))))
    return np.array(errs).reshape(-1, 3), jack


def accuracy_claim(*, kinds: np.ndarray, inliers: np.ndarray, src: np.ndarray, tgt: np.ndarray,
                   weights: np.ndarray | None, cameras: np.ndarray, stated: list, fit_mode: str,
                   gps_quality: dict | None, checkpoints: list[np.ndarray]) -> dict:
    """The absolute accuracy (1 sigma, horizontal per axis and vertical) the georegistered block can
    claim, from the evidence, and which evidence it rests on (``source``):

    - ``stated``: the points' stated accuracy (geo.txt accuracy columns, the GCPs' stated accuracy)
      where most points in the fit carry one, unless the fit's own errors are more than 1.5 times
      larger (then those, saying the stated accuracy is contradicted);
    - ``leave-one-out`` / ``check points``: else the error of each point when the Sim(3) is fitted
      without it (a fit of N points absorbs part of their error; leaving one out does not), combined
      with the transform's jackknife spread at the cameras (GCPs far below the cameras: their lever
      arm), and the check points' error where any are marked (the larger rules). Positions that
      scatter like a GPS's (> SURVEY_GRADE_M) carry a common bias that no residual shows: the
      source's typical bias is added (``fit + typical GPS bias``). Fewer than 6 points and no check
      point: ``weak``, the leave-one-out scatter taken at its 95 % upper bound (:func:`weak_inflation`:
      on the tiny sample's 4 GCPs the cameras were off by up to 3 x the plain figure);
    - ``typical``: only 3 points (nothing left to check the fit with) and nothing stated: the
      source's typical accuracy, weak.
    A gravity-held fit (consumer GPS, its tilt from gravity) claims from its horizontal and vertical
    scatter (after the altitude drift; heights + half the drift) the same way.

    ``kinds``/``inliers``/``src``/``tgt``: the fit's points (block frame -> world); ``weights``:
    their weights in the fit (None: equal); ``cameras``: the block's camera centres (block frame);
    ``stated``: each point's stated (h, v) or None; ``checkpoints``: check points' errors (3-vectors)."""
    from .gps_fit import UNSTATED_BIAS_H_M, UNSTATED_BIAS_V_M

    inl = np.asarray(inliers, bool)
    kinds = np.asarray(kinds)
    n = int(inl.sum())
    what = fitted_to(kinds, inl)
    ev: dict = {"n_points": n}
    st = [s for s, ok in zip(stated, inl) if ok and s is not None]
    st_h = st_v = None
    if st and len(st) >= n / 2:
        st_h = float(np.median([s[0] for s in st]))
        st_v = float(np.median([s[1] if s[1] is not None else s[0] for s in st]))
        ev["stated_h_m"], ev["stated_v_m"] = st_h, st_v
    gps_in = inl & (kinds == "gps")
    emp = None           # (h, v) from the fit's own errors
    how = ""
    if fit_mode in ("gravity-held", "combined") and gps_quality and gps_quality.get("scatter_h_m") is not None:
        # the tilt from gravity: heading, scale, position from the positions (4 parameters)
        k = max(float(gps_quality.get("n_effective") or n), 2.0)
        infl = float(np.sqrt(1.0 + 4.0 / (3.0 * k)))
        emp = (float(gps_quality["scatter_h_m"]) * infl, float(gps_quality["scatter_v_m"]) * infl)
        ev["scatter_h_m"], ev["scatter_v_m"] = gps_quality["scatter_h_m"], gps_quality["scatter_v_m"]
        how = f"the scatter of {int(gps_in.sum())} GPS positions about a gravity-held fit"
    elif n >= 4:
        loo, jack = leave_one_out(np.asarray(src)[inl], np.asarray(tgt)[inl],
                                  None if weights is None else np.asarray(weights)[inl], cameras)
        if len(loo):
            lh, lv = _axes(loo)
            ev["leave_one_out_h_m"], ev["leave_one_out_v_m"] = round(lh, 4), round(lv, 4)
            if jack is not None:
                ev["transform_at_cameras_h_m"], ev["transform_at_cameras_v_m"] = round(jack[0], 4), round(jack[1], 4)
            k = weak_inflation(n) if n < MIN_STRONG_POINTS and not checkpoints else 1.0
            if k > 1.0:   # few points: the 95 % upper bound of the scatter they show
                lh, lv = lh * k, lv * k
                ev["weak_inflation"] = round(k, 2)
            emp = (float(np.hypot(lh, jack[0] if jack else 0.0)), float(np.hypot(lv, jack[1] if jack else 0.0)))
            how = (f"the fit's leave-one-out error over {what}" + (f" (x{k:.1f}: its 95 % upper bound)" if k > 1.0 else "")
                   + (" and its spread at the cameras" if jack else ""))
    if checkpoints:
        ch, cv = _axes(np.array(checkpoints))
        ev["checkpoints_h_m"], ev["checkpoints_v_m"], ev["n_checkpoints"] = round(ch, 4), round(cv, 4), len(checkpoints)
        if emp is None or ch > emp[0] or cv > emp[1]:
            emp = (max(ch, emp[0] if emp else 0.0), max(cv, emp[1] if emp else 0.0))
            how = f"{len(checkpoints)} check point{'s' if len(checkpoints) > 1 else ''}" + (f" and {how}" if how else "")
    weak = n < MIN_STRONG_POINTS and not checkpoints
    r = lambda v: round(float(v), 4)   # noqa: E731
    if st_h is not None and (emp is None or (emp[0] <= CONTRADICTS * st_h and emp[1] <= CONTRADICTS * st_v)):
        h, v, source = st_h, st_v, "stated"
        detail = (f"the stated accuracy of {what}"
                  + (f" (the fit's own errors agree: {_m(emp[0])} / {_m(emp[1])} by {how})" if emp else ""))
        weak = False
    elif emp is not None:
        h, v = emp
        source = "check points" if how.startswith(f"{len(checkpoints)} check point") and checkpoints else (
            "gravity-held fit" if fit_mode in ("gravity-held", "combined") else "leave-one-out")
        detail = how
        if st_h is not None:
            detail += f" (larger than the stated {_m(st_h)} / {_m(st_v)}, which the fit contradicts)"
        elif gps_in.sum() and emp[0] > SURVEY_GRADE_M:
            # GPS-grade positions: their common bias does not show in any residual
            h = float(np.hypot(emp[0], max(emp[0], UNSTATED_BIAS_H_M)))
            v = float(np.hypot(emp[1], max(emp[1], UNSTATED_BIAS_V_M)))
            source += " + typical GPS bias"
            detail += (f", and a typical GPS bias: the positions scatter like a GPS's ({_m(emp[0])}), so a common bias of "
                       "at least "
                       f"{UNSTATED_BIAS_H_M:g} m horizontal / {UNSTATED_BIAS_V_M:g} m vertical is assumed (no residual "
                       "shows it): give geo.txt accuracy columns, GCPs or check points to claim more")
        elif not checkpoints:
            detail += "; a common offset of every point would not show here: check points measure it"
        if weak:
            detail += f" (weak: only {n} points in the fit)"
    else:
        # nothing left over to check the fit with: the source's typical accuracy
        weak, source = True, "typical"
        if gps_in.sum():
            h, v = UNSTATED_BIAS_H_M, UNSTATED_BIAS_V_M
            detail = f"a consumer GPS's typical accuracy (weak: only {what}, nothing left to check the fit with)"
        else:
            h, v = TYPICAL_GCP_M
            detail = (f"surveyed GCPs' typical accuracy (weak: only {what}, nothing left to check the fit with; "
                      "mark a check point)")
    # the words every display prints (reference report, gtkit sfm, the run summary, the GT report)
    line = f"absolute accuracy ~{_m(h)} horizontal / ~{_m(v)} vertical (1 sigma) from {detail}"
    short = f"absolute accuracy ~{_m(h)} horizontal / ~{_m(v)} vertical (1 sigma, {source}{', weak' if weak else ''})"
    return {"h_m": r(h), "v_m": r(v), "source": source, "weak": bool(weak), "detail": detail, "line": line,
            "short": short, "evidence": ev}


def _m(v: float) -> str:
    """Metres to the precision a claim deserves: 2 significant figures, mm at least."""
    return (f"{v:.0f} m" if v >= 10 else f"{v:.2g} m" if v >= 0.01 else f"{v * 1000:.0f} mm" if v >= 0.001
            else f"{v * 1000:.1f} mm")


def claim_of_fit(names: list[str], kinds: np.ndarray, inliers: np.ndarray, src, tgt, sigmas: dict | None,
                 cameras: np.ndarray, stated: tuple, fit_mode: str, gps_quality: dict | None, report: dict) -> dict:
    """:func:`accuracy_claim` of one georegistration fit, from what ``georegister`` holds: each group
    weighted by its own scatter (``sigmas``); ``stated`` = (GPS accuracy by photo, GCP (h, v) by name,
    the GCPs' default); the check points' errors from ``report["gcp_residuals"]``."""
    gps_acc, gcp_acc, gcp_default = stated
    return accuracy_claim(
        kinds=kinds, inliers=inliers, src=np.array(src), tgt=np.array(tgt),
        weights=np.array([1.0 / max(sigmas[k], 1e-6) ** 2 for k in kinds]) if sigmas else None, cameras=cameras,
        stated=[stated_accuracy(n, k, gps_acc, gcp_acc, gcp_default) for n, k in zip(names, kinds)],
        fit_mode=fit_mode, gps_quality=gps_quality,
        checkpoints=[np.array([v["dx_m"], v["dy_m"], v["dz_m"]]) for v in report["gcp_residuals"].values()
                     if v["status"] == "ok" and v["check"]])


def stated_accuracy(name: str, kind: str, gps_accuracy: dict, gcp_accuracy: dict, gcp_default: float | None):
    """A fit point's stated (h, v) accuracy in metres, or None."""
    if kind == "gps":
        a = gps_accuracy.get(name)
        return (float(a), float(a)) if a else None
    h, v = gcp_accuracy.get(name, (None, None))
    h = h or gcp_default
    return (float(h), float(v or h)) if h else None
