"""The depth step on a GPU (COLMAP's PatchMatch, ``pycolmap-cuda12``) against the CPU path (SGBM) on the
same project: per-photo depth maps against the true depth, then each path's whole model (fusion,
surface, texture on this machine) as a DSM against the true world.

For a machine whose GPU is elsewhere (a GPU box, a lent cloud machine): the depth maps are made there
from a COLMAP workspace written here, and the rest of the build runs here on the maps brought back.

    gtkit sample create S && mv S/model S_delivered && gtkit sfm S --block reference
    python benchmarks/bench_model.py S                                  # the CPU path (SGBM) and its DSM
    python benchmarks/bench_patchmatch.py prepare S W                   # W/ws: the workspace; W/carry
    # on the GPU machine (needs only pycolmap-cuda12, numpy, OpenCV): depth maps, packed into OUT
    python benchmarks/bench_patchmatch.py gpu W/carry OUT
    python benchmarks/bench_patchmatch.py finish S S_pm OUT             # S_pm: a copy of S built from them

``prepare`` writes the workspace exactly as ``gtkit model build`` does on a GPU machine
(:func:`gtkit.model.patchmatch.write_workspace`, the same views and neighbours as the SGBM maps) and
what travels to the GPU machine (``W/carry``: its images as lossless WebP, checked to decode to the
same pixels, the sparse model and stereo config as .tar.xz). ``gpu`` runs
``pycolmap.patch_match_stereo`` with :func:`gtkit.model.patchmatch.patchmatch_options` (read from
options.json) and packs each depth map COLMAP wrote (photometric and geometric) as a 16-bit PNG of
depth / step (step = the map's largest depth / 65,000: under 7 mm at 430 m, so quantisation adds at
most 3.5 mm) in tar files of at most 15 MiB. ``finish`` prints each kind of map against the true
depth (truth/world.ply drawn at each view's estimated pose: valid share, median and p95 relative
error) beside SGBM's on the same photos; then turns the maps of ``--kind`` (geometric: what the build
uses) into gtkit's depth maps (:func:`gtkit.model.patchmatch.collect`) in a copy of the project, builds
the model there with ``depth_method = "patchmatch"`` (every map is there, so PatchMatch itself is not
called; this machine's pycolmap needs no CUDA) and prints both models' DSMs against the true world
(gtkit.evaluate.model; completeness over the delivered model's area with ``--delivered``).
Reads truth/ (evaluation only).
"""
from __future__ import annotations

import argparse
import io
import json
import os
import sys
import tarfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

STEPS = 65000                 # the largest depth of a map is stored as this many steps (uint16)
PART_BYTES = 15 * 2 ** 20     # each tar of packed maps stays under this (the GPU machine returns 16 MiB files)


def _option_values(o) -> dict:
    """The plain settings of a pycolmap options object (numbers, strings, booleans)."""
    out = {}
    for k in dir(o):
        if k.startswith("_"):
            continue
        v = getattr(o, k)
        if isinstance(v, (bool, int, float, str)):
            out[k] = v
    return out


def prepare(project: Path, work: Path) -> None:
    import cv2

    from gtkit.model.patchmatch import patchmatch_options, workspace_name, write_workspace
    from gtkit.model.settings import ModelSettings
    from gtkit.model.views import block_dir, choose_neighbours, load_views
    from gtkit.project import Project

    proj = Project.load(project)
    settings = ModelSettings(depth_method="patchmatch")
    views, _ = load_views(proj, settings)
    nb, skipped = choose_neighbours(views, settings)
    ws = work / "ws"
    t0 = time.time()
    write_workspace(proj, views, nb, block_dir(proj), ws)
    carry = work / "carry"                       # what travels: lossless WebP images, the rest compressed
    for n in views:
        png = ws / "images" / workspace_name(n)
        img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        ok, buf = cv2.imencode(".webp", img, [cv2.IMWRITE_WEBP_QUALITY, 101])
        if not ok or not np.array_equal(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), img):
            raise SystemExit(f"{png}: lossless WebP did not give the same pixels back")
        dest = carry / "images" / (workspace_name(n) + ".webp")
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(buf.tobytes())
    with tarfile.open(carry / "rest.tar.xz", "w:xz") as tar:
        tar.add(ws / "sparse", "sparse")
        tar.add(ws / "stereo" / "patch-match.cfg", "stereo/patch-match.cfg")
    (carry / "options.json").write_text(json.dumps(_option_values(patchmatch_options(settings)), indent=1))
    size = sum(f.stat().st_size for f in carry.rglob("*") if f.is_file())
    print(f"workspace {ws}: {len(views)} views, {len(nb)} with neighbours ({len(skipped)} skipped); "
          f"{carry} to carry: {size / 2 ** 20:.1f} MiB; written in {time.time() - t0:.0f} s")


def gpu(work: Path, out: Path) -> None:
    """On the GPU machine: PatchMatch over the workspace, its photometric and geometric maps packed into ``out``."""
    import cv2
    import pycolmap

    from gtkit.io.colmap_dense import read_colmap_array   # numpy only: no other gtkit dependency there

    ws = work.parent / (work.name + "_ws")      # the workspace made again from what was carried
    print(f"pycolmap {pycolmap.__version__}, has_cuda {pycolmap.has_cuda}", flush=True)
    if not pycolmap.has_cuda:
        raise SystemExit("this pycolmap has no CUDA")
    with tarfile.open(work / "rest.tar.xz") as tar:
        tar.extractall(ws)
    for f in sorted((work / "images").rglob("*.webp")):
        img = cv2.imdecode(np.fromfile(str(f), np.uint8), cv2.IMREAD_GRAYSCALE)
        dest = ws / "images" / f.relative_to(work / "images").with_suffix("")
        for sub in ("images", "stereo/depth_maps", "stereo/normal_maps", "stereo/consistency_graphs"):
            (ws / sub / dest.relative_to(ws / "images")).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dest), img)
    opts = pycolmap.PatchMatchOptions()
    for k, v in json.loads((work / "options.json").read_text()).items():
        try:
            setattr(opts, k, v)
        except (AttributeError, TypeError):
            pass                                 # read-only or derived fields
    t0 = time.time()
    pycolmap.patch_match_stereo(str(ws), options=opts)
    wall = time.time() - t0
    dm = ws / "stereo" / "depth_maps"
    maps = sorted(dm.rglob("*.bin"))              # photometric and geometric
    print(f"patch_match_stereo: {len(maps)} depth maps (photometric and geometric) in {wall:.1f} s", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    steps, part, tar, size = {}, 0, None, 0
    for f in maps:
        d = read_colmap_array(f)
        step = max(float(np.nanmax(np.where(d > 0, d, 0))), 1e-3) / STEPS
        q = np.where(d > 0, np.clip(np.rint(d / step), 1, 65535), 0).astype(np.uint16)
        ok, buf = cv2.imencode(".png", q, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        data = buf.tobytes()
        if tar is None or size + len(data) > PART_BYTES:
            if tar is not None:
                tar.close()
            part += 1
            tar, size = tarfile.open(out / f"depth_{part:02d}.tar", "w"), 0
        ti = tarfile.TarInfo(str(f.relative_to(dm)) + ".png")
        ti.size = len(data)
        tar.addfile(ti, io.BytesIO(data))
        size += len(data) + 1024
        steps[str(f.relative_to(dm))] = step
    if tar is not None:
        tar.close()
    (out / "gpu.json").write_text(json.dumps({"wall_s": wall, "maps": len(maps), "steps": steps,
                                              "pycolmap": pycolmap.__version__}, indent=1))
    print(f"packed into {part} file(s), {sum(p.stat().st_size for p in out.glob('depth_*.tar')) / 2 ** 20:.1f} MiB")


def _unpack(results: list[Path], ws: Path) -> dict:
    """The packed maps back as COLMAP files in ``ws/stereo/depth_maps`` (depth = step x stored value)."""
    import cv2

    from gtkit.io.colmap_dense import write_colmap_array

    runs = []
    for r in results:
        run = json.loads((r / "gpu.json").read_text())
        steps = run.pop("steps")
        runs.append(run)
        for tf in sorted(r.glob("depth_*.tar")):
            with tarfile.open(tf) as tar:
                for m in tar.getmembers():
                    q = cv2.imdecode(np.frombuffer(tar.extractfile(m).read(), np.uint8), cv2.IMREAD_UNCHANGED)
                    name = m.name[:-len(".png")]
                    d = q.astype(np.float32) * np.float32(steps[name])
                    dest = ws / "stereo" / "depth_maps" / name
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    write_colmap_array(dest, d)
    return {"runs": runs}


def _depth_stats(est: np.ndarray, ref: np.ndarray) -> tuple[float, np.ndarray]:
    ok = np.isfinite(est) & np.isfinite(ref) & (ref > 0)
    return float(np.isfinite(est).mean()), np.abs(est[ok] - ref[ok]) / ref[ok]


def finish(project: Path, results: list[Path], copy: Path, resolution: float, kind: str,
           delivered: Path | None = None) -> None:
    import shutil

    from gtkit.evaluate.model import dsm_vs_truth
    from gtkit.export import dsm
    from gtkit.model import build as B
    from gtkit.model import depth as D
    from gtkit.model import patchmatch
    from gtkit.io.colmap_dense import read_colmap_array
    from gtkit.model.patchmatch import workspace_name
    from gtkit.model.settings import ModelSettings
    from gtkit.model.texture import _gtkit_camera
    from gtkit.model.views import choose_neighbours, load_views
    from gtkit.project import Project
    from gtkit.render.renderer import Renderer
    from gtkit.synth.truth import read_world_ply

    if not copy.exists():
        top = {"model", "exports"}                # the project's own model and exports (not work/*/model)
        shutil.copytree(project, copy, symlinks=True,
                        ignore=lambda d, names: [n for n in names if Path(d) == project and n in top])
        shutil.rmtree(copy / "work" / "model", ignore_errors=True)
        (copy / "model").mkdir()
    proj = Project.load(copy)
    proj.config.pop("model", None)               # the copy has no model until this build makes one
    proj.save()
    settings = ModelSettings(depth_method="patchmatch")
    views, _ = load_views(proj, settings)
    nb, _ = choose_neighbours(views, settings)
    ws = copy / "work" / "model" / "from_gpu"
    info = _unpack(results, ws)
    dm = ws / "stereo" / "depth_maps"

    def colmap_map(n, k):
        f = dm / (workspace_name(n) + f".{k}.bin")
        if not f.is_file():
            return None
        d = read_colmap_array(f)
        return np.where(d > 0, d, np.nan).astype(np.float32)

    # the depth maps: each path against the true depth (the true world drawn at the view's estimated pose)
    sgbm = B.depth_folder(Project.load(project), ModelSettings(depth_method="sgbm"), "sgbm")
    world = Renderer(read_world_ply(copy / "truth" / "world.ply"))   # evaluation only: the true surface
    rows = {}
    for n in nb:
        t = world.render(_gtkit_camera(views[n]), views[n].pose, with_rgb=False).depth
        maps = {"sgbm": D.read_depth(D.depth_file(sgbm, n)) if D.depth_file(sgbm, n).is_file() else None,
                "photometric": colmap_map(n, "photometric"), "geometric": colmap_map(n, "geometric")}
        for k, est in maps.items():
            if est is not None:
                share, rel = _depth_stats(est, t)
                rows.setdefault(k, {})[n] = (share, float(np.median(rel)), float(np.percentile(rel, 95)))
    print("\ndepth maps against the true depth (median over photos of each photo's valid share, median and "
          "p95 relative error):")
    print("| depth maps | photos | valid share | median rel. error | p95 rel. error | SGBM on the same photos |")
    print("|---|---|---|---|---|---|")
    for k in ("sgbm", "photometric", "geometric"):
        if k not in rows:
            continue
        names = list(rows[k])
        r = np.array([rows[k][n] for n in names])
        g = np.array([rows["sgbm"][n] for n in names if n in rows["sgbm"]])
        print(f"| {k} | {len(names)} | {100 * np.median(r[:, 0]):.1f} % | {np.median(r[:, 1]):.5f} | "
              f"{np.median(r[:, 2]):.4f} | {100 * np.median(g[:, 0]):.1f} % / {np.median(g[:, 1]):.5f} / "
              f"{np.median(g[:, 2]):.4f} |")

    # the whole model from the GPU maps of ``kind`` (each photo needs one), built here
    folder = B.depth_folder(proj, settings, "patchmatch")
    folder.mkdir(parents=True, exist_ok=True)
    if kind != "geometric":                      # collect() reads COLMAP's geometric files: the other kind stands in
        for f in dm.rglob(f"*.{kind}.bin"):
            shutil.copy(f, str(f).replace(f".{kind}.bin", ".geometric.bin"))
    failed = patchmatch.collect(ws, views, nb, folder)
    print(f"\nthe model from the GPU's {kind} maps: {len(nb) - len(failed)} of {len(nb)} photos have one")
    if failed:
        print("not built: every photo needs a map")
        return
    patchmatch.cuda_available = lambda: True     # every map is there: PatchMatch is not called here

    def no_gpu(*a, **k):
        raise RuntimeError("PatchMatch asked for on a machine without CUDA: a depth map is missing")
    import pycolmap
    pycolmap.patch_match_stereo = no_gpu
    t0 = time.time()
    summary = B.run(proj, settings, show=False)
    print(f"built here from them: {time.time() - t0:.0f} s, steps {json.dumps(summary['seconds'])}, "
          f"{summary['points']} points, {summary['triangles']} triangles")
    s = dsm.DsmSettings(resolution=resolution)
    d_del = dsm.run(proj, s, input=delivered, out=copy / "exports" / "dsm_delivered.tif") if delivered else None
    out = {}
    for name, root in (("sgbm", project), (f"patchmatch ({kind})", copy)):
        d = dsm.run(Project.load(root), s, input=root / "model" / "reference.obj", out=copy / "exports" / f"dsm_{name.split()[0]}.tif")
        out[name] = dsm_vs_truth(root, d, **({"area_of": d_del} if d_del else {}))
    print("\n| depth path | completeness (of the delivered area) | median off edges | p95 off edges | median all | p95 all | bias |")
    print("|---|---|---|---|---|---|---|")
    for name, m in out.items():
        o, a = m["off_edges"], m["all"]
        c = m.get("completeness_of_other_area", m["completeness"])
        print(f"| {name} | {100 * c:.2f} % | {o['median']:.3f} | {o['p95']:.3f} | {a['median']:.3f} | "
              f"{a['p95']:.3f} | {m['bias']:+.3f} |")
    (copy / "reports").mkdir(exist_ok=True)
    (copy / "reports" / "bench_patchmatch.json").write_text(json.dumps(
        {"gpu": info["runs"], "build": summary, "dsm": out,
         "depth": rows}, indent=1, default=float))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare", help="the COLMAP workspace of a project's reference views")
    p.add_argument("project", type=Path)
    p.add_argument("work", type=Path)
    p = sub.add_parser("gpu", help="on the GPU machine: PatchMatch, the maps packed")
    p.add_argument("work", type=Path)
    p.add_argument("out", type=Path)
    p = sub.add_parser("finish", help="the model built from the GPU maps in a copy, both paths measured")
    p.add_argument("project", type=Path)
    p.add_argument("copy", type=Path)
    p.add_argument("results", type=Path, nargs="+", help="folders of the GPU machine's packed maps (gpu.json + depth_*.tar)")
    p.add_argument("--kind", choices=("geometric", "photometric"), default="geometric",
                   help="which of COLMAP's maps the model is built from (geometric: what `gtkit model build` uses)")
    p.add_argument("--delivered", type=Path, help="the delivered model (OBJ): completeness over its area, as bench_model.py")
    p.add_argument("--resolution", type=float, default=0.5)
    a = ap.parse_args(argv)
    if a.cmd == "prepare":
        prepare(a.project, a.work)
    elif a.cmd == "gpu":
        gpu(a.work, a.out)
    else:
        finish(a.project, a.results, a.copy, a.resolution, a.kind, a.delivered)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
