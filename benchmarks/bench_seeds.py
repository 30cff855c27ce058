"""The main job's figures over several seeds of a preset: one row a seed, then the median and the worst.

For each seed a sample site is generated (or reused from --work) and the README's main job
(``python -m pipelines.full``) run on it; the table gives the pseudo-GT median position / rotation
error vs truth and registered photos, localization recall at (1 m,1°)/(3 m,3°)/(5 m,5°) and R@1,
tracking median 3D error and targets lost, and wall seconds. Recall is also pooled over all queries of
all seeds (the figure the targets are stated on). No figure of gtkit's should be a one-seed figure.

    python benchmarks/bench_seeds.py --preset small --seeds 1 2 3 4 5 --work /tmp/seeds
    python benchmarks/bench_seeds.py ... --code /path/to/other/checkout    # before / after
    python benchmarks/bench_seeds.py ... --rerun localize                    # redo that stage only

``--rerun`` deletes the named stages' outputs in existing projects first (localize: the rendered
database, its features and the localization runs; pseudo_gt: SfM of both blocks and the registration;
track),
so a code change is measured on the same sites. Wall seconds include the machine's other load:
quote them as idle only when nothing else ran.
"""
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

RERUN = {  # stage -> work folders (and reports) removed so the stage runs again
    "localize": ["work/render_db", "work/localize_db", "work/localize", "work/track", "reports/localization.json"],
    "pseudo_gt": ["work/sfm_reference", "work/sfm_queries", "work/register", "work/rig", "work/export_dsm",
                  "work/export_ortho", "work/export_mesh_obj", "work/export_coordinates", "work/track"],
    "track": ["work/track"],
}
THRESHOLDS = ((1.0, 1.0), (3.0, 3.0), (5.0, 5.0))


def run_seed(preset: str, seed: int, code: Path, work: Path, rerun: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(code), GTKIT_PROGRESS="0")
    proj = work / f"{preset}_{seed}"
    if not (proj / "project.toml").is_file():
        shutil.rmtree(proj, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "gtkit.cli", "sample", "create", str(proj), "--preset", preset,
                        "--seed", str(seed), "-q"], env=env, cwd=code, check=True, capture_output=True)
    for stage in rerun:
        for rel in RERUN[stage]:
            p = proj / rel
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
    t = time.time()
    r = subprocess.run([sys.executable, "-m", "pipelines.full", str(proj)], env=env, cwd=code,
                       capture_output=True, text=True)
    wall = time.time() - t
    (proj / "bench_seeds.log").write_text(r.stdout + r.stderr)
    summary = proj / "reports/summary.json"
    if r.returncode or not summary.is_file():
        return {"seed": seed, "error": (r.stderr.strip().splitlines() or ["?"])[-1][:200], "wall_s": wall}
    return {"seed": seed, "wall_s": wall, **figures(json.loads(summary.read_text()))}


def figures(s: dict) -> dict:
    pg, loc = s.get("pseudo_gt") or {}, s.get("localization") or {}
    tr = (s.get("tracking") or {}).get("evaluation") or {}
    queries = [(q.get("pos_err_m"), q.get("rot_err_deg")) if q.get("ok") else (None, None)
               for q in loc.get("queries", [])]
    return {
        "pgt_registered": f"{pg.get('n_registered')}/{pg.get('n_images')}",
        "pgt_pos_m": pg.get("median_pos_err_m"), "pgt_rot_deg": pg.get("median_rot_err_deg"),
        "loc_recall": [recall(queries, m, d) for m, d in THRESHOLDS],
        "loc_r1": loc.get("retrieval_R1"), "loc_median_m": loc.get("median_pos_err_m"),
        "loc_queries": queries,
        "track_3d_m": tr.get("median_err_3d_m"), "track_failed": tr.get("n_failed"),
        "track_targets": tr.get("n_targets"),
        "stage_s": sum((s.get("seconds") or {}).values()),
    }


def recall(queries: list, max_m: float, max_deg: float) -> float | None:
    if not queries:
        return None
    return float(np.mean([p is not None and p <= max_m and r <= max_deg for p, r in queries]))


def fmt(v, nd=3, pct=False):
    if v is None:
        return "-"
    return f"{100 * v:.1f}" if pct else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def table(rows: list[dict]) -> str:
    head = ("| seed | pseudo-GT registered | pseudo-GT m | pseudo-GT ° | loc (1m,1°) | (3m,3°) | (5m,5°) | R@1 "
            "| loc median m | tracking 3D m | targets lost | stage s | wall s |")
    out = [head, "|" + "---|" * 13]
    ok = [r for r in rows if "error" not in r]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['seed']} | error: {r['error']} |" + " |" * 11)
            continue
        rec = r["loc_recall"]
        out.append(f"| {r['seed']} | {r['pgt_registered']} | {fmt(r['pgt_pos_m'])} | {fmt(r['pgt_rot_deg'])} | "
                   + " | ".join(fmt(x, pct=True) for x in rec)
                   + f" | {fmt(r['loc_r1'], pct=True)} | {fmt(r['loc_median_m'])} | {fmt(r['track_3d_m'], 2)} | "
                     f"{r['track_failed']}/{r['track_targets']} | {r['stage_s']:.0f} | {r['wall_s']:.0f} |")
    if ok:
        def col(key, i=None):
            vals = [(r[key][i] if i is not None else r[key]) for r in ok]
            return [v for v in vals if v is not None]

        med = lambda v: float(np.median(v)) if v else None  # noqa: E731
        out.append(f"| **median** | | {fmt(med(col('pgt_pos_m')))} | {fmt(med(col('pgt_rot_deg')))} | "
                   + " | ".join(fmt(med(col('loc_recall', i)), pct=True) for i in range(3))
                   + f" | {fmt(med(col('loc_r1')), pct=True)} | {fmt(med(col('loc_median_m')))} | "
                     f"{fmt(med(col('track_3d_m')), 2)} | | | |")
        worst = lambda v, f: f(v) if v else None  # noqa: E731
        out.append(f"| **worst** | | {fmt(worst(col('pgt_pos_m'), max))} | {fmt(worst(col('pgt_rot_deg'), max))} | "
                   + " | ".join(fmt(worst(col('loc_recall', i), min), pct=True) for i in range(3))
                   + f" | {fmt(worst(col('loc_r1'), min), pct=True)} | {fmt(worst(col('loc_median_m'), max))} | "
                     f"{fmt(worst(col('track_3d_m'), max), 2)} | {sum(r['track_failed'] or 0 for r in ok)} lost | | |")
        pooled = [q for r in ok for q in r["loc_queries"]]
        out.append(f"| **pooled** ({len(pooled)} queries) | | | | "
                   + " | ".join(fmt(recall(pooled, m, d), pct=True) for m, d in THRESHOLDS) + " |" + " |" * 6)
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--work", type=Path, required=True, help="folder of the sample projects (kept, reused)")
    ap.add_argument("--code", type=Path, default=ROOT, help="checkout whose gtkit runs (default: this one)")
    ap.add_argument("--rerun", nargs="*", default=[], choices=sorted(RERUN))
    ap.add_argument("--json", type=Path, help="write the rows here too")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in a.seeds:
        rows.append(run_seed(a.preset, seed, a.code.resolve(), a.work.resolve(), a.rerun))
        print(f"seed {seed}: " + json.dumps({k: v for k, v in rows[-1].items() if k != "loc_queries"}), flush=True)
        if a.json:
            a.json.write_text(json.dumps(rows, indent=1))
    print(f"\n{a.preset}, seeds {' '.join(map(str, a.seeds))}, code {a.code.resolve()}\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
