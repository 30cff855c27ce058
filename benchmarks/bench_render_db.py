"""Where a render-db view's time goes, on a project's model: one process, every STEP-th planned view.

    .venv/bin/python benchmarks/bench_render_db.py PROJECT [--step 50] [--model model/tiles]

Per planned view: the free ray-box probe, the 80 x 60 drawn probe (views the ray grid cannot settle),
the full 640 x 480 render (views the probes keep), the JPEG encode and the depth file write (views
kept). Printed: how many views each step ran on, ms per run, and views/s of this one process (the
stage runs two worker processes; Mesa's rasteriser threads besides). Writes nothing to the project.
Measured on medium seed 6 (README, issue 16; --step 50, idle): ray probe 2.8, drawn probe 8.2, full
render 18.3, JPEG 1.0, depth file 6.6 ms; 37.0 views/s.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("project")
    ap.add_argument("--step", type=int, default=50)
    ap.add_argument("--model", default=None, help="the model to draw, relative to the project "
                    "(default: render-db's, model/reference.obj); a folder = a tiled model, streamed")
    args = ap.parse_args()
    import cv2

    from gtkit.localize import database as D
    from gtkit.project import Project

    project = Project.load(args.project)
    s = D.RenderDbSettings() if not args.model else dataclasses.replace(D.RenderDbSettings(), model=args.model)
    t = time.perf_counter()
    views, info, s = D.plan_views(project, s)
    print(f"planned {len(views)} views in {time.perf_counter() - t:.1f} s")
    t = time.perf_counter()
    r = D._renderer_for(str(project.paths.root), s, info["ground_level_z"])
    print(f"model opened in {time.perf_counter() - t:.1f} s")
    cam = D.db_camera(s)
    probe, boxes = cam.scaled(D.PROBE_SCALE), r.boxes()
    T = {k: [0.0, 0] for k in ("ray probe", "drawn probe", "full render", "jpeg", "depth file")}

    def timed(name, fn, *a, **k):
        t0 = time.perf_counter()
        out = fn(*a, **k)
        T[name][0] += time.perf_counter() - t0
        T[name][1] += 1
        return out

    lo = s.min_valid_fraction - D.PROBE_MARGIN
    sub = views[::args.step]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for v in sub:
            frac = D.probed_fraction(r, cam, probe, v, s, boxes, timed)   # render-db's own rule
            if frac < lo:
                continue
            rr = timed("full render", D.render_view, r, cam, v, s.parts)
            frac = float(np.isfinite(rr.depth).mean())
            if frac >= s.min_valid_fraction:
                timed("jpeg", cv2.imencode, ".jpg", cv2.cvtColor(rr.rgb, cv2.COLOR_RGB2BGR),
                      [cv2.IMWRITE_JPEG_QUALITY, s.jpeg_quality])
                timed("depth file", D.write_depth, Path(tmp) / "d.npz", rr.depth, frac)
    wall = time.perf_counter() - t0
    print(f"\n{len(sub)} views (every {args.step}th), {wall:.1f} s, {len(sub) / wall:.1f} views/s in one process\n")
    print("| step | views | ms a run |\n|---|---|---|")
    for k, (sec, n) in T.items():
        print(f"| {k} | {n} | {1000 * sec / max(n, 1):.1f} |")


if __name__ == "__main__":
    main()
