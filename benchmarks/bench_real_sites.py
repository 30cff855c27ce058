"""The reference block on sample-site variants that reproduce real photo sets' failures, against truth.

For each seed and variant (see gtkit.synth.variants: no-gps, no-focal, flat-gcps, checkpoints,
no-gcps, no-attitude, consumer-gps, ... and combinations joined by '+'), a fresh sample is generated,
the variant applied (its GPS errors drawn from the seed), and ``gtkit sfm --block reference`` run;
the table gives registered photos, models, median camera position / rotation error vs truth, the
block frame's tilt and heading against the true world, GCP and check-point residual medians, how
the block was fitted (free Sim(3) or gravity-held) and seconds. A refused block shows its one line.

Consumer sites (issue 33):
    python benchmarks/bench_real_sites.py --preset tiny --seeds 0 1 2 \
        --variants no-gcps consumer-gps+no-gcps consumer-gps+no-gcps+no-focal no-attitude+no-gcps

    python benchmarks/bench_real_sites.py --preset tiny --seeds 0 1 2 \
        --variants base no-gps flat-gcps no-gps+flat-gcps no-focal no-gps+no-focal+flat-gcps
Add ``--code DIR`` to run another checkout's gtkit (before/after comparisons).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def evaluate(project: Path) -> dict:
    sys.path.insert(0, str(ROOT))
    from gtkit.evaluate.poses import medians, pose_errors
    from gtkit.io.poses import read_poses

    b = json.loads((project / "work/sfm_reference/block.json").read_text())
    out = {"registered": f"{b.get('n_registered', 0)}/{b['n_images']}", "models": b.get("n_models", "-")}
    pf = project / "work/sfm_reference/poses.txt"
    geo = b.get("georegistration", {})
    if pf.is_file() and "error" not in geo:
        from gtkit.evaluate.poses import block_frame_errors

        est, truth = read_poses(pf), read_poses(project / "truth/poses.txt")
        m = medians(pose_errors(est, truth, [n for n in est if n in truth]))
        out.update(pos_m=m["median_pos_err_m"], rot_deg=m["median_rot_err_deg"], **block_frame_errors(est, truth))
    fit = geo.get("fit") or {}
    out.update(gcp_m=geo.get("gcp_median_err_m"), check_m=geo.get("checkpoint_median_err_m"),
               fit=fit.get("mode"), share=(geo.get("gps_quality") or {}).get("share_kept"),
               claim_h=(geo.get("gps_quality") or {}).get("absolute_accuracy_h_m"),
               claim_v=(geo.get("gps_quality") or {}).get("absolute_accuracy_v_m"),
               error=geo.get("error") or b.get("error"))
    return out


def run_one(preset: str, seed: int, variant: str, code: Path, work: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(code), GTKIT_PROGRESS="0")
    proj = work / f"{preset}_{seed}_{variant}"
    shutil.rmtree(proj, ignore_errors=True)
    py = [sys.executable, "-m", "gtkit.cli"]
    subprocess.run(py + ["sample", "create", str(proj), "--preset", preset, "--seed", str(seed)], env=env, cwd=code,
                   check=True, capture_output=True)
    if variant != "base":
        sys.path.insert(0, str(ROOT))
        from gtkit.synth.variants import apply_variant

        for v in variant.split("+"):
            apply_variant(proj, v, seed=seed)
    t = time.time()
    r = subprocess.run(py + ["sfm", str(proj), "--block", "reference"], env=env, capture_output=True, text=True,
                       cwd=code)  # python -m puts the working folder first on sys.path
    sec = time.time() - t
    out = evaluate(proj) if (proj / "work/sfm_reference/block.json").is_file() else {"error": r.stderr.strip()[-200:]}
    if r.returncode and not out.get("error"):
        out["error"] = r.stderr.strip().splitlines()[-1][:200]
    out["seconds"] = sec
    return out


def fmt(v, nd=3):
    return "-" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--variants", nargs="+", default=["base", "no-gps", "flat-gcps", "no-gps+flat-gcps",
                                                       "no-focal", "no-gps+no-focal+flat-gcps", "no-gps+checkpoints"])
    ap.add_argument("--code", type=Path, default=ROOT, help="checkout whose gtkit runs (default: this one)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_real_sites_"))
    rows = []
    print("| variant | seed | registered | position err (m) | rotation err (deg) | tilt (deg) | heading (deg) | "
          "horizontal / vertical err (m) | claimed (m) | shape (m) | GCP median (m) | check points (m) | fit | GPS kept | s | error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for v in a.variants:
        for s in a.seeds:
            r = run_one(a.preset, s, v, a.code.resolve(), work)
            rows.append({"variant": v, "seed": s, **r})
            print(f"| {v} | {s} | {r.get('registered', '-')} | {fmt(r.get('pos_m'))} | "
                  f"{fmt(r.get('rot_deg'))} | {fmt(r.get('tilt_deg'))} | {fmt(r.get('heading_deg'), 2)} | "
                  f"{fmt(r.get('horizontal_m'), 2)} / {fmt(r.get('vertical_m'), 2)} | "
                  f"{fmt(r.get('claim_h'), 1)} / {fmt(r.get('claim_v'), 1)} | {fmt(r.get('shape_m'))} | {fmt(r.get('gcp_m'))} | {fmt(r.get('check_m'))} | {r.get('fit') or '-'} | {fmt(r.get('share'), 2)} | "
                  f"{r['seconds']:.0f} | {(r.get('error') or '')[:120]} |", flush=True)
    print("\nmedian and worst over seeds:")
    print("| variant | position median / worst (m) | rotation median / worst (deg) | tilt median / worst (deg) | "
          "GCP median / worst (m) |")
    print("|---|---|---|---|---|")
    for v in a.variants:
        rs = [r for r in rows if r["variant"] == v]

        def mw(key):
            x = [r.get(key) for r in rs]
            if any(val is None for val in x):
                return f"failed in {sum(val is None for val in x)} of {len(x)}"
            return f"{np.median(x):.3f} / {max(x):.3f}"
        print(f"| {v} | {mw('pos_m')} | {mw('rot_deg')} | {mw('tilt_deg')} | {mw('gcp_m')} |")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
