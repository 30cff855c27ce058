"""A GCP click or a geo.txt edit re-runs only the georegistration (issue 57): how long
``gtkit sfm SITE --block reference`` takes after each, and how far the block's poses are from a full
re-run's (``--force``: features, matches and mapping again).

On a copy of SITE (photos linked, not copied):
1. before the first run the last click of ``gcp_list.txt`` is held back (the click not yet made) and,
   with ``--geo``, a ``geo.txt`` is written from the photos' own positions (as gtkit reads them);
2. ``gtkit sfm COPY --block reference`` (the full SfM, timed);
3. the held-back click added to ``gcp_list.txt``; ``gtkit sfm`` again, timed as a user runs it (a new
   process: Python start-up and imports included); then the same on a second copy with ``--force``,
   and the two blocks' camera centres and rotations compared;
4. with ``--geo``: one photo's position in ``geo.txt`` moved by ``--move`` metres east; the same.

    python benchmarks/bench_georeg_step.py SITE --work /tmp/w [--geo] [--move 0.5]
    python benchmarks/bench_georeg_step.py --brighton --work /tmp/w --geo    # the shared Brighton photos
    python benchmarks/bench_georeg_step.py BUILT_SITE --work /tmp/w --repeat 3 [--no-force]

A SITE whose reference block is already built (its ``work/`` is copied too) skips the full first SfM:
its first run is then the georegistration alone (the click held back).

Timings on a shared, loaded machine are upper bounds (the load average is printed)."""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
BRIGHTON = ROOT.parent / "shared" / "data" / "brighton_beach"


def gtkit(*args) -> float:
    """Wall seconds of one gtkit command in a new process (its CPU seconds in ``LAST_CPU``)."""
    import resource

    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.time()
    r = subprocess.run([sys.executable, "-m", "gtkit.cli", *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    if r.returncode:
        raise SystemExit(f"gtkit {' '.join(map(str, args))} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    LAST_CPU[0] = ru.ru_utime + ru.ru_stime - ru0.ru_utime - ru0.ru_stime
    return time.time() - t


LAST_CPU = [0.0]


def copy_site(src: Path, dst: Path) -> Path:
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, symlinks=True, ignore=shutil.ignore_patterns("reports", "exports"))
    return dst


def brighton_site(dst: Path) -> Path:
    """The 18 shared Brighton photos as a project's reference block (linked), its CRS UTM 15N."""
    from gtkit.cli import main

    (dst.parent / "brighton_photos").mkdir(parents=True, exist_ok=True)
    src = dst.parent / "brighton_photos" / "reference"
    if not src.exists():
        src.symlink_to(BRIGHTON / "images")
    if not (dst / "project.toml").is_file():
        assert main(["init", str(dst), "--reference", str(src)]) == 0
    return dst


def write_geo_txt(root: Path) -> Path:
    """geo.txt from the photos' positions as gtkit reads them (EXIF GPS + altitude), in the project CRS."""
    from gtkit.photo_positions import positions_and_accuracy
    from gtkit.project import Project
    from gtkit.sfm.blocks import list_images

    p = Project.load(root)
    names = list_images(p.paths.reference_images, p.paths.images)
    pos, _ = positions_and_accuracy(p, names)
    lines = [p.frame.crs_spec] + [f"{Path(n).name} " + " ".join(f"{v:.4f}" for v in p.frame.local_to_crs(pos[n]))
                                  for n in names if n in pos]
    (root / "geo.txt").write_text("\n".join(lines) + "\n")
    return root / "geo.txt"


def move_one_position(root: Path, metres: float) -> str:
    lines = (root / "geo.txt").read_text().splitlines()
    k = len(lines) // 2
    f = lines[k].split()
    f[1] = f"{float(f[1]) + metres:.4f}"
    lines[k] = " ".join(f)
    (root / "geo.txt").write_text("\n".join(lines) + "\n")
    return f[0]


def compare(a: Path, b: Path) -> dict:
    from gtkit.io.poses import read_poses

    pa, pb = (read_poses(r / "work" / "sfm_reference" / "poses.txt") for r in (a, b))
    common = sorted(set(pa) & set(pb))
    dc = np.array([np.linalg.norm(pa[n].center - pb[n].center) for n in common])
    dr = np.array([np.degrees(np.arccos(np.clip((np.trace(pa[n].R @ pb[n].R.T) - 1) / 2, -1, 1))) for n in common])
    return {"n": len(common), "n_only_one": len(set(pa) ^ set(pb)), "centre_max_mm": round(1000 * float(dc.max()), 4),
            "centre_median_mm": round(1000 * float(np.median(dc)), 4), "rotation_max_deg": round(float(dr.max()), 6)}


def step_case(site: Path, work: Path, label: str, undo=None, redo=None, repeat: int = 1, force: bool = True) -> dict:
    """The step after the edit, timed; with ``repeat`` > 1 the edit undone and redone (``undo`` / ``redo``)
    and the step timed again each time (2 runs a repeat; min and median reported: a loaded machine's
    noise is one-sided). Then, with ``force``, a full re-run on a copy and the two blocks compared."""
    mapped = site / "work" / "sfm_reference" / "mapped" / "mapped.json"
    before = mapped.stat().st_mtime_ns
    load0 = os.getloadavg()[0]
    t = gtkit("sfm", site, "--block", "reference")
    runs = [(t, LAST_CPU[0], load0)]
    block = json.loads((site / "work" / "sfm_reference" / "block.json").read_text())
    for _ in range(repeat - 1):
        for edit in (undo, redo):
            edit()
            load = os.getloadavg()[0]
            runs.append((gtkit("sfm", site, "--block", "reference"), LAST_CPU[0], load))
    wall, cpu = np.array([r[0] for r in runs]), np.array([r[1] for r in runs])
    print(f"{label}: gtkit sfm {t:.1f} s wall, {runs[0][1]:.1f} s CPU (load {load0:.1f})"
          + (f"; {len(runs)} runs: wall min {wall.min():.1f} / median {np.median(wall):.1f} s, CPU min "
             f"{cpu.min():.1f} / median {np.median(cpu):.1f} s" if len(runs) > 1 else ""), flush=True)
    out = {"case": label, "seconds": round(t, 2), "cpu_seconds": round(runs[0][1], 2), "load_avg_1m": round(load0, 2),
           "georegistration_step_cpu_s": (block.get("cpu_seconds") or {}).get("georegistration"),
           "mapping_reused": bool((block.get("mapping") or {}).get("reused")),
           "mapped_models_untouched": mapped.stat().st_mtime_ns == before,
           "held_by_positions": {k: (block.get("held_by_positions") or {}).get(k)
                                 for k in ("points_dropped", "iterations", "converged", "seconds")}}
    if len(runs) > 1:
        out["runs"] = [{"wall_s": round(w, 2), "cpu_s": round(c, 2), "load_avg_1m": round(lo, 2)} for w, c, lo in runs]
        out.update(wall_min_s=round(float(wall.min()), 2), wall_median_s=round(float(np.median(wall)), 2),
                   cpu_min_s=round(float(cpu.min()), 2), cpu_median_s=round(float(np.median(cpu)), 2))
    if force:
        print(f"{label}: now the --force run", flush=True)
        full = copy_site(site, work / f"force_{label}")
        out["force_seconds"] = round(gtkit("sfm", full, "--block", "reference", "--force"), 1)
        out["vs_force"] = compare(site, full)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("site", nargs="?")
    ap.add_argument("--brighton", action="store_true", help="the shared Brighton photos as the site")
    ap.add_argument("--work", required=True)
    ap.add_argument("--geo", action="store_true", help="write geo.txt from the photos' positions; also move one")
    ap.add_argument("--move", type=float, default=0.5, help="metres one geo.txt position moves east")
    ap.add_argument("--repeat", type=int, default=1, help="time the step 2 x REPEAT - 1 times (the edit undone and "
                    "redone): min and median")
    ap.add_argument("--no-force", action="store_true", help="time the step only (no full re-run to compare with)")
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    site = copy_site(Path(a.site), work / "site") if a.site else brighton_site(work / "site")
    held = None
    gl = site / "gcp_list.txt"
    if gl.is_file():
        lines = gl.read_text().splitlines()
        held = lines[-1]
        gl.write_text("\n".join(lines[:-1]) + "\n")
    if a.geo:
        write_geo_txt(site)
    t0 = gtkit("sfm", site, "--block", "reference")
    print(f"first run: {t0:.1f} s wall, {LAST_CPU[0]:.1f} s CPU", flush=True)
    out = {"site": str(a.site or BRIGHTON), "first_run_seconds": round(t0, 1), "cases": []}
    if held is not None:
        without = gl.read_text()

        def add_click():
            gl.write_text(without + held + "\n")

        add_click()
        out["cases"].append(step_case(site, work, "gcp_click", lambda: gl.write_text(without), add_click,
                                      a.repeat, not a.no_force))
    if a.geo:
        before = (site / "geo.txt").read_text()
        out["moved_photo"] = move_one_position(site, a.move)
        after = (site / "geo.txt").read_text()
        out["cases"].append(step_case(site, work, "geo_txt_move", lambda: (site / "geo.txt").write_text(before),
                                      lambda: (site / "geo.txt").write_text(after), a.repeat, not a.no_force))
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
