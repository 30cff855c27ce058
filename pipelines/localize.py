"""UAVLoc, top to bottom: render the database, localize every query, evaluate against truth.

    python -m pipelines.localize DIR                 # render-db -> localize -> evaluate (default settings)
    python -m pipelines.localize DIR --ablations     # + every ablation (the paper's tables), one table
    python -m pipelines.localize DIR --ablations no-gravity top1

The database is rendered with the project's [render_db] settings (gtkit.stages.settings_for, as
`gtkit render-db` and `gtkit run`; it resumes when settings and inputs match), by default a grid that
follows the queries' heights, gimbal pitches and field of view (gtkit.localize.database.resolve_grid;
without them the paper's grid plus a 70-degree off-nadir level; ablation 'render-paper' = the paper's
pitches only). Each ablation writes work/localize-<name>/ and reports/localization-<name>.json; finished runs
are reused when their settings match, so re-running only computes what changed.
"""
from __future__ import annotations

import argparse
import sys

from gtkit.errors import GtkitError
from gtkit.evaluate import localization as evaluation
from gtkit.localize import database, localize
from gtkit.localize.executors import ExecutorSettings

COLUMNS = ("recall_1m1deg", "recall_3m3deg", "recall_5m5deg", "retrieval_R1", "retrieval_R3", "retrieval_P3")


def run(root, ablations=("default",), executor: ExecutorSettings = ExecutorSettings()) -> dict[str, dict]:
    """The database, then each ablation's localization, then its evaluation against truth; settings
    from the stage table (project.toml [render_db] / [localize] over the defaults; an ablation's
    changes over the defaults), each stage resuming when its settings and inputs match."""
    from gtkit.project import Project
    from gtkit.stages import settings_for

    project = Project.load(root)
    loc = settings_for("localize", project)
    database.run(project, settings_for("render_db", project), executor, localize_settings=loc)   # 1. offline
    reports = {}
    for name in ablations:
        s = settings_for("localize", project, base=localize.settings_for(name))
        localize.run(project, s, ablation=name, executor=executor)          # 2. online
        reports[name] = evaluation.evaluate(project, ablation=name)         # 3. against truth
    return reports


def table(reports: dict[str, dict]) -> str:
    head = "| run | (1m,1°) | (3m,3°) | (5m,5°) | R@1 | R@3 | P@3 | med. m | med. ° | s/query |"
    rows = [head, "|" + "---|" * 10]
    for name, r in reports.items():
        cells = [f"{100 * r[c]:.2f}" if r.get(c) is not None else "-" for c in COLUMNS]
        med = [f"{r[k]:.3f}" if r.get(k) is not None else "-" for k in ("median_pos_err_m", "median_rot_err_deg")]
        rows.append(f"| {name} | " + " | ".join(cells + med) + f" | {r['sec_per_query']:.2f} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m pipelines.localize", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("project")
    p.add_argument("--ablations", nargs="*", default=None,
                   help=f"run these ablations too (none named = all: {', '.join(localize.ABLATIONS)})")
    p.add_argument("--executor", default="local", choices=("serial", "local", "dask"))
    p.add_argument("--workers", type=int, default=0)
    a = p.parse_args(argv)
    names = ["default"] if a.ablations is None else (a.ablations or list(localize.ABLATIONS))
    if "default" not in names:
        names.insert(0, "default")
    try:
        reports = run(a.project, names, executor=ExecutorSettings(a.executor, a.workers))
    except GtkitError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(table(reports))
    return 0


if __name__ == "__main__":
    sys.exit(main())
