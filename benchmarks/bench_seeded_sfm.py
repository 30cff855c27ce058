"""The reference block mapped incrementally and seeded by its photos' priors (issue 34), on the SAME
feature database, against truth.

For each preset and seed a sample is generated (or an existing sample project reused, ``--samples``),
copied twice, and ``gtkit sfm --block reference`` run with ``mapper = incremental`` on the first copy
(features + matches + mapping); its ``database.db`` is then given to the second copy, which runs with
``mapper = seeded`` (no features or matching: the stage reuses the database). A sample that has a
reference feature database already (``work/sfm_reference/database.db`` + ``database.key``, e.g. one the
main job ran on) gives it to both copies, so that neither extracts nor matches (at large that saves
~13 min a copy). The table gives, per
mapper: the mapping's wall and CPU seconds, those of mapping + georegistration (with the position-held
BA), registered photos, camera centre error vs truth after georegistration (median / worst, m) and
rotation error (median / worst, deg), as ``gtkit.evaluate.poses`` measures them.

    python benchmarks/bench_seeded_sfm.py --preset tiny --seeds 0 1 2
    python benchmarks/bench_seeded_sfm.py --preset small --seeds 13 14
    python benchmarks/bench_seeded_sfm.py --samples /tmp/h34/small13 --work /tmp/h34/bench
    python benchmarks/bench_seeded_sfm.py --samples /tmp/one/large_0 --work /tmp/h34/bench   # its database

Each block runs in its own process (``gtkit sfm``), one after the other; the machine's load shows in
wall seconds (CPU seconds are the process's own).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_real_sites import fmt   # this folder is first on sys.path when run as a script

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
MAPPERS = ("incremental", "seeded")


def evaluate(project: Path) -> dict:
    from gtkit.evaluate.poses import pose_errors
    from gtkit.io.poses import read_poses

    b = json.loads((project / "work/sfm_reference/block.json").read_text())
    sec, cpu = b.get("seconds", {}), b.get("cpu_seconds", {})
    out = {"mapper": b.get("mapper"), "why": b.get("mapper_why"),
           "registered": f"{b.get('n_registered', 0)}/{b['n_images']}",
           "map_s": sec.get("mapping"), "map_cpu": cpu.get("mapping"),
           "map_geo_s": (sec.get("mapping") or 0) + (sec.get("georegistration") or 0),
           "map_geo_cpu": (cpu.get("mapping") or 0) + (cpu.get("georegistration") or 0),
           "reproj_px": b.get("mean_reproj_px"), "error": (b.get("georegistration") or {}).get("error") or b.get("error")}
    pf = project / "work/sfm_reference/poses.txt"
    if pf.is_file() and not out["error"]:
        est, truth = read_poses(pf), read_poses(project / "truth/poses.txt")
        e = pose_errors(est, truth, [n for n in est if n in truth])
        p = np.array([v["pos_err_m"] for v in e.values()])
        r = np.array([v["rot_err_deg"] for v in e.values()])
        out.update(pos_med=float(np.median(p)), pos_max=float(p.max()), rot_med=float(np.median(r)),
                   rot_max=float(r.max()))
    return out


def run_sfm(proj: Path, mapper: str, env: dict) -> dict:
    toml = proj / "project.toml"
    text = toml.read_text()
    if "[sfm]" in text:
        raise SystemExit(f"{toml} has an [sfm] section already: give a sample without one")
    toml.write_text(text + f'\n[sfm]\nmapper = "{mapper}"\n')
    r = subprocess.run([sys.executable, "-m", "gtkit.cli", "sfm", str(proj), "--block", "reference"], env=env,
                       capture_output=True, text=True, cwd=ROOT)
    out = evaluate(proj) if (proj / "work/sfm_reference/block.json").is_file() else {}
    if r.returncode and not out.get("error"):
        out["error"] = (r.stderr.strip().splitlines() or ["failed"])[-1][:200]
    return out


def run_one(sample: Path, label: str, work: Path, env: dict) -> dict[str, dict]:
    res = {}
    own = sample / "work/sfm_reference"
    own = own if (own / "database.db").is_file() and (own / "database.key").is_file() else None
    for mapper in MAPPERS:
        proj = work / f"{label}_{mapper}"
        shutil.rmtree(proj, ignore_errors=True)
        shutil.copytree(sample, proj, ignore=shutil.ignore_patterns("work", "reports", "exports"))
        if own or mapper != MAPPERS[0]:   # the same feature database: features and matches are reused
            src = own or work / f"{label}_{MAPPERS[0]}/work/sfm_reference"
            dst = proj / "work/sfm_reference"
            dst.mkdir(parents=True)
            for f in ("database.db", "database.key", "pairs.json"):
                if (src / f).is_file():
                    shutil.copy2(src / f, dst / f)
        res[mapper] = run_sfm(proj, mapper, env)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    ap.add_argument("--samples", type=Path, nargs="*", default=[], help="existing sample projects (instead of generating)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_seeded_sfm_"))
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT), GTKIT_PROGRESS="0")
    samples = [(p.resolve(), p.name) for p in a.samples]
    if not a.samples:
        for s in a.seeds:
            p = work / f"{a.preset}{s}_sample"
            if not (p / "project.toml").is_file():
                subprocess.run([sys.executable, "-m", "gtkit.cli", "sample", "create", str(p), "--preset", a.preset,
                                "--seed", str(s), "-q"], env=env, cwd=ROOT, check=True, capture_output=True)
            samples.append((p, f"{a.preset}{s}"))
    rows = []
    print("| sample | mapper | map s | map CPU s | map+georeg s | map+georeg CPU s | registered | "
          "centre err median / worst (m) | rotation err median / worst (deg) | reproj px | note |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for path, label in samples:
        res = run_one(path, label, work, env)
        for mapper, r in res.items():
            rows.append({"sample": label, "asked": mapper, **r})
            print(f"| {label} | {r.get('mapper') or mapper} | {fmt(r.get('map_s'), 1)} | {fmt(r.get('map_cpu'), 1)} | "
                  f"{fmt(r.get('map_geo_s'), 1)} | {fmt(r.get('map_geo_cpu'), 1)} | {r.get('registered', '-')} | "
                  f"{fmt(r.get('pos_med'))} / {fmt(r.get('pos_max'))} | {fmt(r.get('rot_med'))} / {fmt(r.get('rot_max'))} | "
                  f"{fmt(r.get('reproj_px'), 2)} | {(r.get('error') or '')[:100]} |", flush=True)
        inc, sd = res["incremental"], res["seeded"]
        if inc.get("map_geo_s") and sd.get("map_geo_s"):
            print(f"|  | seeded / incremental | x{inc['map_s'] / max(sd['map_s'], 1e-6):.1f} faster | "
                  f"x{inc['map_cpu'] / max(sd['map_cpu'], 1e-6):.1f} | x{inc['map_geo_s'] / sd['map_geo_s']:.1f} | "
                  f"x{inc['map_geo_cpu'] / max(sd['map_geo_cpu'], 1e-6):.1f} | | "
                  f"{fmt((sd.get('pos_med') or 0) - (inc.get('pos_med') or 0), 4)} / "
                  f"{fmt((sd.get('pos_max') or 0) - (inc.get('pos_max') or 0), 4)} (seeded - incremental) | | | |",
                  flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
