"""``gtkit annotate DIR``: open the annotator GUI (tie points, suggestions, alignment review)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("annotate", help="open the annotator GUI on a project")
    p.add_argument("project")
    p.add_argument("--poses", help="pose file for the alignment review (default: the register stage's poses)")
    p.add_argument("--query", help="start on this query image (name relative to images/)")
    p.set_defaults(func=run, writes=False)   # no lock for the session: each save of the annotator takes it (gui/write_guard.py)


def run(args):
    from gui.app import main  # Qt is imported only here: gtkit itself never imports Qt

    return main(args.project, poses=args.poses, query=args.query)
