"""Tile streaming memory and speed: a 100-tile textured model, rendered view by view.

    .venv/bin/python benchmarks/bench_tiles.py [--tiles-side 10] [--tex 512] [--cells 40] [--budget 64]

Writes a synthetic 10 x 10-tile model (each 50 m tile has its own texture, like a ContextCapture
delivery), then measures in separate processes (so peak memory is each mode's own):
  stream   TileStreamer with a memory budget: only the tiles in each view's frustum are uploaded
  all      the whole model loaded and uploaded at once, then the same views
  dsm-*    a 0.25 m top-down raster (DSM heights + ortho colours) of the whole site in 512 px windows,
           streamed under the budget or with the whole model uploaded ("view ms" = the whole raster)
Printed per mode: tiles drawn / loaded per view, resident tiles, resident memory (VmRSS) after
the views, peak memory (VmHWM), time per view (load + render).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

CRS, ORIGIN = "EPSG:32650", (500000.0, 4000000.0, 0.0)


def vm(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0  # MiB
    return float("nan")


def views(n_side: int, tile_m: float):
    from gtkit.pose import Pose

    half = n_side * tile_m / 2
    rng = np.random.default_rng(0)
    out = []
    for k in range(12):  # a flight line of nadir views, then obliques
        x = -half + (k + 0.5) * 2 * half / 12
        out.append(Pose.from_dji(0, -90, 0, [x, 0.3 * x, 70.0]))
    for _ in range(6):
        C = [rng.uniform(-half * 0.8, half * 0.8), rng.uniform(-half * 0.8, half * 0.8), 60.0]
        out.append(Pose.from_dji(rng.uniform(-180, 180), -50.0, 0, C))
    return out


def measure(model_dir: str, mode: str, n_side: int, tile_m: float, budget: float) -> dict:
    from gtkit.camera import Camera
    from gtkit.geo import GeoFrame
    from gtkit.io.tiled import read_tiled
    from gtkit.render.renderer import Renderer
    from gtkit.render.tiles import TileStreamer, near_far

    import cv2  # noqa: F401 - every library a tile load touches, imported before the baseline
    import PIL.Image  # noqa: F401
    import trimesh  # noqa: F401

    from gtkit.render.renderer import gl_context

    gl_context()
    frame = GeoFrame(CRS, ORIGIN)
    model = read_tiled(model_dir, frame)
    cam = Camera.from_hfov(800, 600, 70.0)
    Renderer(model.load_tile(model.names[0])).render(cam, views(n_side, tile_m)[0])  # warm up (shaders, FBO)
    base = vm("VmRSS")
    per_view, drawn, loaded = [], [], []
    t0 = time.perf_counter()
    if mode.startswith("dsm"):  # a top-down raster of the whole site, 0.25 m, in 512 px windows
        lo, hi = model.bounds()
        t = time.perf_counter()
        if mode == "dsm-stream":
            s = TileStreamer(model, budget_mb=budget)
            s.render_ortho(lo[0], lo[1], hi[0], hi[1], 0.25, tile=512)
            drawn, loaded, resident = [s.stats.tiles_drawn], [s.stats.tiles_loaded], len(s.resident)
        else:
            r = Renderer()
            r.add_mesh(model.load_all(), origin=model.bounds().mean(0))
            r.render_ortho(lo[0], lo[1], hi[0], hi[1], 0.25, tile=512)
            drawn = loaded = [len(model)]
            resident = len(model)
        setup, per_view = 0.0, [time.perf_counter() - t]
    elif mode == "stream":
        s = TileStreamer(model, budget_mb=budget)
        setup = time.perf_counter() - t0
        for pose in views(n_side, tile_m):
            t = time.perf_counter()
            s.render(cam, pose)
            per_view.append(time.perf_counter() - t)
            drawn.append(s.stats.tiles_drawn)
            loaded.append(s.stats.tiles_loaded)
        resident = len(s.resident)
    else:
        r = Renderer()
        mesh = model.load_all()
        origin = model.bounds().mean(0)
        r.add_mesh(mesh, origin=origin)
        del mesh
        setup = time.perf_counter() - t0
        for pose in views(n_side, tile_m):
            t = time.perf_counter()
            n, f = near_far(model.bounds(), pose)
            r.render(cam, pose, near=n, far=f)
            per_view.append(time.perf_counter() - t)
        drawn = loaded = [len(model)]
        resident = len(model)
    return {"mode": mode, "tiles": len(model), "setup_s": setup, "drawn_mean": float(np.mean(drawn)),
            "drawn_max": int(np.max(drawn)), "loaded_per_view": float(np.mean(loaded)), "resident": resident,
            "rss_mb": vm("VmRSS") - base, "peak_mb": vm("VmHWM"), "base_mb": base,
            "view_ms_median": 1000 * float(np.median(per_view)), "view_ms_max": 1000 * float(np.max(per_view))}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--tiles-side", type=int, default=10)
    ap.add_argument("--tile-m", type=float, default=50.0)
    ap.add_argument("--cells", type=int, default=40)
    ap.add_argument("--tex", type=int, default=512)
    ap.add_argument("--budget", type=float, default=32.0)
    ap.add_argument("--measure", nargs=2, metavar=("DIR", "MODE"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.measure:
        print(json.dumps(measure(a.measure[0], a.measure[1], a.tiles_side, a.tile_m, a.budget)))
        return
    from test_import_support import grid_site

    from gtkit.io.tiled import write_tiled

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        mesh = grid_site(a.tiles_side, a.tile_m, a.cells, a.tex)
        out = write_tiled(mesh, Path(tmp) / "model", CRS, ORIGIN, tile_size=a.tile_m)
        n_tri = mesh.n_triangles
        del mesh
        size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
        print(f"model: {a.tiles_side ** 2} tiles, {n_tri} triangles, {a.tiles_side ** 2} textures "
              f"{a.tex}x{a.tex}, {size:.0f} MiB on disk, written in {time.perf_counter() - t:.1f} s")
        print(f"{'mode':10s} {'drawn/view':>10s} {'loaded/view':>11s} {'resident':>8s} {'RSS+ MiB':>9s} "
              f"{'peak MiB':>9s} {'setup s':>8s} {'view ms (median/max)':>21s}")
        for mode in ("stream", "all", "dsm-stream", "dsm-all"):
            res = subprocess.run([sys.executable, __file__, "--measure", str(out), mode,
                                  "--tiles-side", str(a.tiles_side), "--tile-m", str(a.tile_m),
                                  "--budget", str(a.budget)], capture_output=True, text=True, check=True)
            r = json.loads(res.stdout.strip().splitlines()[-1])
            print(f"{r['mode']:10s} {r['drawn_mean']:6.1f}/{r['drawn_max']:<3d} {r['loaded_per_view']:11.1f} "
                  f"{r['resident']:8d} {r['rss_mb']:9.0f} {r['peak_mb']:9.0f} {r['setup_s']:8.2f} "
                  f"{r['view_ms_median']:10.0f}/{r['view_ms_max']:<10.0f}")
        print(f"(budget {a.budget:.0f} MiB; RSS+ = resident memory after the views minus after imports, GL "
              "context and one warm-up render; peak = the process's VmHWM)")


if __name__ == "__main__":
    main()
