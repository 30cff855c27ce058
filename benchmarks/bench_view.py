"""The 3D scene view's open time, frame time while orbiting, and memory (``gtkit view`` and the
annotator's 3D tab), on a sample preset.

    python benchmarks/bench_view.py /tmp/view_medium --preset medium     # scene-only project, then measure
    python benchmarks/bench_view.py SITE                                 # an existing project

Without a project at DIR it writes a *scene-only* project of the preset: the sample generator's
world and reference model (the same code and seed as ``gtkit sample create``), ``cameras.txt``, and
the flight plan's camera poses as the reference block's and the pseudo-GT poses (what a finished
project holds there); no photos are rendered, so it takes a few minutes instead of the hour a full
medium sample takes. Each measurement runs in its own process (peak memory per process).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def scene_only_project(root: Path, preset: str, seed: int = 0) -> None:
    import numpy as np

    from gtkit.geo import GeoFrame
    from gtkit.io.mesh import write_obj, write_offset_sidecar
    from gtkit.io.poses import write_intrinsics, write_poses
    from gtkit.project import Paths, Project
    from gtkit.synth import flights
    from gtkit.synth.generate import _rng
    from gtkit.synth.refmodel import reference_model
    from gtkit.synth.settings import load_preset
    from gtkit.synth.shading import world_glsl
    from gtkit.synth.targets import make_tracks
    from gtkit.synth.world import build_world

    s = load_preset(preset)
    frame = GeoFrame.for_lonlat(s.site.lon, s.site.lat, 0.0)
    world = build_world(s, _rng(seed, 1))
    glsl = world_glsl(world)
    Project.create(root, frame, name=f"scene-{preset}")
    P = Paths(root)
    model = reference_model(world, s, glsl, _rng(seed, 6))
    off = np.floor(np.asarray(frame.origin) / s.model.offset_round_m) * s.model.offset_round_m
    off[2] = 0.0
    write_obj(P.model / "reference.obj", model.translated(np.asarray(frame.origin) - off))
    write_offset_sidecar(P.model / "reference.obj", frame.crs_spec, off)
    tracks = make_tracks(world, (s.targets.car_speed, s.targets.person_speed), _rng(seed, 12))
    ref = flights.reference_shots(world, s)
    qs = [q for q in flights.query_shots(world, tracks, s, _rng(seed, 2)) if q.name.endswith("_W.jpg")]
    write_intrinsics(P.cameras, {sh.name: sh.camera for sh in ref + qs})
    write_poses(P.stage("sfm_reference") / "poses.txt", {sh.name: sh.pose for sh in ref})
    write_poses(P.stage("register") / "poses.txt", {sh.name: sh.pose for sh in qs})
    print(f"scene-only {preset} project: {model.n_triangles} triangles, {len(ref)} reference and {len(qs)} query poses")


GUI = r"""
import json, os, sys, time
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
sys.path.insert(0, sys.argv[2])
import numpy as np
from PySide6.QtWidgets import QApplication
from gui.app import make_app
from gui.main_window import MainWindow
from gtkit.view.scene import peak_rss_mb
app = make_app()
from pathlib import Path
Path(sys.argv[1], "work/annotate/session.json").unlink(missing_ok=True)  # open on the tie-point tab
w = MainWindow(sys.argv[1]); w.resize(1500, 900); w.show(); QApplication.processEvents()
t = time.perf_counter(); w.tabs.setCurrentIndex(3); QApplication.processEvents(); tab_s = time.perf_counter() - t
sc = w.scene3d
sc.overview("oblique")
n0 = len(sc.frame_ms)
for _ in range(36):
    sc.drag(10, 0)  # orbit: 4 degrees a step, each drawn into the tab
ms = sc.frame_ms[n0:]
print(json.dumps({"tab_open_s": round(tab_s, 3), "scene_open_s": round(sc.open_s, 3),
                  "view_px": [sc.view.width(), sc.view.height()],
                  "frame_ms_median": round(float(np.median(ms)), 1), "frame_ms_p90": round(float(np.percentile(ms, 90)), 1),
                  "max_rss_mb": peak_rss_mb()}))
w.close()
"""


def _run_view(root: Path, size: str, env: dict) -> dict:
    r = subprocess.run([sys.executable, "-m", "gtkit.cli", "view", str(root), "--size", size, "--out", str(root / "reports")],
                       env=env, capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


def _run_tab(root: Path, env: dict) -> dict:
    r = subprocess.run([sys.executable, "-c", GUI, str(root), str(ROOT)], env=env, capture_output=True, text=True, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _load() -> str:
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--size", default="1280x800")
    ap.add_argument("--repeat", type=int, default=3, help="measure each case this many times (median and worst)")
    ap.add_argument("--json", help="also write every run's figures here")
    a = ap.parse_args()
    root = Path(a.project)
    if not (root / "project.toml").is_file():
        scene_only_project(root, a.preset)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cache = root / "work" / "view"

    def fresh():  # as a project the view never opened: no model cache, no photo priors cache
        for f in [*cache.glob("model_*.npz"), cache / "priors.npz"]:
            f.unlink(missing_ok=True)

    runs: dict[str, list[dict]] = {k: [] for k in ("view_first", "view_cached", "tab_first", "tab_cached")}
    loads = [_load()]
    for _ in range(a.repeat):
        fresh()
        runs["view_first"].append(_run_view(root, a.size, env))
        runs["view_cached"].append(_run_view(root, a.size, env))
        fresh()
        runs["tab_first"].append(_run_tab(root, env))
        runs["tab_cached"].append(_run_tab(root, env))
        loads.append(_load())
    v = runs["view_cached"][0]
    print(f"{root}: model {v['triangles'][0]:,} triangles shown as {v['triangles'][1]:,}; {v['n_reference_cameras']} "
          f"reference cameras; trajectories {v['trajectories']}; {v.get('n_tiepoints', 0)} tie points; "
          f"{v['n_gcps']} GCPs; {v.get('n_targets', 0)} targets")
    print(f"load average (1, 5, 15 min) before and after each round: {' | '.join(loads)}; {os.cpu_count()} cores")
    print(f"median / worst of {a.repeat} runs, each in fresh processes:\n")
    print("| case | open s | frame ms while orbiting | peak memory MB |\n|---|---|---|---|")

    def mw(xs):
        xs = sorted(xs)
        return f"{xs[len(xs) // 2]:.2f} / {xs[-1]:.2f}" if len(xs) % 2 else f"{(xs[len(xs) // 2 - 1] + xs[len(xs) // 2]) / 2:.2f} / {xs[-1]:.2f}"

    for key, label in (("view_first", f"`gtkit view` {a.size}, first open (no cache)"),
                       ("view_cached", f"`gtkit view` {a.size}, cached"),
                       ("tab_first", "annotator 3D tab, first open (no cache)"), ("tab_cached", "annotator 3D tab, cached")):
        rs = runs[key]
        if key.startswith("view"):
            print(f"| {label} | {mw([r['open_s'] for r in rs])} (load {mw([r['load_s'] for r in rs])}; CPU time "
                  f"{mw([r['open_cpu_s'] for r in rs])}) | "
                  f"{mw([r['frame_ms_median'] for r in rs])} render, {mw([r['frame_with_readback_ms_median'] for r in rs])} "
                  f"with read-back | renderer {mw([r['max_rss_mb'] for r in rs])} |")
        else:
            print(f"| {label} | {mw([r['tab_open_s'] for r in rs])} | {mw([r['frame_ms_median'] for r in rs])} "
                  f"(p90 {mw([r['frame_ms_p90'] for r in rs])}) into the tab, {rs[0]['view_px'][0]}x{rs[0]['view_px'][1]} | "
                  f"GUI {mw([r['max_rss_mb'] for r in rs])} + renderer |")
    if a.json:
        Path(a.json).write_text(json.dumps({"loads": loads, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
