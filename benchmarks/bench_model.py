"""``gtkit model build`` measured: time and peak memory per step, the built model's DSM against the
true world (and the delivered model's beside it), their height difference, overlay misalignment at
the true query poses with each model.

    gtkit sample create S && mv S/model S_delivered_model && gtkit sfm S --block reference
    .venv/bin/python benchmarks/bench_model.py S --delivered S_delivered_model/reference.obj [--overlays]

Reads truth/ (evaluation). DSMs of both models on the same grid resolution (``--resolution``);
cells within 1 m of a true height jump > 2 m are reported apart (gtkit.evaluate.model). Prints one
table; times are wall seconds on this machine (a shared, noisy 2-core box unless said otherwise),
with the build's CPU seconds per step beside them (the load inflates wall time, not CPU time).

A medium site whose build already ran (or runs elsewhere, e.g. under ``nohup``) is measured without
building again: the stage is up to date, so the call only reads its record and makes the DSMs.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from gtkit.project import Project, StageClock  # noqa: E402


def _row(name, m):
    o, a, e = m["off_edges"], m["all"], m["near_edges"]
    extra = f" | {100 * m['completeness_of_other_area']:.2f} %" if "completeness_of_other_area" in m else " | "
    return (f"| {name} | {m['resolution']} | {100 * m['completeness']:.2f} %{extra} | {o['median']:.3f} | {o['p95']:.3f} | "
            f"{a['median']:.3f} | {a['p95']:.3f} | {e['median']:.3f} / {e['p95']:.2f} | {m['bias']:+.3f} |")


def _overlays(root: Path, model: Path) -> float:
    """Median misalignment (full-resolution px) of the wide query photos at their TRUE poses over ``model``."""
    import numpy as np

    from gtkit.render.overlay import OverlayScene, alignment

    truth_poses = root / "truth" / "poses.txt"
    scene = OverlayScene(Project.load(root), truth_poses, model_path=model)
    names = [n for n in scene.images() if n.endswith("_W.jpg")]
    mis = []
    for n in names:
        photo, rgb, valid, s = scene.render(n, 1024)
        mis.append(alignment(photo, rgb, valid, scale=s).misalignment_px)
    return float(np.nanmedian(mis))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("project")
    ap.add_argument("--delivered", help="the delivered model (OBJ + sidecar) to set beside the built one")
    ap.add_argument("--resolution", type=float, default=0.5, help="DSM cell, m (default %(default)s)")
    ap.add_argument("--overlays", action="store_true", help="also overlay misalignment at the true query poses")
    ap.add_argument("--force", action="store_true", help="rebuild the model (depth maps are kept)")
    a = ap.parse_args(argv)

    from gtkit.evaluate.model import dsm_vs_truth
    from gtkit.export import dsm
    from gtkit.model.build import run as build
    from gtkit.model.compare import run as compare

    from gtkit.stages import settings_for

    root = Path(a.project)
    t0 = time.time()
    summary = build(root, settings_for("model", Project.load(root)), force=a.force)
    wall = time.time() - t0
    proj = Project.load(root)
    built = root / summary["model"]
    s = dsm.DsmSettings(resolution=a.resolution)
    costs = {}  # each measurement's wall / CPU seconds and its own peak memory (gtkit.project.StageClock)

    def timed(name, fn, *args, **kw):
        clock = StageClock()
        out = fn(*args, **kw)
        c = clock.cost([])
        costs[name] = {k: c[k] for k in ("wall_s", "cpu_s", "peak_rss_gb", "load_avg_1m")}
        return out

    d_built = timed("dsm built", dsm.run, proj, s, input=built, out=root / "exports" / "dsm_built.tif")
    rows = []
    if a.delivered:
        d_del = timed("dsm delivered", dsm.run, proj, s, input=Path(a.delivered),
                      out=root / "exports" / "dsm_delivered.tif")
        rows.append(("built", timed("truth (built)", dsm_vs_truth, root, d_built, area_of=d_del)))
        rows.append(("delivered", timed("truth (delivered)", dsm_vs_truth, root, d_del)))
        diff = timed("compare", compare, proj, built, Path(a.delivered), a.resolution,
                     root / "exports" / "model_diff.tif")
    else:
        rows.append(("built", timed("truth (built)", dsm_vs_truth, root, d_built)))
        diff = None
    print(f"\nmodel build of {root}: {summary['depth_maps']} depth maps of {summary['photos']} photos, "
          f"{summary['points']} fused points, {summary['triangles']} triangles in {summary['parts']} parts "
          f"({wall:.0f} s wall in this call; {os.cpu_count()} CPUs)")
    print("seconds per step (wall): " + json.dumps(summary["seconds"])
          + ("; CPU seconds: " + json.dumps(summary["cpu_seconds"]) if "cpu_seconds" in summary else "")
          + "; peak memory GB in each step: " + json.dumps(summary["peak_memory_gb"]))
    print(f"load average at the end: {os.getloadavg()[0]:.1f} / {os.getloadavg()[1]:.1f} / {os.getloadavg()[2]:.1f} (1/5/15 min)")
    print("measurement (wall s / CPU s / own peak memory GB / 1-min load at start, end): " + "; ".join(
        f"{n} {c['wall_s']:.0f} / {c['cpu_s']:.0f} / {c['peak_rss_gb']:.2f} / {c['load_avg_1m']}" for n, c in costs.items()))
    for n, why in summary["skipped"].items():
        print(f"  skipped {n}: {why}")
    print("\n| model | cell m | completeness (grid) | (of delivered area) | median off edges | p95 off edges | "
          "median all | p95 all | near edges median / p95 | bias |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, m in rows:
        print(_row(name, m))
    if diff:
        print(f"\nbuilt - delivered: median {diff['median']:+.3f} m, median |d| {diff['median_abs']:.3f} m, "
              f"p95 |d| {diff['p95_abs']:.3f} m over {diff['cells']} cells ({diff['out']})")
    if a.overlays:
        # the scene reads an OBJ with gtkit.io.obj_geometry, a material at a time (bounded memory)
        ov = {"built": timed("overlays (built)", _overlays, root, built)}
        if a.delivered:
            ov["delivered"] = timed("overlays (delivered)", _overlays, root, Path(a.delivered))
        print("overlay median misalignment at the true query poses (px): " + json.dumps(ov))
        print("overlays (wall s / CPU s / own peak memory GB): " + "; ".join(
            f"{n} {c['wall_s']:.0f} / {c['cpu_s']:.0f} / {c['peak_rss_gb']:.2f}" for n, c in costs.items()
            if n.startswith("overlays")))
    out = root / "reports" / "bench_model.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"summary": summary, "dsm": dict(rows), "diff": diff, "measurement_cost": costs,
                               "overlays": ov if a.overlays else None}, indent=1))


if __name__ == "__main__":
    main()
