"""``gtkit sample create DIR [--preset small|medium|large] [--seed N] [--gps-denied]``:
generate a sample project with known truth (see :mod:`gtkit.synth`)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("sample", help="generate sample projects with known truth")
    ss = p.add_subparsers(dest="sample_command", metavar="ACTION")
    c = ss.add_parser("create", help="write a complete sample project folder")
    c.add_argument("dir", help="new (or empty) project folder")
    c.add_argument("--preset", default="small",
                   help="preset name in sample_projects/ (small, medium, large) or a .toml path")
    c.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's)")
    c.add_argument("--gps-denied", action="store_true", help="query photos without EXIF GPS")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    c.set_defaults(func=run)
    p.set_defaults(func=lambda args: p.print_help() or 2)


def run(args):
    from ..synth.generate import create_sample
    from ..synth.settings import load_preset

    s = load_preset(args.preset, seed=args.seed, gps_denied=True if args.gps_denied else None)
    summary = create_sample(args.dir, s, quiet=args.quiet)
    t = summary["timings_s"]
    print(f"sample '{s.preset}' (seed {s.seed}) written to {summary['root']}: {summary['n_reference']} reference "
          f"+ {summary['n_query']} query photos, {summary['n_gcp_clicks']} GCP clicks, "
          f"{summary['n_tiepoints']} tie points in {t['total']:.1f} s")
    print("  " + ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if k != "total"))
    from ..project import Project
    from ..view.model import prepare_cache

    print("  " + prepare_cache(Project.load(summary["root"])))
    return 0
