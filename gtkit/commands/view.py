"""``gtkit view DIR``: the project's 3D scene as PNG snapshots in ``reports/`` (offscreen)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("view", help="3D scene (model, cameras, trajectories, GCPs, tracks) as PNG "
                       "snapshots in reports/ (offscreen, pyvista)")
    p.add_argument("project")
    p.add_argument("--size", default="1280x800", help="snapshot size WxH (default 1280x800)")
    p.add_argument("--max-triangles", type=int, default=None,
                   help="decimate the model to at most this many triangles (default 60,000; cached in work/view/)")
    p.add_argument("--out", default=None, help="folder for the PNGs (default DIR/reports)")
    p.set_defaults(func=run, writes=False)


def run(args):
    import json

    from ..errors import GtkitError
    from ..view.process import snapshots
    from ..view.settings import ViewSettings

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise GtkitError(f"--size must be WxH, e.g. 1280x800, got {args.size!r}") from None
    s = ViewSettings(width=w, height=h)
    if args.max_triangles is not None:
        s.max_triangles = args.max_triangles
    info = snapshots(args.project, s, args.out)
    print(json.dumps(info, indent=1))
    return 0
