"""Localization benchmark: database rendering views/s, seconds per query by step, memory peak,
recall. Prints a table; run by hand (not a test):

    python benchmarks/bench_localize.py DIR [--render-views 48] [--queries 'queries/seq1/*']

DIR must hold a reference model and (for recall) truth/. The database is rendered first when
work/render_db/ is missing (paper settings). Everything runs in this process (serial executor)
so the memory peak is the pipeline's own.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtkit.evaluate import localization as evaluation  # noqa: E402
from gtkit.localize import database, localize  # noqa: E402
from gtkit.localize.executors import ExecutorSettings  # noqa: E402
from gtkit.project import Project  # noqa: E402
from gtkit.stages import settings_for  # noqa: E402


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_render(project: Project, n: int) -> dict:
    s = database.RenderDbSettings()
    views, _info, s = database.plan_views(project, s)
    step = max(1, len(views) // n)
    views = views[::step][:n]
    t0 = time.perf_counter()
    r = database.open_model(project.paths.root, s.model, project.frame, s.tile_budget_mb)
    t_load = time.perf_counter() - t0
    cam = database.db_camera(s)
    t0 = time.perf_counter()
    for v in views:
        database.render_view(r, cam, v, s.parts)
    dt = time.perf_counter() - t0
    r.release()
    return {"model_load_s": t_load, "views": len(views), "views_per_s": len(views) / dt}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("project")
    p.add_argument("--render-views", type=int, default=48)
    p.add_argument("--queries", default=None, help="only the query photos matching this glob under images/ (default: every query photo, [sfm] query_pattern)")
    a = p.parse_args(argv)
    proj = Project.load(a.project)
    rows = []
    rb = bench_render(proj, a.render_views)
    rows.append(("render-db: views / s (640x480, one process)", f"{rb['views_per_s']:.2f}"))
    rows.append(("render-db: model load s", f"{rb['model_load_s']:.2f}"))
    rows.append(("memory peak after rendering (MiB)", f"{peak_mib():.0f}"))
    if not (proj.paths.stage(database.STAGE) / "stage.json").is_file():
        database.run(proj, settings_for("render_db", proj), ExecutorSettings("serial"),
                     localize_settings=settings_for("localize", proj))
    rec = json.loads((proj.paths.stage(database.STAGE) / "stage.json").read_text())
    rows.append(("render-db stage: views kept / planned", f"{rec['summary']['n_kept']} / {rec['summary']['n_views']}"))
    s = settings_for("localize", proj)
    if a.queries:
        s = dataclasses.replace(s, query_subset=a.queries)
    t0 = time.perf_counter()
    out = localize.run(proj, s, ablation="bench", executor=ExecutorSettings("serial"), force=True)
    wall = time.perf_counter() - t0
    st = json.loads((out / "status.json").read_text())
    off = st["offline"]
    rows.append(("db features (SIFT) s, views", f"{off['db_features_s']:.1f} s, {off['db_features_views']} views"))
    nv = max(1, off["db_features_views"])
    rows.append(("db features: CPU / wall s a view", f"{off['db_features_cpu_s'] / nv:.3f} / {off['db_features_s'] / nv:.3f}"))
    rows.append(("db features: kB a view on disk", f"{off['db_features_kb_per_view']:.0f}"))
    rows.append(("db VLAD codebook + descriptors s (CPU)", f"{off['db_global_s']:.1f} ({off['db_global_cpu_s']:.1f})"))
    rep = evaluation.evaluate(proj, ablation="bench")
    for k, v in rep["sec_per_query_by_step"].items():
        rows.append((f"s / query: {k}", f"{v:.3f}"))
    rows.append(("s / query: total (end to end)", f"{rep['sec_per_query']:.3f}"))
    rows.append(("CPU s / query (process time, all threads)", f"{rep['cpu_sec_per_query']:.3f}"))
    import os

    rows.append(("load average (1 min) at the end", f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"))
    rows.append(("localize wall s (incl. offline) / queries", f"{wall:.1f} / {rep['n_queries']}"))
    rows.append(("memory peak (MiB)", f"{peak_mib():.0f}"))
    for k in ("recall_1m1deg", "recall_3m3deg", "recall_5m5deg", "retrieval_R1", "retrieval_R3", "retrieval_P3"):
        rows.append((k, f"{100 * rep[k]:.2f} %"))
    w = max(len(r[0]) for r in rows)
    print(f"{'measure':<{w}}  value")
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
