"""The main job's figures over several seeds of a preset: one row a seed, then the median and the worst.

For each seed a sample site is generated (or reused from --work) and the README's main job
(``python -m pipelines.full``) run on it; the table gives the pseudo-GT median position / rotation
error vs truth and registered photos, localization recall at (1 m,1°)/(3 m,3°)/(5 m,5°) and R@1,
tracking median 3D error and targets lost, and wall seconds. Recall is also pooled over all queries of
all seeds (the figure the targets are stated on). No figure of gtkit's should be a one-seed figure.

After the table, every failure with its cause, and a count of the causes:

- localization: each query not localized, or localized more than 3 m / 3 deg off (a wrong pose
  accepted). The cause is the first top-k round's reason as gtkit.localize words it (features,
  matching: too few matches, gravity check: every hypothesis or the refined pose off the IMU gravity,
  PnP: too few inliers or too uncertain), except that a round whose retrieved views all overlap the
  true view by at most 0.5 (the evaluation's R@k miss; fallback views are not scored) is put down to
  retrieval. Later fallback rounds' causes follow in the evidence.
- pseudo-GT: each sequence not registered, each photo not registered (its SfM's and resection's
  reasons), and each sequence whose median position error exceeds 0.08 m: registration (its photos
  hold fewer than 15 tie points each in the final BA, so it hangs on its Sim(3)), biased automatic (or
  clicked) ties (held by many ties, the sequence is off as a whole: its photos' median error vector
  is at least half their median error; the smooth-surface test's shift and limit follow), else
  scattered photos.

Truth is read here (truth/poses.txt, the evaluation's reports), never by the estimators.

    python benchmarks/bench_seeds.py --preset small --seeds 1 2 3 4 5 --work /tmp/seeds
    python benchmarks/bench_seeds.py ... --code /path/to/other/checkout    # before / after
    python benchmarks/bench_seeds.py ... --rerun localize                    # redo that stage only
    python benchmarks/bench_seeds.py --work /tmp/seeds --report-only           # rows + failures, nothing run

``--rerun`` deletes the named stages' outputs in existing projects first (localize: the rendered
database, its features and the localization runs; pseudo_gt: SfM of both blocks and the registration;
track),
so a code change is measured on the same sites. Wall seconds include the machine's other load:
quote them as idle only when nothing else ran. ``--report-only`` runs nothing: it rebuilds the rows
and the failure listing from the projects in --work that have reports/summary.json (all of the preset's,
or those of --seeds), also for a bench run by an older version of this script (no wall seconds then).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gtkit.io.poses import read_poses  # noqa: E402
from gtkit.sfm.register import tie_test_words  # noqa: E402

RERUN = {  # stage -> work folders (and reports) removed so the stage runs again
    "localize": ["work/render_db", "work/localize_db", "work/localize", "work/track", "reports/localization.json"],
    "pseudo_gt": ["work/sfm_reference", "work/sfm_queries", "work/register", "work/rig", "work/export_dsm",
                  "work/export_ortho", "work/export_mesh_obj", "work/export_coordinates", "work/track"],
    "track": ["work/track"],
}
THRESHOLDS = ((1.0, 1.0), (3.0, 3.0), (5.0, 5.0))
WRONG_M, WRONG_DEG = 3.0, 3.0   # a localized query farther off is a wrong pose accepted
OVERLAP = 0.5                   # a retrieved view is right when it sees more of the query's ground (evaluation)
PGT_MAX_M = 0.08                # a pseudo-GT sequence with a larger median position error is listed
FEW_TIES = 15                   # tie points a photo in the final BA below which a sequence hangs on its Sim(3)
LOC_CAUSES = (  # cause <- words of gtkit.localize's reasons, first match
    ("features", ("too few keypoints",)),
    ("retrieval", ("no database view",)),
    ("matching", ("no 2D-3D correspondences", "too few 2D-3D matches")),
    ("gravity check", ("agrees with the IMU gravity", "disagrees with the IMU gravity")),
    ("PnP", ("too few inliers", "too uncertain", "without a covariance", "no P3P hypothesis", "invalid refined pose")),
)


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
    if r.returncode or not (proj / "reports/summary.json").is_file():
        return {"seed": seed, "error": (r.stderr.strip().splitlines() or ["?"])[-1][:200], "wall_s": wall}
    return project_row(proj, seed, wall)


def project_row(proj: Path, seed: int, wall: float | None) -> dict:
    s = json.loads((proj / "reports/summary.json").read_text())
    gt = load(proj / "reports/gt_report.json")
    n = sum(1 for r in (gt.get("per_image") or {}).values() if r.get("pos_err_m") is not None)
    return {"seed": seed, "wall_s": wall, **figures(s),
            "pgt_2sigma": [gt.get("share_within_2sigma"), gt.get("share_within_2sigma_ellipsoid"), n],
            "failures": loc_failures(proj, s.get("localization") or {}) + pgt_failures(proj)}


def figures(s: dict) -> dict:
    pg, loc = s.get("pseudo_gt") or {}, s.get("localization") or {}
    tr = (s.get("tracking") or {}).get("evaluation") or {}
    queries = [(q.get("pos_err_m"), q.get("rot_err_deg")) if q.get("ok") else (None, None)
               for q in loc.get("queries", [])]
    return {
        "pgt_registered": f"{pg.get('n_registered')}/{pg.get('n_images')}",
        "pgt_pos_m": pg.get("median_pos_err_m"), "pgt_rot_deg": pg.get("median_rot_err_deg"),
        "pgt_sequences": len(pg.get("sequences") or {}),
        "loc_recall": [recall(queries, m, d) for m, d in THRESHOLDS],
        "loc_r1": loc.get("retrieval_R1"), "loc_median_m": loc.get("median_pos_err_m"),
        "loc_queries": queries,
        "track_3d_m": tr.get("median_err_3d_m"), "track_failed": tr.get("n_failed"),
        "track_targets": tr.get("n_targets"),
        "stage_s": sum((s.get("seconds") or {}).values()),
    }


def load(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def loc_cause(reason: str | None) -> str:
    return next((c for c, words in LOC_CAUSES if any(w in (reason or "") for w in words)), "other")


def loc_failures(proj: Path, loc: dict) -> list[dict]:
    runs = {q["name"]: q for q in load(proj / "work/localize/status.json").get("queries", [])}
    out = []
    for q in loc.get("queries", []):
        run = runs.get(q["name"], {})
        ov = q.get("retrieved_overlap") or []
        seen = f"retrieved overlap {'/'.join(f'{v:.2f}' for v in ov)}" if ov else "retrieval not scored"
        if q.get("ok"):
            p, r = q.get("pos_err_m"), q.get("rot_err_deg")
            if p is None or (p <= WRONG_M and r <= WRONG_DEG):
                continue
            cause = "wrong pose accepted"
            before = [loc_cause(x) for x in run.get("failed_rounds", [])]
            why = (f"{p:.2f} m / {r:.2f} deg off, {q.get('n_inliers')} inliers, "
                   f"sigma {fmt(run.get('sigma_pos_m'), 2)} m"
                   + (f", fallback round {len(before)} (before: {', '.join(before)})" if before else ""))
        else:
            rounds = run.get("failed_rounds", []) + [q.get("reason")]
            causes = [loc_cause(x) for x in rounds]
            miss = bool(ov) and max(ov) <= OVERLAP and causes[0] not in ("features", "other")
            cause = "retrieval" if miss else causes[0]
            why = re.sub(r" \(also with \d+ fallback round.*\)$", "", rounds[0] or "?") + (
                f"; {len(rounds) - 1} fallback round(s): {', '.join(causes[1:])}" if len(rounds) > 1 else "")
        out.append({"stage": "localization", "item": q["name"], "cause": cause, "evidence": f"{why}; {seen}"})
    return out


def pgt_failures(proj: Path) -> list[dict]:
    rep = load(proj / "reports/gt_report.json")
    seqs = rep.get("sequences") or {}
    per = rep.get("per_image") or {}
    tests = load(proj / "work/register/registration.json").get("auto_ties_test_by_sequence") or {}
    out = [{"stage": "pseudo-GT", "item": q, "cause": "sequence not registered", "evidence": s.get("error")}
           for q, s in sorted(seqs.items()) if s.get("status") == "error"]
    left = {n: r for s in seqs.values() for n, r in (s.get("left_out_by_sfm") or {}).items()}
    unreg = {n: why for b in (rep.get("query_blocks") or {}).values()
             for n, why in (b.get("unregistered") or {}).items()}
    for n, e in sorted(per.items()):
        if not e.get("registered") and seqs.get(n.split("/")[1], {}).get("status") != "error":
            r = left.get(n, {})
            why = [r.get("sfm_reason") or unreg.get(n), r.get("reason"), r.get("auto_reason")]
            out.append({"stage": "pseudo-GT", "item": n, "cause": "photo not registered",
                        "evidence": "; ".join(w for w in why if w) or "not in the joint BA"})
    est_file, truth_file = proj / "work/register/poses.txt", proj / "truth/poses.txt"
    est = read_poses(est_file) if est_file.is_file() else {}
    truth = read_poses(truth_file) if truth_file.is_file() else {}
    by_seq: dict[str, list[str]] = {}
    for n, e in per.items():
        if e.get("registered") and e.get("pos_err_m") is not None and n in est and n in truth:
            by_seq.setdefault(n.split("/")[1], []).append(n)
    for q, names in sorted(by_seq.items()):
        med = float(np.median([per[n]["pos_err_m"] for n in names]))
        if med <= PGT_MAX_M:
            continue
        off = np.median([est[n].center - truth[n].center for n in names], axis=0)
        clicked = float(np.median([per[n].get("n_tiepoints", 0) for n in names]))
        auto = float(np.median([per[n].get("n_auto_tiepoints", 0) for n in names]))
        sig = [per[n]["sigma_pos_m"] for n in names if per[n].get("sigma_pos_m") is not None]
        s = seqs.get(q, {})
        why = [f"median {med:.3f} m over {len(names)} photos (sigma {np.median(sig) if sig else np.nan:.3f} m), "
               f"offset of the sequence ({', '.join(f'{x:+.3f}' for x in off)}) m, ties a photo in the final BA "
               f"{clicked:.0f} clicked + {auto:.0f} automatic, registered by {s.get('registered_by', '?')}"]
        if clicked + auto < FEW_TIES:
            cause = "registration (few ties)"
            a = s.get("automatic") or {}
            why.append(f"{a.get('n_photos_agreeing')}/{a.get('n_photos')} photos agree, Sim(3) from "
                       f"{a.get('sim3_from')}" if a else
                       f"Sim(3) on {s.get('n_sim3_inliers')}/{s.get('n_tiepoints')} clicked ties")
        elif np.linalg.norm(off) >= 0.5 * med:
            cause = "biased automatic ties" if auto >= clicked else "biased clicked ties"
            t = tests.get(q)
            why.append(f"smooth-surface test: {tie_test_words(t)}, "
                       f"{'smooth-surface ties only' if t['smooth_only'] else 'all ties'}" if t else
                       "no smooth-surface test (no ties off smooth surface)")
        else:
            cause = "scattered photos"
            worst = max(names, key=lambda n: per[n]["pos_err_m"])
            why.append(f"worst {worst} {per[worst]['pos_err_m']:.3f} m")
        out.append({"stage": "pseudo-GT", "item": q, "cause": cause, "evidence": "; ".join(why)})
    return out


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
                     f"{r['track_failed']}/{r['track_targets']} | {fmt(r['stage_s'], 0)} | {fmt(r['wall_s'], 0)} |")
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
        two = [r["pgt_2sigma"] for r in ok if r.get("pgt_2sigma") and r["pgt_2sigma"][0] is not None]
        if two:
            n = sum(t[2] for t in two)
            share = [sum(t[i] * t[2] for t in two if t[i] is not None) / max(n, 1) for i in (0, 1)]
            out += ["", f"pseudo-GT photos within 2 sigma, pooled over {n}: {fmt(share[0], pct=True)} % (radius), "
                        f"{fmt(share[1], pct=True)} % (ellipsoid); per seed {fmt(min(t[0] for t in two), pct=True)}"
                        f"-{fmt(max(t[0] for t in two), pct=True)} %"]
    return "\n".join(out)


def listing(rows: list[dict]) -> str:
    fails = [(r["seed"], f) for r in rows for f in r.get("failures", [])]
    ok = [r for r in rows if "error" not in r]
    n_q = sum(len(r["loc_queries"]) for r in ok)
    n_seq = sum(r.get("pgt_sequences", 0) for r in ok)
    out = [f"Failures: localization queries not localized or more than {WRONG_M:g} m / {WRONG_DEG:g} deg off "
           f"(of {n_q}); pseudo-GT sequences or photos not registered, sequences over {PGT_MAX_M:g} m median "
           f"(of {n_seq} sequences)", ""]
    if not fails:
        return "\n".join(out + ["none"])
    out += ["| seed | stage | item | cause | evidence |", "|---|---|---|---|---|"]
    out += [f"| {seed} | {f['stage']} | {f['item']} | {f['cause']} | {f['evidence']} |" for seed, f in fails]
    seeds: dict[tuple, list] = {}
    for seed, f in fails:
        seeds.setdefault((f["stage"], f["cause"]), []).append(seed)
    out += ["", "| stage | cause | count | seeds |", "|---|---|---|---|"]
    out += [f"| {st} | {c} | {len(v)} | {' '.join(str(x) for x in sorted(set(v)))} |"
            for (st, c), v in sorted(seeds.items(), key=lambda kv: (kv[0][0], -len(kv[1])))]
    return "\n".join(out)


def found_seeds(work: Path, preset: str) -> list[int]:
    return sorted(int(m.group(1)) for p in work.glob(f"{preset}_*/reports/summary.json")
                  if (m := re.fullmatch(rf"{re.escape(preset)}_(\d+)", p.parent.parent.name)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seeds", type=int, nargs="+", help="default 1-5 (--report-only: every finished one)")
    ap.add_argument("--work", type=Path, required=True, help="folder of the sample projects (kept, reused)")
    ap.add_argument("--code", type=Path, default=ROOT, help="checkout whose gtkit runs (default: this one)")
    ap.add_argument("--rerun", nargs="*", default=[], choices=sorted(RERUN))
    ap.add_argument("--json", type=Path, help="write the rows here too")
    ap.add_argument("--report-only", action="store_true",
                    help="run nothing: rows and failures from the projects in --work with reports/summary.json")
    a = ap.parse_args(argv)
    if a.report_only:
        done = found_seeds(a.work, a.preset)
        a.seeds = [s for s in a.seeds if s in done] if a.seeds else done
    else:
        a.seeds = a.seeds or [1, 2, 3, 4, 5]
        a.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in a.seeds:
        if a.report_only:
            rows.append(project_row(a.work / f"{a.preset}_{seed}", seed, None))
        else:
            rows.append(run_seed(a.preset, seed, a.code.resolve(), a.work.resolve(), a.rerun))
            brief = {k: v for k, v in rows[-1].items() if k not in ("loc_queries", "failures")}
            print(f"seed {seed}: " + json.dumps(brief | {"failures": len(rows[-1].get("failures", []))}), flush=True)
        if a.json:
            a.json.write_text(json.dumps(rows, indent=1))
    print(f"\n{a.preset}, seeds {' '.join(map(str, a.seeds))}, "
          + (f"projects in {a.work.resolve()}" if a.report_only else f"code {a.code.resolve()}") + "\n")
    print(table(rows))
    print("\n" + listing(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
