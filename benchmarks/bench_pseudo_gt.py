"""Time per stage of the pseudo-GT pipeline and its figures against truth (run by hand).

    .venv/bin/python benchmarks/bench_pseudo_gt.py DIR [DIR ...] [--create small|medium] [--force]
    .venv/bin/python benchmarks/bench_pseudo_gt.py /tmp/bb --point-cloud .../model.laz --gps-inlier-m 5

With --create PRESET a missing DIR is first generated with `gtkit sample create`. Prints one
table per project: the seconds of each stage and sub-step, and the report's figures.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtkit.evaluate import gt_report as report  # noqa: E402
from gtkit.sfm import blocks  # noqa: E402
from pipelines.pseudo_gt import main as pseudo_gt  # noqa: E402


def bench(root: Path, args) -> None:
    if not (root / "project.toml").is_file():
        if not args.create:
            raise SystemExit(f"{root}: not a project (use --create small)")
        from gtkit.cli import main as cli

        t = time.time()
        cli(["sample", "create", str(root), "--preset", args.create, "-q"])
        print(f"sample create {args.create}: {time.time() - t:.1f} s")
    s = blocks.SfmSettings()
    if args.gps_inlier_m:
        s.georegister.gps_inlier_m = args.gps_inlier_m
    t = time.time()
    out = pseudo_gt(str(root), s, rep=report.ReportSettings(args.point_cloud), force=args.force)
    total = time.time() - t
    rows = []
    w = root / "work"
    for f in [w / "sfm_reference" / "block.json", *sorted((w / "sfm_queries").glob("*/block.json"))]:
        if f.is_file():
            b = json.loads(f.read_text())
            for k, v in (b.get("seconds") or {}).items():
                rows.append((f"{f.parent.name}: {k}", v))
    reg = w / "register" / "registration.json"
    if reg.is_file():
        for k, v in (json.loads(reg.read_text()).get("seconds") or {}).items():
            rows.append((f"register: {k}", v))
    print(f"\n== {root} ==")
    print(f"{'stage':40s} {'seconds':>9s}")
    for k, v in out["seconds"].items():
        print(f"{k:40s} {v:9.1f}")
    print("-- sub-steps (from the stage records; 0 when resumed) --")
    for k, v in rows:
        print(f"{k:40s} {v:9.1f}")
    print(f"{'total (this run)':40s} {total:9.1f}")
    for k in ("n_registered", "n_images", "median_reproj_px", "median_tiepoint_reproj_px", "median_pos_err_m",
              "median_rot_err_deg"):
        print(f"{k:40s} {out.get(k)}")
    pc = out.get("point_cloud_comparison")
    if pc:
        print(f"{'vertical offset from cloud (m)':40s} {pc['vertical_offset_m']:+.3f}")
        print(f"{'horizontal offset from cloud (m)':40s} {pc['horizontal_offset_m']:.3f}")


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("projects", nargs="+")
    ap.add_argument("--create", default=None, help="generate a missing project with this sample preset")
    ap.add_argument("--point-cloud", default=None)
    ap.add_argument("--gps-inlier-m", type=float, default=None)
    ap.add_argument("--force", action="store_true", help="recompute every stage")
    a = ap.parse_args()
    for p in a.projects:
        bench(Path(p), a)
