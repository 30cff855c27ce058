"""``gtkit info DIR``: a project's CRS, origin, images, which stages are finished and who writes it
now (the project lock; info itself only reads, beside a run too)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("info", help="summarise a project folder")
    p.add_argument("project")
    p.set_defaults(func=run, writes=False)


def run(args):
    from ..project import Project, read_stage_record
    from ..project_lock import holder

    proj = Project.load(args.project)
    P = proj.paths
    print(f"project   {proj.name}  ({P.root})")
    print(f"crs       {proj.frame.crs_spec}  origin {list(proj.frame.origin)}")
    h = holder(P.root)
    print(f"writer    {h.describe() if h else 'none (no gtkit command writes it now)'}")
    n_ref = len(list(P.reference_images.glob("*.*"))) if P.reference_images.is_dir() else 0
    print(f"reference {n_ref} photos")
    for seq in P.query_sequences():
        print(f"sequence  {seq}: {len(list((P.query_images / seq).glob('*.*')))} photos")
    if P.work.is_dir():
        for d in sorted(p for p in P.work.iterdir() if p.is_dir()):
            rec = read_stage_record(d)
            if rec is not None:
                print(f"stage     {d.name}: finished {rec.finished}")
