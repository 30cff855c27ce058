"""Time per stage of the pseudo-GT pipeline and its figures against truth (run by hand).

    .venv/bin/python benchmarks/bench_pseudo_gt.py DIR [DIR ...] [--create small|medium] [--force]
    .venv/bin/python benchmarks/bench_pseudo_gt.py /tmp/bb --point-cloud .../model.laz --gps-inlier-m 5
    .venv/bin/python benchmarks/bench_pseudo_gt.py W/s13_gps5 --create small --seed 13 --from W/s13 \
        --variant query-gps-5 --no-clicks

With --create PRESET a missing DIR is first generated with `gtkit sample create` (--seed N), or,
with --from BASE, copied from the sample project BASE with its work/ (its SfM then resumes where the
inputs are unchanged: a query-only variant reuses BASE's reference block). --variant NAME applies a
sample variant (gtkit.synth.variants) to a DIR it creates. --no-clicks moves the project's
tiepoints.json aside (to tiepoints.json.off), so `gtkit register` places every sequence by its
automatic matches. Prints one table per project: the seconds of each stage and sub-step, the
report's figures, how each sequence was registered, and one summary line ``ROW dir variant clicks
registered median_m worst_m median_deg worst_deg`` (errors of the query photos against truth/).
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtkit.evaluate import gt_report as report  # noqa: E402
from gtkit.project import Project  # noqa: E402
from gtkit.stages import settings_for  # noqa: E402
from gtkit.settings import resolve  # noqa: E402
from gtkit.sfm import blocks, register  # noqa: E402
from pipelines.pseudo_gt import main as pseudo_gt  # noqa: E402


def bench(root: Path, args) -> None:
    if not (root / "project.toml").is_file():
        if args.base:
            shutil.copytree(args.base, root, ignore=shutil.ignore_patterns("register", "reports", "exports"))
            print(f"copied {args.base} (with its SfM) to {root}")
        elif args.create:
            from gtkit.cli import main as cli

            t = time.time()
            cli(["sample", "create", str(root), "--preset", args.create, "-q"]
                + (["--seed", str(args.seed)] if args.seed is not None else []))
            print(f"sample create {args.create}: {time.time() - t:.1f} s")
        else:
            raise SystemExit(f"{root}: not a project (use --create small)")
        if args.variant:
            from gtkit.synth.variants import apply_variant

            apply_variant(root, args.variant)
            (root / "bench_variant.txt").write_text(args.variant + "\n")
    elif args.variant and not (root / "bench_variant.txt").is_file():
        raise SystemExit(f"{root}: exists without the variant {args.variant} (--variant applies to a DIR it creates)")
    variant = (root / "bench_variant.txt").read_text().strip() if (root / "bench_variant.txt").is_file() else "-"
    tp = root / "tiepoints.json"
    if args.no_clicks and tp.is_file():
        tp.replace(root / "tiepoints.json.off")
    s = resolve(blocks.SfmSettings(), "sfm", Project.load(root), {"georegister.gps_inlier_m": args.gps_inlier_m})
    t = time.time()
    out = pseudo_gt(str(root), s, rep=report.ReportSettings(args.point_cloud), force=args.force)
    if not tp.is_file():   # the pipeline registers only where tie points were clicked
        t1 = time.time()
        out["sequences"] = register.run(root, settings_for("register", Project.load(root)), force=args.force)["sequences"]
        t2 = time.time()
        summary = report.run(root, report.ReportSettings(args.point_cloud))
        out["seconds"].update({"register": round(t2 - t1, 1), "report": round(time.time() - t2, 1)})
        out.update({k: summary.get(k) for k in ("n_registered", "n_images", "median_reproj_px",
                                                "median_tiepoint_reproj_px", "median_pos_err_m", "median_rot_err_deg")})
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
    for q, info in (out.get("sequences") or {}).items():
        print(f"  {q}: " + (f"ERROR {info['error']}" if info["status"] == "error" else
                            f"registered by {info.get('registered_by', 'clicked tie points')}"))
    rep = json.loads((root / "reports" / "gt_report.json").read_text())
    errs = [e for e in rep.get("per_image", {}).values() if e.get("pos_err_m") is not None]
    pos = [e["pos_err_m"] for e in errs]
    rot = [e["rot_err_deg"] for e in errs]
    f = (lambda v, fn: f"{fn(v):.3f}" if v else "-")
    print(f"ROW {root.name} {variant} {'no-clicks' if not tp.is_file() else 'clicks'} "
          f"{out.get('n_registered')}/{out.get('n_images')} {f(pos, np.median)} {f(pos, max)} {f(rot, np.median)} {f(rot, max)}")
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
    ap.add_argument("--seed", type=int, default=None, help="sample seed for --create")
    ap.add_argument("--from", dest="base", type=Path, default=None,
                    help="create a missing DIR as a copy of this sample project with its SfM")
    ap.add_argument("--variant", default=None, help="sample variant applied to a DIR this run creates "
                    "(e.g. query-gps-5, query-gps-15, no-attitude)")
    ap.add_argument("--no-clicks", action="store_true", help="move tiepoints.json aside: register without clicks")
    a = ap.parse_args()
    for p in a.projects:
        bench(Path(p), a)
