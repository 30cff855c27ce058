"""``gtkit evaluate results SITE RESULTS``: any method's localization result scored against the
pseudo-GT, the way the UAVD4L paper reports it, plus what its own uncertainty allows.

``SITE`` is a gtkit project (its published pseudo-GT, chosen as ``gtkit export dataset`` chooses it:
:mod:`gtkit.dataset.gt`) or a dataset ``gtkit export dataset`` wrote (its hloc pose file and
``pseudo_gt_uncertainty.txt``). ``RESULTS`` is an hloc pose file (``name qw qx qy qz tx ty tz``,
world-to-camera), a kapture folder or a COLMAP model, in the dataset's frame. ``--against truth``
(sample sites) scores against ``truth/`` instead, over the project's query photos, exactly as the
main job's localization report does.

Figures: recall at (1 m, 1°), (3 m, 3°), (5 m, 5°) over every reference photo (one the results do not
place fails), median position (camera-centre distance) and rotation (geodesic) errors, the mean
camera-centre offset (results minus reference). Sigma-aware: a photo can judge a threshold
(m, deg) only where its pseudo-GT 2-sigma lies within it (``2 sigma_pos_m <= m`` and
``2 sigma_rot_deg <= deg``, sigma as :func:`gtkit.dataset.gt.sigmas` defines it): the table
says how many photos each threshold can judge and the recall among them.

Bad input is one line naming the file: a site with no pseudo-GT, a results file of an unknown format,
results naming photos the reference does not know (photos the dataset keeps out are not judged, and
counted). Writes ``<stem>.json``, ``<stem>.md`` and ``<stem>_error_vs_sigma.png`` into ``--out``
(default: the project's ``reports/results/``, or beside the results for a dataset).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import atomic_path, write_json, write_text
from ..pose import Pose
from .poses import THRESHOLDS, medians, pose_errors, recall

AGAINST = ("pseudo-gt", "truth")


@dataclass
class Reference:
    poses: dict[str, Pose]
    sigma: dict[str, tuple[float, float]]                 # name -> (sigma_pos_m, sigma_rot_deg); {} for truth
    kept_out: dict[str, tuple[str, str]] = field(default_factory=dict)
    source: str = ""
    frame: object = None                                  # gtkit.geo.GeoFrame
    root: Path | None = None                              # the project (None for a dataset)


def load_reference(site: str | Path, against: str = "pseudo-gt") -> Reference:
    """The poses ``site`` judges against (see the module doc)."""
    from ..dataset import formats
    from ..dataset.folder import read_sheet
    from ..geo import GeoFrame

    site = Path(site)
    if against not in AGAINST:
        raise GtkitError(f"unknown reference {against!r} (choose {' or '.join(AGAINST)})")
    d = read_sheet(site) if site.is_dir() else None
    if d is not None:
        if against == "truth":
            raise GtkitError("an exported dataset holds no truth (--against truth needs a sample project)", site)
        from ..imports import read_pose_source

        hloc = site / formats.HLOC / formats.HLOC_POSES
        src = hloc if hloc.is_file() else site / "kapture" / "query"
        _k, poses, _c = read_pose_source(src)
        unc = formats.read_uncertainty(site / formats.UNCERTAINTY)
        bare = sorted(set(poses) - set(unc))
        if bare:
            raise GtkitError(f"{len(bare)} published poses have no sigma (e.g. {bare[0]})", site / formats.UNCERTAINTY)
        s = d.get("site") or {}
        return Reference({n: Pose(p.R, p.t, unc[n][2]) for n, p in poses.items()},
                         {n: (unc[n][0], unc[n][1]) for n in poses}, formats.read_kept_out(site / formats.KEPT_OUT),
                         f"the dataset's pseudo-GT ({src})", GeoFrame(str(s.get("crs")), tuple(s.get("origin") or (0, 0, 0))))
    from ..project import PROJECT_FILE, Project

    if not (site / PROJECT_FILE).is_file():
        raise GtkitError("neither a gtkit project (project.toml) nor a dataset gtkit export dataset wrote (dataset.json)",
                         site)
    project = Project.load(site)
    if against == "truth":
        from ..io.poses import read_poses
        from ..queries import query_photos

        tf = project.paths.truth_poses
        if not tf.is_file():
            raise GtkitError("no truth to score against (only sample sites have truth/)", tf)
        truth = read_poses(tf)
        names = query_photos(project)
        lacking = [n for n in names if n not in truth]
        if lacking:
            raise GtkitError(f"{len(lacking)} query photos have no true pose (e.g. {lacking[0]})", tf)
        return Reference({n: truth[n] for n in names}, {}, {}, f"truth ({tf})", project.frame, project.paths.root)
    from ..dataset.gt import collect

    gt = collect(project)
    return Reference(gt.poses, gt.sigma, gt.kept_out, f"the pseudo-GT ({project.paths.pseudo_gt_poses})",
                     project.frame, project.paths.root)


def read_results(path: str | Path, ref: Reference) -> tuple[str, dict[str, Pose], list[str]]:
    """(format, poses by reference name, names the reference keeps out) of a results file."""
    from ..imports import read_pose_source

    path = Path(path)
    if not path.exists():
        raise GtkitError("results not found", path)
    if path.is_file() and path.suffix.lower() != ".txt":
        raise GtkitError("unknown results format (expected an hloc pose file 'name qw qx qy qz tx ty tz' (.txt), "
                         "a kapture folder or a COLMAP model folder)", path)
    kind, est, _cams = read_pose_source(path, ref.frame)
    known = set(ref.poses) | set(ref.kept_out)
    unknown = sorted(n for n in est if n not in known)
    if unknown:
        raise GtkitError(f"the results name {len(unknown)} photo{'s' if len(unknown) != 1 else ''} the reference does "
                         f"not know (e.g. {unknown[0]}; reference: {ref.source})", path)
    ignored = sorted(n for n in est if n in ref.kept_out)
    return kind, {n: p for n, p in est.items() if n in ref.poses}, ignored


def score(ref: Reference, est: dict[str, Pose]) -> dict:
    """The figures of the module doc (no files)."""
    names = sorted(ref.poses)
    errors = pose_errors(est, ref.poses, names)
    rep: dict = {"n_reference": len(names), "n_localized": sum(1 for n in names if n in est)}
    rep.update(recall(errors, THRESHOLDS))
    rep.update(medians(errors))
    placed = [n for n in names if n in est]
    rep["mean_centre_offset_m"] = (np.mean([est[n].center - ref.poses[n].center for n in placed], axis=0).tolist()
                                   if placed else None)
    rows = []
    for m, d in THRESHOLDS:
        can = [n for n in names if _can_judge(ref, n, m, d)]
        ok = sum(1 for n in can if not errors[n].get("missing")
                 and errors[n]["pos_err_m"] <= m and errors[n]["rot_err_deg"] <= d)
        rows.append({"threshold_m": m, "threshold_deg": d, "n_can_judge": len(can), "n_cannot_judge": len(names) - len(can),
                     "n_pass": ok, "recall_among_judged": ok / len(can) if can else None})
    rep["sigma_aware"] = rows if ref.sigma else None
    rep["per_photo"] = {n: {**errors[n], **({"sigma_pos_m": ref.sigma[n][0], "sigma_rot_deg": ref.sigma[n][1]}
                                            if n in ref.sigma else {})} for n in names}
    return rep


def _can_judge(ref: Reference, n: str, m: float, d: float) -> bool:
    if not ref.sigma:
        return True
    sp, sr = ref.sigma[n]
    return 2 * sp <= m and 2 * sr <= d


def evaluate_results(site: str | Path, results: str | Path, against: str = "pseudo-gt",
                     out_dir: str | Path | None = None) -> dict:
    """Score ``results`` against ``site`` and write the report (see the module doc); returns it."""
    ref = load_reference(site, against)
    results = Path(results)
    kind, est, ignored = read_results(results, ref)
    rep = {"results": str(results), "format": kind, "reference": ref.source, "against": against,
           "n_results": len(est) + len(ignored), "n_ignored_kept_out": len(ignored), "ignored_kept_out": ignored,
           **score(ref, est)}
    stem = results.name if results.is_dir() else f"{results.parent.name}_{results.stem}"
    if out_dir is None:
        out_dir = (ref.root / "reports" / "results") if ref.root is not None else results.parent / f"{stem}_evaluation"
    out_dir = Path(out_dir)
    rep["plot"] = str(_plot(out_dir / f"{stem}_error_vs_sigma.png", rep)) if ref.sigma else None
    rep["json"], rep["markdown"] = str(out_dir / f"{stem}.json"), str(out_dir / f"{stem}.md")
    write_json(rep["json"], rep)
    write_text(rep["markdown"], markdown(rep))
    return rep


def _f(v, nd=3, unit=""):
    return "–" if v is None else f"{v:.{nd}f}{unit}"


def _pct(v):
    return "–" if v is None else f"{100 * v:.1f} %"


def markdown(rep: dict) -> str:
    off = rep.get("mean_centre_offset_m")
    L = [f"# Localization results: `{rep['results']}`", "",
         f"Against {rep['reference']}: {rep['n_localized']} of {rep['n_reference']} photos localized"
         + (f"; {rep['n_ignored_kept_out']} results for photos kept out of the pseudo-GT not judged" if rep["n_ignored_kept_out"] else "")
         + ".", "",
         "| (1 m, 1°) | (3 m, 3°) | (5 m, 5°) | median position error | median rotation error |", "|---|---|---|---|---|",
         f"| {_pct(rep['recall_1m1deg'])} | {_pct(rep['recall_3m3deg'])} | {_pct(rep['recall_5m5deg'])} | "
         f"{_f(rep['median_pos_err_m'], 3, ' m')} | {_f(rep['median_rot_err_deg'], 3, '°')} |", ""]
    if off is not None:
        L += [f"Mean camera-centre offset (results minus reference): dx {off[0]:+.3f} m, dy {off[1]:+.3f} m, "
              f"dz {off[2]:+.3f} m.", ""]
    if rep.get("sigma_aware"):
        L += ["Sigma-aware: a photo judges a threshold only where its pseudo-GT 2-sigma lies within it.", "",
              "| threshold | photos that can judge it | cannot (2-sigma beyond it) | pass | recall among those that can |",
              "|---|---|---|---|---|"]
        L += [f"| ({r['threshold_m']:g} m, {r['threshold_deg']:g}°) | {r['n_can_judge']} | {r['n_cannot_judge']} | "
              f"{r['n_pass']} | {_pct(r['recall_among_judged'])} |" for r in rep["sigma_aware"]]
        L += ["", f"![error vs sigma]({Path(rep['plot']).name})", ""]
    return "\n".join(L)


def _plot(path: Path, rep: dict) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per = [e for e in rep["per_photo"].values() if not e.get("missing")]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, (ek, sk, unit, th) in zip(axes, (("pos_err_m", "sigma_pos_m", "m", [t[0] for t in THRESHOLDS]),
                                              ("rot_err_deg", "sigma_rot_deg", "deg", [t[1] for t in THRESHOLDS]))):
        s = np.array([e[sk] for e in per])
        err = np.maximum(np.array([e[ek] for e in per]), 1e-6)
        if len(s):
            ax.loglog(s, err, "o", ms=4, alpha=0.7)
            lo, hi = min(s.min(), err.min()) / 2, max(s.max(), err.max(), max(th)) * 2
            ax.plot([lo, hi], [2 * lo, 2 * hi], "k--", lw=0.8, label="error = 2 sigma")
            for t in th:
                ax.axhline(t, color="#c0392b", lw=0.6, ls=":")
                ax.axvline(t / 2, color="#7f8c8d", lw=0.6, ls=":")
        ax.set_xlabel(f"pseudo-GT sigma ({unit}); dotted: threshold / 2")
        ax.set_ylabel(f"error ({unit}); dotted: thresholds")
        ax.legend(fontsize=8)
    fig.suptitle("localization error against the pseudo-GT's sigma, per photo")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path
