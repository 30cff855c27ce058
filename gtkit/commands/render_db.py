"""``gtkit render-db DIR``: render the localization database (RGB + depth + poses) over the model."""
from __future__ import annotations


def _floats(s: str) -> tuple[float, ...]:
    return tuple(float(v) for v in s.split(",") if v.strip())


def register(sub):
    from ..localize.database import PAPER_GRID as G
    from ..localize.database import RenderDbSettings as S

    p = sub.add_parser("render-db", help="render the localization database over the reference model")
    p.add_argument("project")
    # flags left out take project.toml [render_db], then RenderDbSettings' defaults (gtkit.stages.settings_for)
    p.add_argument("--heights", type=_floats, default=None,
                   help="heights above the model's ground level, m (default: from the queries' GPS altitudes above "
                        f"the model's ground, else {G['heights']})")
    p.add_argument("--intervals", type=_floats, default=None,
                   help="grid interval per height, m (default: from each height and the field of view; "
                        f"{G['intervals']} for the default heights at 60 deg)")
    p.add_argument("--pitches", type=_floats, default=None,
                   help="paper pitches from nadir: 0 = DJI -90, 45 = DJI -45 (default: spanning the queries' gimbal "
                        f"pitches, else {G['paper_pitches']})")
    p.add_argument("--yaw-step", type=float, default=None, help=f"deg (default {S.yaw_step})")
    p.add_argument("--anchor", choices=("look_at", "camera"), default=None,
                   help="grid positions are the points the views look at (look_at) or the camera centres (camera, "
                        f"the paper) (default {S.anchor})")
    p.add_argument("--size", default=None, help=f"view size WxH (default {S.width}x{S.height})")
    p.add_argument("--hfov", type=float, default=None,
                   help=f"horizontal FOV, deg (default: the queries' median, 30-90, else {G['hfov_deg']})")
    p.add_argument("--min-valid", type=float, default=None,
                   help=f"drop views seeing less of the model than this share (default {S.min_valid_fraction})")
    p.add_argument("--texture-detail", choices=("views", "stored"), default=None,
                   help="views: textures finer than the views can show are halved on load; stored: as "
                        f"stored (default {S.texture_detail})")
    p.add_argument("--tile-budget-mb", type=float, default=None,
                   help=f"memory for resident tiles of a tiled model, MB (default {S.tile_budget_mb})")
    _executor_args(p)
    p.add_argument("--views", choices=("reachable", "all"), default=None,
                   help="render the grid's views the query photos' GPS + gimbal priors can reach (default; "
                        "localize renders more when an ablation reaches more) or every view (queries flown later)")
    p.add_argument("--force", action="store_true", help="re-render even when up to date")
    p.set_defaults(func=run)


def _executor_args(p, default: str | None = "local", help: str = "where fan-out work runs (default: local processes)"):
    """--executor, --workers, --dask-address (render-db, localize, run; sfm and model build with no
    default: their work runs in the command's own process unless told)."""
    p.add_argument("--executor", choices=("serial", "local", "dask"), default=default, help=help)
    p.add_argument("--workers", type=int, default=0, help="worker processes for --executor (0 = min(2, CPUs))")
    p.add_argument("--dask-address", "--address", dest="dask_address", default=None,
                   help="existing Dask scheduler for --executor dask (default: a LocalCluster)")


def executor_settings(args):
    """The flags of :func:`_executor_args` as ExecutorSettings; None where no --executor was given
    (and it has no default)."""
    from ..localize.executors import ExecutorSettings

    if args.executor is None:
        if args.dask_address:
            from ..errors import GtkitError

            raise GtkitError("--dask-address needs --executor dask")
        return None
    return ExecutorSettings(args.executor, args.workers, args.dask_address)


def run(args):
    from ..errors import GtkitError
    from ..localize import database
    from ..project import Project
    from ..stages import STAGE, settings_for

    w = h = None
    if args.size is not None:
        try:
            w, h = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise GtkitError(f"--size must be WxH, got {args.size!r}") from None
    project = Project.load(args.project)
    STAGE["render_db"].check_inputs(project)      # every bad query photo named at once
    s = settings_for("render_db", project, {
        "heights": args.heights, "intervals": args.intervals, "paper_pitches": args.pitches,
        "yaw_step": args.yaw_step, "anchor": args.anchor, "width": w, "height": h, "hfov_deg": args.hfov,
        "min_valid_fraction": args.min_valid, "texture_detail": args.texture_detail,
        "tile_budget_mb": args.tile_budget_mb, "views": args.views})
    out = database.run(project, s, executor_settings(args), force=args.force,
                       localize_settings=settings_for("localize", project))
    print(f"database: {out}")
