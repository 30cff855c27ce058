"""``gtkit render-db DIR``: render the localization database (RGB + depth + poses) over the model."""
from __future__ import annotations


def _floats(s: str) -> tuple[float, ...]:
    return tuple(float(v) for v in s.split(",") if v.strip())


def register(sub):
    from ..localize.database import RenderDbSettings as S

    p = sub.add_parser("render-db", help="render the localization database over the reference model")
    p.add_argument("project")
    p.add_argument("--heights", type=_floats, default=S.heights,
                   help="heights above the model's ground level, m (default %(default)s)")
    p.add_argument("--intervals", type=_floats, default=S.intervals,
                   help="grid interval per height, m (default %(default)s)")
    p.add_argument("--pitches", type=_floats, default=S.paper_pitches,
                   help="paper pitches from nadir: 0 = DJI -90, 45 = DJI -45 (default %(default)s)")
    p.add_argument("--yaw-step", type=float, default=S.yaw_step, help="deg (default %(default)s)")
    p.add_argument("--size", default=f"{S.width}x{S.height}", help="view size WxH (default %(default)s)")
    p.add_argument("--hfov", type=float, default=S.hfov_deg, help="horizontal FOV, deg (default %(default)s)")
    p.add_argument("--min-valid", type=float, default=S.min_valid_fraction,
                   help="drop views seeing less of the model than this share (default %(default)s)")
    p.add_argument("--texture-detail", choices=("views", "stored"), default=S.texture_detail,
                   help="views: textures finer than the views can show are halved on load; stored: as "
                        "stored (default %(default)s)")
    p.add_argument("--tile-budget-mb", type=float, default=S.tile_budget_mb,
                   help="memory for resident tiles of a tiled model, MB (default %(default)s)")
    _executor_args(p)
    p.add_argument("--force", action="store_true", help="re-render even when up to date")
    p.set_defaults(func=run)


def _executor_args(p):
    p.add_argument("--executor", choices=("serial", "local", "dask"), default="local",
                   help="where fan-out work runs (default: local processes)")
    p.add_argument("--workers", type=int, default=0, help="worker processes (0 = min(2, CPUs))")
    p.add_argument("--dask-address", default=None, help="existing Dask scheduler (default: a LocalCluster)")


def executor_settings(args):
    from ..localize.executors import ExecutorSettings

    return ExecutorSettings(args.executor, args.workers, args.dask_address)


def run(args):
    from ..errors import GtkitError
    from ..localize import database

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise GtkitError(f"--size must be WxH, got {args.size!r}") from None
    s = database.RenderDbSettings(heights=args.heights, intervals=args.intervals, paper_pitches=args.pitches,
                                  yaw_step=args.yaw_step, width=w, height=h, hfov_deg=args.hfov,
                                  min_valid_fraction=args.min_valid, texture_detail=args.texture_detail,
                                  tile_budget_mb=args.tile_budget_mb)
    out = database.run(args.project, s, executor_settings(args), force=args.force)
    print(f"database: {out}")
