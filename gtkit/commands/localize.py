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
    p.add_argument("--queries", default=None, help="glob under images/ (default queries/*/*_W.jpg)")
    _executor_args(p)
    p.add_argument("--force", action="store_true", help="recompute even when up to date")
    p.set_defaults(func=run)


def run(args):
    import dataclasses

    from ..localize import localize
    from .render_db import executor_settings

    s = localize.settings_for(args.ablation)
    over = {k: v for k, v in (("top_k", args.top_k), ("gps_radius_m", args.gps_radius),
                              ("query_glob", args.queries)) if v is not None}
    s = dataclasses.replace(s, **over)
    out = localize.run(args.project, s, ablation=args.ablation, executor=executor_settings(args), force=args.force)
    print(f"poses: {out / 'poses.txt'}  status: {out / 'status.json'}")
