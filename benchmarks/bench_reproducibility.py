"""Run-to-run spread of every stage's poses: the same sample, the same settings, run twice (issue 49).

For each seed a sample site is generated once into ``WORK/src/s<seed>``, copied to ``WORK/s<seed>/a``,
``/b`` ... and the README's main job (``python -m pipelines.full``) run on each copy. Then every pair of
runs of a seed is compared stage by stage:

    sfm_reference   work/sfm_reference/poses.txt          (georegistered reference block)
    sfm_queries     work/sfm_queries/<seq>/poses.txt      (each sequence in its own SfM frame)
    register        work/register/poses.txt               (the pseudo-GT)
    render_db       work/render_db/poses.txt              (database views)
    localize        work/localize/poses.txt
    track           exports/tracks.csv                    (x, y, z of each detection)

A row gives the photos in both runs, those only in one, how many differ at all (bit for bit on the
written text), and the median and the worst camera-centre distance (m) and rotation angle (deg).
The accuracy of each run against truth (pseudo-GT and localization median position error) follows,
since determinism must not be bought with accuracy. Truth is read here, never by the estimators.

    python benchmarks/bench_reproducibility.py --seeds 0 1 --runs 2 --work /tmp/rep49/after
    python benchmarks/bench_reproducibility.py --work /tmp/rep49/after --report-only
    python benchmarks/bench_reproducibility.py --compare RUN_A RUN_B      # two project folders
    python benchmarks/bench_reproducibility.py ... --code /path/to/other/checkout   # before / after

Wall seconds include the machine's other load: quote them as idle only when nothing else ran.
"""
from __future__ import annotations

import argparse
import csv
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

from gtkit.conventions import rotation_angle_deg  # noqa: E402
from gtkit.io.poses import read_poses  # noqa: E402

STAGES = ("sfm_reference", "sfm_queries", "register", "render_db", "localize", "track")
RUNS = "abcdefgh"


def _pose_files(project: Path, stage: str) -> list[Path]:
    if stage == "sfm_queries":
        return sorted((project / "work" / "sfm_queries").glob("*/poses.txt"))
    return [project / "work" / stage / "poses.txt"]


def _read_stage(project: Path, stage: str) -> dict[str, tuple[str, np.ndarray, np.ndarray | None]]:
    """name -> (written text, position, world-to-camera R or None) of one stage's output."""
    out: dict = {}
    if stage == "track":
        f = project / "exports" / "tracks.csv"
        if not f.is_file():
            return out
        rows = [r for r in csv.reader(l for l in f.read_text().splitlines() if not l.startswith("#"))]
        head = rows[0]
        for r in rows[1:]:
            d = dict(zip(head, r))
            key = f"{d['label']}@{d['image']}"
            xyz = np.array([float(d[k]) for k in ("x", "y", "z")]) if d.get("x") else None
            out[key] = (",".join(r), xyz, None)
        return out
    for f in _pose_files(project, stage):
        if not f.is_file():
            continue
        prefix = f.parent.name + ":" if stage == "sfm_queries" else ""
        text = {l.split()[0]: l for l in f.read_text().splitlines() if l.strip() and not l.startswith("#")}
        for name, p in read_poses(f).items():
            out[prefix + name] = (text[name], p.center, p.R)
    return out


def compare_stage(a: Path, b: Path, stage: str) -> dict:
    """The spread between two runs' outputs of one stage (see the module doc)."""
    A, B = _read_stage(a, stage), _read_stage(b, stage)
    both = sorted(set(A) & set(B))
    dpos, drot, differ, lost = [], [], 0, 0
    for k in both:
        (ta, ca, ra), (tb, cb, rb) = A[k], B[k]
        differ += ta != tb
        if ca is None or cb is None:
            lost += (ca is None) != (cb is None)
            continue
        dpos.append(float(np.linalg.norm(ca - cb)))
        if ra is not None:
            drot.append(rotation_angle_deg(ra, rb))
    row = {"stage": stage, "n": len(both), "only_one": len(set(A) ^ set(B)) + lost, "differ": differ}
    for key, v in (("pos_m", dpos), ("rot_deg", drot)):
        row[f"median_{key}"] = float(np.median(v)) if v else None
        row[f"max_{key}"] = float(np.max(v)) if v else None
    return row


def accuracy(project: Path) -> dict:
    """Median position error (m) vs truth of the pseudo-GT and the localization, photos posed."""
    truth_file = project / "truth" / "poses.txt"
    if not truth_file.is_file():
        return {}
    truth = read_poses(truth_file)
    out = {}
    for stage in ("register", "localize"):
        f = project / "work" / stage / "poses.txt"
        if f.is_file():
            err = [float(np.linalg.norm(p.center - truth[n].center)) for n, p in read_poses(f).items() if n in truth]
            out[stage] = {"n": len(err), "median_m": float(np.median(err)) if err else None,
                          "max_m": float(np.max(err)) if err else None}
    return out


def run_seed(work: Path, seed: int, runs: int, preset: str, code: Path) -> list[Path]:
    """Generate the seed's sample once, copy it per run and run the main job on each copy."""
    env = {**os.environ, "PYTHONPATH": str(code)}
    src = work / "src" / f"s{seed}"
    if not (src / "project.toml").is_file():
        shutil.rmtree(src, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "gtkit.cli", "sample", "create", str(src), "--preset", preset,
                        "--seed", str(seed), "-q"], cwd=code, env=env, check=True)
    out = []
    for r in RUNS[:runs]:
        dst = work / f"s{seed}" / r
        if not (dst / "reports" / "summary.json").is_file():
            shutil.rmtree(dst, ignore_errors=True)
            shutil.copytree(src, dst, symlinks=True)
            t = time.time()
            with open(dst.parent / f"{r}.log", "w") as log:
                subprocess.run([sys.executable, "-m", "pipelines.full", str(dst)], cwd=code, env=env,
                               stdout=log, stderr=subprocess.STDOUT, check=False)
            (dst.parent / f"{r}.seconds").write_text(f"{time.time() - t:.1f}\n")
        out.append(dst)
    return out


def _f(v, fmt="{:.2e}"):
    return "-" if v is None else (("0" if v == 0 else fmt.format(v)) if isinstance(v, float) else str(v))


def report(pairs: dict[str, list[Path]]) -> dict:
    """Print and return each seed's stage rows (every pair of its runs) and each run's accuracy."""
    result: dict = {}
    print(f"{'seed':>5} {'pair':>4} {'stage':14} {'n':>4} {'only1':>5} {'differ':>6} "
          f"{'med m':>9} {'max m':>9} {'med deg':>9} {'max deg':>9}")
    for seed, runs in pairs.items():
        rows = []
        for i in range(len(runs)):
            for j in range(i + 1, len(runs)):
                for st in STAGES:
                    row = {"pair": runs[i].name + runs[j].name, **compare_stage(runs[i], runs[j], st)}
                    rows.append(row)
                    print(f"{seed:>5} {row['pair']:>4} {st:14} {row['n']:>4} {row['only_one']:>5} {row['differ']:>6} "
                          f"{_f(row['median_pos_m']):>9} {_f(row['max_pos_m']):>9} "
                          f"{_f(row['median_rot_deg']):>9} {_f(row['max_rot_deg']):>9}")
        acc = {r.name: accuracy(r) for r in runs}
        for name, a in acc.items():
            print(f"{seed:>5} run {name}: " + "; ".join(
                f"{st} {v['n']} posed, median {_f(v['median_m'], '{:.4f}')} m, worst {_f(v['max_m'], '{:.4f}')} m"
                for st, v in a.items()))
        result[seed] = {"rows": rows, "accuracy": acc}
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--work", type=Path, default=Path("/tmp/gtkit_reproducibility"))
    ap.add_argument("--code", type=Path, default=ROOT, help="checkout whose gtkit runs (before / after)")
    ap.add_argument("--report-only", action="store_true", help="compare the runs already in --work")
    ap.add_argument("--compare", type=Path, nargs=2, metavar=("RUN_A", "RUN_B"), help="two project folders")
    a = ap.parse_args()
    if a.compare:
        report({"-": list(a.compare)})
        return
    pairs = {}
    for seed in a.seeds:
        if a.report_only:
            pairs[seed] = sorted(p for p in (a.work / f"s{seed}").glob("?") if (p / "work").is_dir())
        else:
            pairs[seed] = run_seed(a.work, seed, a.runs, a.preset, a.code.resolve())
    res = report(pairs)
    (a.work / "reproducibility.json").write_text(json.dumps(res, indent=1, default=str))


if __name__ == "__main__":
    main()
