"""Consumer sites end to end (issue 33): a sample made into a consumer photo set, then ``gtkit run``
as a user would (no hand-written file), measured against the sample's truth.

For each seed: ``gtkit sample create`` (the delivered model removed, so ``gtkit run`` builds one from
the photos), the variants applied (default ``consumer-gps`` + ``no-gcps``: ~10 m wandering GPS,
altitude drifting 60 m, no XMP attitude, no GCPs), optionally the tie-point clicks removed, then
``gtkit run SITE``. Printed per seed:
- the reference block against the true world: tilt, heading, horizontal / vertical offset (what a
  consumer GPS allows) and its shape (camera centres after the best similarity);
- pseudo-GT (``work/register/poses.txt``) and localization (``work/localize/poses.txt``) against
  the truth **in the block's frame** (truth carried through the similarity fitted between the
  reference cameras' estimated and true centres, as ``shared/tools/heldout_eval.py`` does with real
  photos: a GPS-placed site is only as absolute as its GPS), and also absolute.

    python benchmarks/bench_consumer.py --preset tiny --seeds 0 1 2 [--no-clicks] [--variants consumer-gps no-gcps]
    python benchmarks/bench_consumer.py --preset small --seeds 13 --no-clicks --work W --resume   # go on
    python benchmarks/bench_consumer.py --preset small --seeds 13 --variants consumer-gps no-gcps nadir-heldout
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
sys.path.insert(0, str(ROOT))


def _aligned(est: dict, truth: dict, sim) -> dict:
    """Truth poses carried into the estimate's frame by ``sim`` (est ~ sim(truth))."""
    from gtkit.pose import Pose

    R = sim.R
    return {n: Pose.from_center(p.R @ R.T, sim.apply(p.center[None])[0]) for n, p in truth.items()}


def evaluate(proj: Path) -> dict:
    from gtkit.evaluate.poses import block_frame_errors, medians, pose_errors, recall
    from gtkit.io.poses import read_poses
    from gtkit.project import Project
    from gtkit.queries import query_photos
    from gtkit.sfm.similarity import umeyama

    truth = read_poses(proj / "truth/poses.txt")
    out = {}
    ref_f = proj / "work/sfm_reference/poses.txt"
    if not ref_f.is_file():
        return out
    ref = read_poses(ref_f)
    out["reference"] = block_frame_errors(ref, truth)
    common = [n for n in ref if n in truth]
    sim = umeyama(np.array([truth[n].center for n in common]), np.array([ref[n].center for n in common]))
    truth_in_block = _aligned(ref, truth, sim)
    for stage, f in (("pseudo_gt", "work/register/poses.txt"), ("localize", "work/localize/poses.txt")):
        if not (proj / f).is_file():
            continue
        est = read_poses(proj / f)
        queries = [n for n in query_photos(Project.load(proj)) if n in truth]   # the project's own query setting
        for frame, t in (("block", truth_in_block), ("absolute", truth)):
            e = pose_errors(est, t, [n for n in queries if n in est])
            m = medians(e)
            rec = recall({n: e.get(n, {"missing": True}) for n in queries})
            out[f"{stage}_{frame}"] = {"n": len(e), "of": len(queries), **m, **rec}
    return out


def run_one(preset: str, seed: int, variants: list[str], no_clicks: bool, work: Path, resume: bool = False) -> dict:
    from gtkit.synth.variants import apply_variant

    env = dict(os.environ, GTKIT_PROGRESS="0")
    proj = work / f"{preset}_{seed}_{'+'.join(variants)}{'_noclicks' if no_clicks else ''}"
    py = [sys.executable, "-m", "gtkit.cli"]
    if not (resume and (proj / "project.toml").is_file()):
        shutil.rmtree(proj, ignore_errors=True)
        subprocess.run(py + ["sample", "create", str(proj), "--preset", preset, "--seed", str(seed)], env=env,
                       cwd=ROOT, check=True, capture_output=True)
        shutil.rmtree(proj / "model", ignore_errors=True)   # the user's site has no model: gtkit run builds one
        for v in variants:
            apply_variant(proj, v, seed=seed)
        if no_clicks:
            (proj / "tiepoints.json").unlink(missing_ok=True)
    t = time.time()
    r = subprocess.run(py + ["run", str(proj)], env=env, capture_output=True, text=True, cwd=ROOT)
    out = {"seconds": time.time() - t, "exit": r.returncode, "project": str(proj)}
    if r.returncode not in (0, 1):
        out["error"] = (r.stderr.strip().splitlines() or ["?"])[-1][:200]
    out.update(evaluate(proj))
    return out


def _f(v, nd=3):
    return "-" if v is None else (f"{v:.{nd}f}" if isinstance(v, (float, np.floating)) else str(v))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--variants", nargs="+", default=["consumer-gps", "no-gcps"])
    ap.add_argument("--no-clicks", action="store_true", help="remove tiepoints.json (click-free pseudo-GT)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--resume", action="store_true",
                    help="a project already in --work is run on (gtkit run resumes its finished stages)")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_consumer_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    print(f"variants {'+'.join(a.variants)}{', no clicks' if a.no_clicks else ''}; preset {a.preset}")
    print("| seed | ref tilt / heading (deg) | ref horiz / vert (m) | ref shape (m) | pseudo-GT in block frame: n, median m / deg "
          "| localization in block frame: n, median m, recall 1/3/5 | absolute loc. recall 3m3° | s | exit |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s in a.seeds:
        r = run_one(a.preset, s, a.variants, a.no_clicks, work, a.resume)
        rows.append({"seed": s, **r})
        ref = r.get("reference") or {}
        pg = r.get("pseudo_gt_block") or {}
        lo = r.get("localize_block") or {}
        la = r.get("localize_absolute") or {}
        rk = sorted(k for k in lo if k.startswith("recall"))
        print(f"| {s} | {_f(ref.get('tilt_deg'))} / {_f(ref.get('heading_deg'), 2)} | {_f(ref.get('horizontal_m'), 2)} / "
              f"{_f(ref.get('vertical_m'), 2)} | {_f(ref.get('shape_m'))} | {pg.get('n', 0)}/{pg.get('of', '-')}, "
              f"{_f(pg.get('median_pos_err_m'))} / {_f(pg.get('median_rot_err_deg'))} | {lo.get('n', 0)}/{lo.get('of', '-')}, "
              f"{_f(lo.get('median_pos_err_m'))}, {' / '.join(_f(100 * lo[k], 1) for k in rk)} | "
              f"{' / '.join(_f(100 * la[k], 1) for k in sorted(k for k in la if k.startswith('recall')))} | "
              f"{r['seconds']:.0f} | {r['exit']} {r.get('error', '')} |", flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
