"""How many tie-point clicks a query sequence needs: the sample's order vs the guided order (run by hand).

    .venv/bin/python benchmarks/bench_guided_clicks.py --seeds 13 14 15 --work /tmp/h35
    .venv/bin/python benchmarks/bench_guided_clicks.py --seeds 13 --work W --ks 3 6 12 all --auto
    .venv/bin/python benchmarks/bench_guided_clicks.py --seeds 33 34 --work W --ks 4 8 12 18 27 40 60 all --click-scale 0.25

For each seed the small sample ``WORK/s<seed>`` is made once (``benchmarks/bench_pseudo_gt.py``'s
``bench``: sample, both SfM blocks, registration, report) and reused. A click here is one tie point
of the sample's ``tiepoints.json`` (a ground point clicked in one query photo and in 1-3 reference
photos); only the tie points whose query photo is in its sequence's block are available (clicks in
zoom photos place nothing). For each k of ``--ks`` the registration (``gtkit register``, by default
with the automatic ties off, so that the clicks alone hold the sequences) is run on a copy holding
k clicks a sequence:
- sample order: the first k available tie points of the file;
- guided order: the first 3 spread over the sequence (:func:`gtkit.sfm.guided_clicks.spread_start`:
  no covariance exists before a registration), then, from each registration's covariance, the
  clicks the guidance takes next among the sample's unused ones (:func:`...greedy`, the covariance
  updated after each pick) up to the next k.
``--click-scale F`` moves every correct click to F x its offset from the true pixel (gross mistakes
kept): the sample's 1-px clicks in its 1,024-px photos carry too little for 0.05 m by clicks alone in
any order (``benchmarks/click_information.py``); 0.25 is a 1-px click in a 4,096-px photo.
Each sequence's error is the median position error of its photos against ``truth/``. "clicks to
X" is the smallest k from which every larger k of the grid stays within X. Prints one table per
seed and a summary with the medians over sequences; ROW lines are for scripts.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pycolmap  # noqa: E402

from benchmarks.bench_pseudo_gt import bench as make_site  # noqa: E402
from gtkit.evaluate.gt_report import CHI2_3_2SIGMA  # noqa: E402
from gtkit.io.poses import read_covariances, read_poses  # noqa: E402
from gtkit.pose import Pose  # noqa: E402
from gtkit.io.tiepoints import Observation, TiePoint, read_tiepoints, write_tiepoints  # noqa: E402
from gtkit.project import Project  # noqa: E402
from gtkit.settings import resolve  # noqa: E402
from gtkit.sfm import guided_clicks as gc  # noqa: E402
from gtkit.sfm import register  # noqa: E402
from gtkit.sfm.geometry import triangulate_clicks  # noqa: E402

COPY = ("project.toml", "cameras.txt", "gcp_list.txt", "truth", "model")


def site(work: Path, seed: int) -> Path:
    root = work / f"s{seed}"
    for _ in range(240):   # being made by another run of this or bench_pseudo_gt: wait for it
        if not (root / "project.toml").is_file() or (root / "work" / "register" / "registration.json").is_file():
            break
        time.sleep(10)
    if not (root / "work" / "register" / "registration.json").is_file():
        make_site(root, argparse.Namespace(create="small", seed=seed, base=None, variant=None, no_clicks=False,
                                           gps_inlier_m=None, point_cloud=None, force=False))
    return root


def run_copy(root: Path, copy: Path, ties: list, auto: bool) -> dict:
    """``gtkit register`` on ``copy`` (the site's photos and SfM linked, not copied) with ``ties``."""
    if not copy.is_dir():
        (copy / "work").mkdir(parents=True)
        for n in COPY + ("images",):
            if (root / n).exists():
                os.symlink(root / n, copy / n)
        for n in ("sfm_reference", "sfm_queries"):
            os.symlink(root / "work" / n, copy / "work" / n)
    write_tiepoints(copy / "tiepoints.json", ties)
    pr = Project.load(copy)
    s = resolve(register.RegisterSettings(), "register", pr, {"cross.enabled": auto})
    return register.run(pr, s, force=True)


def seq_errors(copy: Path, truth: dict, photos: dict | None = None) -> dict[str, float]:
    """Each sequence's median position error vs truth; ``photos`` (if given) gets each photo's
    (error m, stated sigma m, inside its 2-sigma ellipsoid) for the calibration figures."""
    f = copy / "work" / "register" / "poses.txt"
    est = read_poses(f) if f.is_file() else {}
    covs = read_covariances(f.with_name("covariances.txt")) if f.with_name("covariances.txt").is_file() else {}
    by: dict[str, list[float]] = {}
    for n, p in est.items():
        if n in truth:
            by.setdefault(n.split("/")[1], []).append(float(np.linalg.norm(p.center - truth[n].center)))
            if photos is not None and n in covs:
                C = Pose(p.R, p.t, covs[n]).center_covariance()
                e = p.center - truth[n].center
                photos[n] = (float(np.linalg.norm(e)), float(np.sqrt(np.trace(C))),
                             bool(e @ np.linalg.solve(C, e) <= CHI2_3_2SIGMA))
    return {q: float(np.median(v)) for q, v in by.items()}


def candidates(ties, poses: dict, cams: dict) -> list[gc.Candidate]:
    """Each available tie point as a guidance candidate: its ground point triangulated from all its
    clicks in posed photos (reference photos, and its query photo where registered)."""
    out = []
    for tp in ties:
        q = [o for o in tp.observations if o.image.startswith("queries/")][0]
        obs = [o for o in tp.observations if o.image in poses and (o.image.startswith("reference/") or o is q)]
        if len(obs) < 2:
            continue
        tri = triangulate_clicks([cams[o.image] for o in obs], [poses[o.image] for o in obs],
                                 np.array([[o.x, o.y] for o in obs]), max_px=4.0)
        if tri.xyz is None:
            continue
        out.append(gc.Candidate(q.image, (q.x, q.y), tri.xyz,
                                [(o.image, (o.x, o.y)) for o in tp.observations if o.image.startswith("reference/")], tp.id))
    return out


def rescaled_clicks(root: Path, ties: list, scale: float) -> list:
    """The sample's tie points with every correct click moved to ``scale`` x its offset from the true
    pixel (``truth/tiepoints_truth.json``; the grossly wrong clicks are kept as they are): the clicks a
    person would make in photos of 1/``scale`` the sample's pixel size (same points, same order)."""
    if scale == 1.0:
        return ties
    truth = {t["id"]: t for t in json.loads((root / "truth" / "tiepoints_truth.json").read_text())["tiepoints"]}
    out = []
    for tp in ties:
        t = truth.get(tp.id, {})
        obs = []
        for o in tp.observations:
            xy = t.get("true_pixels", {}).get(o.image)
            wrong = t.get("gross_mistake") and o.image == t.get("wrong_image")
            obs.append(o if xy is None or wrong else
                       Observation(o.image, xy[0] + scale * (o.x - xy[0]), xy[1] + scale * (o.y - xy[1])))
        out.append(TiePoint(tp.id, obs, tp.source, tp.note))
    return out


def tag_of(auto: bool, scale: float) -> str:
    return ("auto" if auto else "clicks") + ("" if scale == 1.0 else f"_x{scale:g}")


def bench_seed(root: Path, ks: list, auto: bool, work: Path, scale: float = 1.0) -> dict:
    truth = read_poses(root / "truth" / "poses.txt")
    ref_rec = pycolmap.Reconstruction(root / "work" / "sfm_reference" / "model")
    refs = gc.reference_views(ref_rec)
    ref_poses = {n: p for n, (p, _) in refs.items()}
    ref_cams = {n: c for n, (_, c) in refs.items()}
    ties = rescaled_clicks(root, read_tiepoints(root / "tiepoints.json"), scale)
    seqs = sorted(p.name for p in (root / "work" / "sfm_queries").iterdir() if (p / "model").is_dir())
    avail: dict[str, list] = {}
    for q in seqs:
        block = {im.name for im in pycolmap.Reconstruction(root / "work" / "sfm_queries" / q / "model").images.values()
                 if im.has_pose}
        avail[q] = [tp for tp in ties if any(o.image in block for o in tp.observations)
                    and sum(o.image.startswith("queries/") for o in tp.observations) == 1]
    n_all = {q: len(v) for q, v in avail.items()}
    grid = sorted({min(k if k != "all" else 10 ** 9, n) for n in n_all.values() for k in ks})
    tag = tag_of(auto, scale)
    res = {"click_scale": scale, "sample": {}, "guided": {}, "photos": {}, "n_available": n_all, "seconds": {}}
    t0 = time.time()
    copy = work / f"g{root.name}_{tag}_sample"
    for k in grid:
        use = [tp for q in seqs for tp in avail[q][:k]]
        run_copy(root, copy, use, auto)
        res["photos"][k] = {}
        res["sample"][k] = seq_errors(copy, truth, res["photos"][k])
        if k == 0:   # no clicks (automatic ties alone): where the guided order starts from
            shutil.rmtree(work / f"g{root.name}_{tag}_k0", ignore_errors=True)
            shutil.copytree(copy / "work" / "register", work / f"g{root.name}_{tag}_k0")
        print(f"  {root.name} sample k={k}: " + ", ".join(f"{q} {e:.3f}" for q, e in res["sample"][k].items()), flush=True)
    res["seconds"]["sample"] = time.time() - t0
    t0 = time.time()
    copy = work / f"g{root.name}_{tag}_guided"
    chosen = {q: [] for q in seqs}
    for k in grid:
        for q in seqs:
            left = [tp for tp in avail[q] if tp not in chosen[q]]
            need = min(k, n_all[q]) - len(chosen[q])
            if need <= 0:
                continue
            reg = copy / "work" / "register" if chosen[q] else work / f"g{root.name}_{tag}_k0"
            state = None
            if (reg / gc.COVARIANCE_FILE).is_file():
                state = gc.load_states(reg / gc.COVARIANCE_FILE, pycolmap.Reconstruction(reg / "model")).get(q)
            if state is None:   # not registered yet: spread over the sequence, then by id
                cands = candidates(left, ref_poses, ref_cams)
                pick = gc.spread_start(cands, min(need, 3))
                ids = {c.id for c in pick}
                picked = [tp for tp in left if tp.id in ids]
                picked += [tp for tp in left if tp.id not in ids][:need - len(picked)]
            else:
                poses = dict(ref_poses, **dict(zip(state.names, state.poses)))
                cams = dict(ref_cams, **dict(zip(state.names, state.cams)))
                order = gc.greedy(state, candidates(left, poses, cams), refs, need)
                ids = [c.id for c, _ in order]
                picked = [next(tp for tp in left if tp.id == i) for i in ids]
                picked += [tp for tp in left if tp.id not in ids][:need - len(picked)]   # none helps: file order
            chosen[q] += picked
        use = [tp for q in seqs for tp in chosen[q]]
        if {tp.id for tp in use} == {tp.id for q in seqs for tp in avail[q][:k]}:   # no clicks or all: the same run
            res["guided"][k] = res["sample"][k]
            continue
        run_copy(root, copy, use, auto)
        res["guided"][k] = seq_errors(copy, truth)
        print(f"  {root.name} guided k={k}: " + ", ".join(f"{q} {e:.3f}" for q, e in res["guided"][k].items()), flush=True)
    res["seconds"]["guided"] = time.time() - t0
    return res


def clicks_to(curve: dict, q: str, limit: float) -> int | None:
    """Smallest k from which the sequence's error stays within ``limit`` at every larger k."""
    ks = sorted(curve)
    ok = [curve[k].get(q, np.inf) <= limit for k in ks]
    for i, k in enumerate(ks):
        if all(ok[i:]):
            return k
    return None


def report(results: dict, targets: list[float], rel: float) -> None:
    rows = []
    for seed, r in results.items():
        seqs = sorted(r["n_available"])
        ks = sorted(set(r["sample"]) | set(r["guided"]))
        print(f"\n== {seed}: median position error (m) of each sequence vs clicks (sample order / guided order)")
        print("k      " + "  ".join(f"{q:>15s}" for q in seqs))
        for k in ks:
            print(f"{k:<6d} " + "  ".join(f"{r['sample'].get(k, {}).get(q, np.nan):7.3f}/{r['guided'].get(k, {}).get(q, np.nan):<7.3f}"
                                          for q in seqs))
        for q in seqs:
            full = r["sample"][max(r["sample"])].get(q)
            lim = {f"{t:.2f} m": t for t in targets}
            if full is not None:
                lim[f"{rel:.2f} x all"] = rel * full
            row = {"seed": seed, "seq": q, "n_available": r["n_available"][q], "all_clicks_m": full}
            for name in [f"{t:.2f} m" for t in targets] + [f"{rel:.2f} x all"]:
                t = lim.get(name)
                row[name] = (None, None) if t is None else (clicks_to(r["sample"], q, t), clicks_to(r["guided"], q, t))
            rows.append(row)
    print("\n== clicks needed (sample order -> guided order; '-': not reached with every available click)")
    names = [k for k in rows[0] if k.endswith(" m") or " x all" in k] if rows else []
    print(f"{'seed':6s} {'seq':5s} {'avail':>5s} {'all clicks m':>12s} " + " ".join(f"{n:>16s}" for n in names))
    for row in rows:
        cells = []
        for n in names:
            a, b = row[n]
            cells.append(f"{'-' if a is None else a:>7} -> {'-' if b is None else b:<5}")
        print(f"{row['seed']:6s} {row['seq']:5s} {row['n_available']:5d} {row['all_clicks_m'] or np.nan:12.3f} " + " ".join(cells))
        print("ROW", json.dumps(row))
    for k in (0, "all"):
        pooled = [v for r in results.values() for kk, ph in r["photos"].items()
                  if (kk == k if k == 0 else kk == max(r["photos"])) for v in ph.values()]
        if pooled:
            print(f"calibration, sample order k={k}, {len(pooled)} photos pooled: within 2 sigma (radius) "
                  f"{100 * np.mean([e <= 2 * s for e, s, _ in pooled]):.1f} %, inside the 2-sigma ellipsoid "
                  f"{100 * np.mean([i for _, _, i in pooled]):.1f} %")
    budgets = sorted({k for r in results.values() for k in r["guided"] if 0 < k < min(r["n_available"].values())})
    for k in budgets:
        pairs = [(r["sample"][k].get(q, np.inf), r["guided"][k].get(q, np.inf)) for r in results.values()
                 if k in r["sample"] and k in r["guided"] for q in r["n_available"]]
        if pairs:
            s_, g_ = np.array(pairs).T
            print(f"k={k:3d} clicks a sequence: median error sample {np.median(s_):.3f} m, guided {np.median(g_):.3f} m; "
                  f"guided better in {np.sum(g_ < s_)} of {len(pairs)} sequences (unregistered counted as infinite)")
    for n in names:
        ratios = [b / a for a, b in (row[n] for row in rows) if a and b is not None]
        if ratios:
            print(f"{n}: guided / sample clicks, median over {len(ratios)} sequences reached in both: "
                  f"{100 * np.median(ratios):.0f} % (worst {100 * max(ratios):.0f} %)")
        else:
            print(f"{n}: reached in no sequence by both orders")


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[13, 14, 15])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--ks", nargs="+", default=["3", "5", "8", "12", "18", "27", "40", "60", "all"],
                    help="clicks a sequence at which the registration is run ('all': every available one)")
    ap.add_argument("--auto", action="store_true", help="keep the automatic tie points on (default: clicks alone)")
    ap.add_argument("--targets", type=float, nargs="+", default=[0.05, 0.10, 0.20])
    ap.add_argument("--rel", type=float, default=1.25, help="also: clicks to within this factor of the all-clicks error")
    ap.add_argument("--click-scale", type=float, default=1.0,
                    help="clicks moved to this x their offset from the truth (e.g. 0.25: as precise as a 1-px "
                         "click in photos of 4x the sample's width; gross mistakes kept)")
    ap.add_argument("--fresh", action="store_true", help="remove this bench's working copies first")
    ap.add_argument("--report-only", action="store_true", help="print the tables from the saved WORK/guided_*.json")
    a = ap.parse_args()
    ks = [k if k == "all" else int(k) for k in a.ks]
    out = {}
    for seed in a.seeds if a.report_only else []:
        f = a.work / f"guided_s{seed}_{tag_of(a.auto, a.click_scale)}.json"
        if f.is_file():
            r = json.loads(f.read_text())
            out[f"s{seed}"] = {**r, **{o: {int(k): v for k, v in r.get(o, {}).items()} for o in ("sample", "guided", "photos")}}
    for seed in [] if a.report_only else a.seeds:
        root = site(a.work, seed)
        if a.fresh:
            for p in a.work.glob(f"g{root.name}_*"):
                shutil.rmtree(p)
        out[root.name] = bench_seed(root, ks, a.auto, a.work, a.click_scale)
        (a.work / f"guided_{root.name}_{tag_of(a.auto, a.click_scale)}.json").write_text(json.dumps(out[root.name], indent=1))
    report(out, a.targets, a.rel)
