"""``gtkit localize DIR [--ablation NAME]``: localize every query photo against the rendered database."""
from __future__ import annotations


def register(sub):
    from ..localize.localize import ABLATIONS
    from .render_db import _executor_args

    p = sub.add_parser("localize", help="6-DoF localization of the query photos (UAVLoc)")
    p.add_argument("project")
    p.add_argument("--ablation", default="default", choices=sorted(ABLATIONS),
                   help="a named variant; writes work/localize-<name>/ (default: work/localize/)")
    p.add_argument("--top-k", type=int, default=None, help="retrieved views per query (default 3)")
    p.add_argument("--gps-radius", type=float, default=None, help="keep views within this radius of GPS, m")
    p.add_argument("--queries", default=None,
                   help="only the query photos matching this glob under images/, e.g. 'queries/seq1/*' (which photos "
                        "are queries: [sfm] query_pattern, default '*_W.*')")
    p.add_argument("--db-features", choices=["reachable", "all"], default=None,
                   help="database views to extract features for: those the queries' GPS + gimbal priors can reach "
                        "(default; the same result) or all of them")
    _executor_args(p)
    p.add_argument("--force", action="store_true", help="recompute even when up to date")
    p.set_defaults(func=run)


def run(args):
    from ..localize import localize
    from ..project import Project
    from ..stages import STAGE, settings_for
    from .render_db import executor_settings

    # the ablation's settings < project.toml [localize] < the flags given (gtkit.stages.settings_for)
    project = Project.load(args.project)
    s = settings_for("localize", project, base=localize.settings_for(args.ablation), cli=
                {"top_k": args.top_k, "gps_radius_m": args.gps_radius, "query_subset": args.queries,
                 "db_features": args.db_features})
    STAGE["localize"].check_inputs(project)      # every bad query photo named at once
    out = localize.run(project, s, ablation=args.ablation, executor=executor_settings(args), force=args.force)
    print(f"poses: {out / 'poses.txt'}  status: {out / 'status.json'}")
