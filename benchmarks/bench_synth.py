"""Sizes and generation times of the sample presets (run by hand).

    .venv/bin/python benchmarks/bench_synth.py [small medium ...] [--keep DIR]

Prints, per preset: photos, tie points, GCP clicks, folder size, wall time per part, and the
process CPU time (wall time on a shared machine can be much longer than CPU time).
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path


def folder_size(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def main():
    from gtkit.synth.generate import create_sample
    from gtkit.synth.settings import load_preset

    ap = argparse.ArgumentParser()
    ap.add_argument("presets", nargs="*", default=["small"])
    ap.add_argument("--keep", help="write the projects under this folder and keep them")
    args = ap.parse_args()
    rows = []
    for name in args.presets:
        base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_synth_"))
        root = base / name
        cpu0, wall0 = time.process_time(), time.perf_counter()
        summ = create_sample(root, load_preset(name), quiet=True)
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
        size = folder_size(root)
        img = sum(p.stat().st_size for p in (root / "images").rglob("*.jpg"))
        mdl = folder_size(root / "model")
        rows.append((name, summ, cpu, wall, size, img, mdl))
        if not args.keep:
            shutil.rmtree(base)
    print(f"{'preset':8} {'ref':>4} {'query':>5} {'tiepts':>6} {'gcp':>4} {'size MB':>8} {'images':>7} {'model':>6}"
          f" {'cpu s':>7} {'wall s':>7}  wall per part (s)")
    for name, summ, cpu, wall, size, img, mdl in rows:
        parts = " ".join(f"{k}={v:.1f}" for k, v in summ["timings_s"].items() if k != "total")
        print(f"{name:8} {summ['n_reference']:4d} {summ['n_query']:5d} {summ['n_tiepoints']:6d} "
              f"{summ['n_gcp_clicks']:4d} {size / 1e6:8.1f} {img / 1e6:7.1f} {mdl / 1e6:6.1f} {cpu:7.1f} {wall:7.1f}  {parts}")


if __name__ == "__main__":
    main()
