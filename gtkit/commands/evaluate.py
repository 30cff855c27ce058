"""``gtkit evaluate DIR [--what NAME|all]``: compare a project's outputs with ``truth/``.

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


def register(sub):
    p = sub.add_parser("evaluate", help="evaluate outputs against truth/ (sample sites)")
    p.add_argument("project")
    p.add_argument("--what", default="all", help="report type (a module in gtkit/evaluate/ with "
                   "evaluate_project, e.g. localization, tracking) or 'all' (default)")
    p.add_argument("--ablation", default="default", help="localization run to evaluate (default: work/localize/)")
    p.set_defaults(func=run)


def run(args):
    import json

    from ..errors import GtkitError
    from ..project import Project

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
