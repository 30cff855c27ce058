"""``gtkit evaluate DIR [--what NAME|all]``: compare a project's outputs with ``truth/``.
``gtkit evaluate results SITE RESULTS``: score a localization result (any method's hloc pose file,
kapture folder or COLMAP model) against the pseudo-GT (see :mod:`gtkit.evaluate.results`).

Each report type is a module ``gtkit/evaluate/<name>.py`` that defines
``evaluate_project(project, **options) -> dict`` (writing ``reports/<name>.json`` and a readable
twin). ``--what all`` runs every such module whose stage has outputs; a new report type needs
no change here.
"""
from __future__ import annotations

import importlib
import inspect
import pkgutil


def report_types() -> list[str]:
    from .. import evaluate

    names = []
    for m in pkgutil.iter_modules(evaluate.__path__):
        if m.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{evaluate.__name__}.{m.name}")
        if hasattr(mod, "evaluate_project"):
            names.append(m.name)
    return sorted(names)


USAGE = """gtkit evaluate DIR [--what NAME|all] [--ablation NAME]
       gtkit evaluate results SITE RESULTS [--against pseudo-gt|truth] [--out DIR]"""


def register(sub):
    p = sub.add_parser("evaluate", help="evaluate outputs against truth/ (sample sites); 'evaluate results SITE "
                       "RESULTS' scores any method's localization result against the pseudo-GT", usage=USAGE)
    p.add_argument("project", metavar="DIR | results", help="project folder, or 'results' followed by SITE RESULTS")
    p.add_argument("rest", nargs="*", metavar="SITE RESULTS", help="with 'results': a project or a dataset "
                   "'gtkit export dataset' wrote, and an hloc pose file, kapture folder or COLMAP model")
    p.add_argument("--what", default="all", help="report type (a module in gtkit/evaluate/ with "
                   "evaluate_project, e.g. localization, tracking) or 'all' (default)")
    p.add_argument("--ablation", default="default", help="localization run to evaluate (default: work/localize/)")
    p.add_argument("--against", default="pseudo-gt", choices=("pseudo-gt", "truth"),
                   help="results: score against the published pseudo-GT (default) or truth/ (sample sites)")
    p.add_argument("--out", help="results: report folder (default: the project's reports/results/, or "
                   "beside the results for a dataset)")
    p.set_defaults(func=run)


def run(args):
    import json

    from ..errors import GtkitError
    from ..project import Project

    if args.project == "results" and args.rest:
        return run_results(args)
    if args.rest:
        raise GtkitError(f"unexpected arguments {' '.join(args.rest)} (did you mean 'gtkit evaluate results SITE RESULTS'?)")
    proj = Project.load(args.project)
    kinds = report_types()
    todo = kinds if args.what == "all" else [args.what]
    for k in todo:
        if k not in kinds:
            raise GtkitError(f"unknown report type {k!r} (available: {', '.join(kinds) or 'none'})")
    done = 0
    for k in todo:
        mod = importlib.import_module(f"gtkit.evaluate.{k}")
        fn = mod.evaluate_project
        params = inspect.signature(fn).parameters
        kw = {"ablation": args.ablation} if "ablation" in params or any(
            p.kind is p.VAR_KEYWORD for p in params.values()) else {}
        try:
            rep = fn(proj, **kw)
        except GtkitError as e:
            if args.what == "all":
                print(f"{k}: skipped ({e})")
                continue
            raise
        done += 1
        keys = [x for x in rep if isinstance(rep[x], (int, float)) and not isinstance(rep[x], bool)]
        print(f"{k}: " + json.dumps({x: round(rep[x], 4) for x in keys}))
    if not done:
        raise GtkitError("nothing to evaluate (run the stages first)", proj.paths.root)


def run_results(args):
    from ..errors import GtkitError
    from ..evaluate.results import evaluate_results

    if len(args.rest) != 2:
        raise GtkitError("gtkit evaluate results needs SITE and RESULTS (a project or exported dataset, and a "
                         "pose file / kapture folder / COLMAP model)")
    rep = evaluate_results(args.rest[0], args.rest[1], args.against, args.out)
    judged = "; ".join(f"({r['threshold_m']:g} m, {r['threshold_deg']:g}°) judged by {r['n_can_judge']}/{rep['n_reference']}"
                       for r in rep["sigma_aware"] or [])
    print(f"{rep['n_localized']}/{rep['n_reference']} localized; recall (1m,1°)/(3m,3°)/(5m,5°) = "
          f"{100 * rep['recall_1m1deg']:.1f} / {100 * rep['recall_3m3deg']:.1f} / {100 * rep['recall_5m5deg']:.1f} %, "
          f"median {rep['median_pos_err_m'] if rep['median_pos_err_m'] is None else round(rep['median_pos_err_m'], 4)} m / "
          f"{rep['median_rot_err_deg'] if rep['median_rot_err_deg'] is None else round(rep['median_rot_err_deg'], 4)} deg"
          + (f"; {judged}" if judged else "")
          + (f"; {rep['n_ignored_kept_out']} results for photos kept out not judged" if rep["n_ignored_kept_out"] else "")
          + f" -> {rep['markdown']}")
    return 0
