"""Real photos with independent truth (issue 55): gtkit's pseudo-GT of held-out photos against surveyed
poses, beside what one plain COLMAP SfM of all the photos gives the same photos (the anchor).

Sets: ../shared/data/real_truth/ (fountain-P11, entry-P10; see its README.md), or any folder of the same
layout (images/, truth.txt, geo.txt, K.txt). Protocol: ../shared/tools/truth_split.py (its docstring):
photos i % 3 != 1 of the sorted list are the reference block with their surveyed centres, i % 3 == 1 a
held-out query sequence. Four cases per set: {known intrinsics: freeK / knownK} x {query positions:
nopos / rtk (the surveyed centres + 2 cm Gaussian noise, no attitude)}.

gtkit: ``truth_split.py make`` -> the printed ``gtkit init`` -> ``gtkit run PROJECT --until report`` ->
``truth_split.py eval``: query median / worst position error, photos with a sigma, share within 2 sigma,
and the reference block's median (all against truth.txt).

Anchor: ONE pycolmap SfM of ALL the set's photos (SIFT extraction, exhaustive matching, incremental
mapping; one shared camera: self-calibrated SIMPLE_RADIAL as COLMAP does without EXIF (focal and k refined,
principal point held at the image centre: COLMAP's default; and again with the principal point refined,
the stronger anchor on these sets), or, knownK, a PINHOLE from K.txt with cx, cy + 0.5 (COLMAP's pixel
centre convention) held fixed), then a similarity
(Umeyama, least squares, nothing rejected) from the reference photos' SfM centres to their surveyed
centres (geo.txt); the held-out photos' errors against truth.txt. It uses no query position, so it is
the same for nopos and rtk. It runs ``--anchor-runs`` times with seeds 0, 1, ...: the seed goes to the
geometric verification's RANSAC (TwoViewGeometryOptions.ransac.random_seed) and to the mapper
(IncrementalPipelineOptions.random_seed, which COLMAP passes on to the mapper's and triangulator's
RANSACs); the same seed gives the same result to the bit with the default multi-threaded mapping, so
one thread is not needed. Features are extracted once per set (CPU SIFT is deterministic) and shared.
Reported: the median over runs of the held-out median error and its spread (max - min over runs).

The images' limit (per set, ``--no-limit`` skips it): every photo at its surveyed pose with K.txt,
COLMAP's tracks (the anchor's features, exhaustive matching) triangulated there; then each photo in turn
resected against its tracks triangulated again from the OTHER photos only. Its distance to its surveyed
centre is what no estimator can be expected to beat with these features, everything else being perfect
(a measure of the yardstick, not of gtkit). Reported: its median over the held-out photos, and per photo.

Verdict "ok" when: every registered photo has a sigma; >= 90 % of them lie within 2 sigma; query
median <= anchor median + max(anchor spread, 2 mm), against the better anchor (freeK: the principal point
held or refined, whichever gives the smaller median); knownK: query median <= 1.5 x reference median
("so is the images' limit" where the held-out photos' limit is above that line too).

    python benchmarks/bench_real_truth.py --work /tmp/brt_base --json /tmp/brt_base/bench.json
    python benchmarks/bench_real_truth.py --sets fountain-P11 --cases knownK,rtk --anchor-runs 1
    python benchmarks/bench_real_truth.py --sets /data/my_set --set-toml register.smooth_surface.enabled=false

``--cases``: comma-separated words from freeK, knownK, nopos, rtk; an axis without a word keeps both.
Cases run one after the other; the gtkit wall times are as measured on whatever load the machine had.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from gtkit.sfm.similarity import umeyama as similarity_umeyama  # noqa: E402
SHARED = ROOT.parent / "shared"
SPLIT = SHARED / "tools" / "truth_split.py"
CASES = [(k, p) for k in ("freeK", "knownK") for p in ("nopos", "rtk")]
HALF_EDITED = re.compile(r"SyntaxError|IndentationError|ImportError|NameError|circular import")


def set_photos(set_dir: Path) -> list[str]:
    """The set's photo names in truth_split's order."""
    return sorted(p.name for p in (set_dir / "images").iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))


def read_truth(set_dir: Path) -> dict:
    out = {}
    for ln in (set_dir / "truth.txt").read_text().splitlines():
        f = ln.split()
        if len(f) == 13:
            out[f[0]] = (np.array(f[1:10], float).reshape(3, 3), np.array(f[10:13], float))
    return out


def read_geo(set_dir: Path) -> dict:
    return {f[0]: np.array(f[1:4], float) for f in (ln.split() for ln in (set_dir / "geo.txt").read_text().splitlines()[1:])
            if len(f) >= 4}


def umeyama(src: np.ndarray, dst: np.ndarray):
    """Least-squares similarity dst ~ c R src + t (gtkit's Umeyama): (c, R, t)."""
    S = similarity_umeyama(src, dst)
    return S.scale, S.R, S.t


# --------------------------------------------------------------------------------------------- anchor
def anchor_features(set_dir: Path, work: Path) -> Path:
    import pycolmap

    db = work / "features.db"
    if not db.is_file():
        work.mkdir(parents=True, exist_ok=True)
        tmp = work / "features.tmp.db"
        tmp.unlink(missing_ok=True)
        pycolmap.extract_features(tmp, set_dir / "images", image_names=set_photos(set_dir),
                                  camera_mode=pycolmap.CameraMode.SINGLE)
        tmp.rename(db)
    return db


def known_pinhole(set_dir: Path, db: Path) -> None:
    """Every camera of the database ``db`` made K.txt's PINHOLE (a focal prior)."""
    import pycolmap

    fx, fy, cx, cy = map(float, (set_dir / "K.txt").read_text().split())
    d = pycolmap.Database.open(db)
    for cam in d.read_all_cameras():
        cam.model = pycolmap.CameraModelId.PINHOLE
        cam.params = [fx, fy, cx + 0.5, cy + 0.5]   # K.txt: top-left pixel centre (0, 0); COLMAP (0.5, 0.5)
        cam.has_prior_focal_length = True
        d.update_camera(cam)
    d.close()


def match_seeded(db: Path, seed: int) -> None:
    """Exhaustive matching of ``db``, its geometric verification's RANSAC seeded."""
    import pycolmap

    ver = pycolmap.TwoViewGeometryOptions()
    ver.ransac.random_seed = seed
    pycolmap.match_exhaustive(db, verification_options=ver)


def rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle between two rotations (degrees), exact near 0: |Ra^T Rb - I| = 2 sqrt(2) sin(angle / 2)."""
    d = np.linalg.norm(Ra.T @ Rb - np.eye(3))
    return float(np.degrees(2 * np.arcsin(min(1.0, d / (2 * np.sqrt(2))))))


def anchor_run(set_dir: Path, known: bool, seed: int, feat_db: Path, work: Path, refine_pp: bool = False,
               every: int = 3) -> dict:
    """One SfM of all photos; held-out / reference centre errors (m) and held-out rotation errors (deg)."""
    import pycolmap

    out = work / f"{'knownK' if known else 'freeK'}{'_pp' if refine_pp else ''}_seed{seed}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    db = out / "database.db"
    shutil.copy(feat_db, db)
    if known:
        known_pinhole(set_dir, db)
    match_seeded(db, seed)
    opt = pycolmap.IncrementalPipelineOptions()
    opt.random_seed = seed
    if known:
        opt.ba_refine_focal_length = opt.ba_refine_principal_point = opt.ba_refine_extra_params = False
    elif refine_pp:   # the stronger anchor: COLMAP told to refine the principal point too
        opt.ba_refine_principal_point = True
    recs = pycolmap.incremental_mapping(db, set_dir / "images", out, options=opt)
    if not recs:
        return {"seed": seed, "error": "no model", "n_models": 0}
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    est = {im.name: (im.cam_from_world().rotation.matrix(), im.projection_center()) for im in rec.images.values()
           if im.has_pose}
    names, truth, geo = set_photos(set_dir), read_truth(set_dir), read_geo(set_dir)
    ref = [n for i, n in enumerate(names) if i % every != 1 and n in est]
    held = [n for i, n in enumerate(names) if i % every == 1]
    c, R, t = umeyama(np.array([est[n][1] for n in ref]), np.array([geo[n] for n in ref]))

    def err(n):
        Rc, C = est[n]
        Rw = Rc @ R.T                                   # world-to-camera in the set's frame
        return float(np.linalg.norm(c * R @ C + t - truth[n][1])), rotation_deg(truth[n][0], Rw)

    q = {n: err(n) for n in held if n in est}
    return {"seed": seed, "n_models": len(recs), "n_registered": len(est), "n_photos": len(names),
            "missing": sorted(set(names) - set(est)), "reference_pos_m": {n: err(n)[0] for n in ref},
            "query": q, "query_median_m": float(np.median([v[0] for v in q.values()])) if q else None,
            "query_median_rot_deg": float(np.median([v[1] for v in q.values()])) if q else None,
            "reference_median_m": float(np.median([err(n)[0] for n in ref]))}


def anchor(set_dir: Path, known: bool, runs: int, work: Path, refine_pp: bool = False, every: int = 3) -> dict:
    import pycolmap

    pycolmap.logging.minloglevel = 2   # errors only
    t = time.time()
    feat = anchor_features(set_dir, work)
    rs = [anchor_run(set_dir, known, s, feat, work, refine_pp, every) for s in range(runs)]
    meds = [r["query_median_m"] for r in rs if r.get("query_median_m") is not None]
    return {"runs": rs, "median_m": float(np.median(meds)) if meds else None,
            "spread_m": float(max(meds) - min(meds)) if meds else None,
            "reference_median_m": float(np.median([r["reference_median_m"] for r in rs if "reference_median_m" in r]))
            if meds else None, "seconds": time.time() - t}


# ------------------------------------------------------------------------------------ the images' limit
def _pinhole_database(set_dir: Path, feat_db: Path, out: Path) -> Path:
    """A copy of the set's features with K.txt's PINHOLE camera, matched exhaustively (seed 0)."""
    db = out / "database.db"
    if db.is_file():
        return db
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "database.tmp.db"
    shutil.copy(feat_db, tmp)
    known_pinhole(set_dir, tmp)
    match_seeded(tmp, 0)
    tmp.rename(db)
    return db


def images_limit(set_dir: Path, work: Path) -> dict:
    """How close the photos' own evidence can bring each photo to its surveyed pose: every photo at its
    surveyed pose with K.txt, COLMAP's tracks triangulated there; then each photo in turn resected
    (LO-RANSAC PnP + refinement, K held) against its tracks triangulated again from the OTHER photos
    only (linear, tracks with a residual over 1 px in those photos left out). Its distance to its
    surveyed centre is what no estimator can be expected to beat on that photo with these features:
    everything else is perfect. A measure of the yardstick and the features, never of gtkit; truth is
    read here only to judge."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    t = time.time()
    db = _pinhole_database(set_dir, anchor_features(set_dir, work / "anchor"), work / "limit")
    truth = read_truth(set_dir)
    offset = np.mean([C for _, C in truth.values()], axis=0)        # a local frame: no 1e6 m coordinates
    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(db) as d:
        cams = {c.camera_id: c for c in d.read_all_cameras()}
        ims = sorted(d.read_all_images(), key=lambda im: im.name)
    for c in cams.values():
        rec.add_camera_with_trivial_rig(c)
    for im in ims:
        R, C = truth[im.name]
        rec.add_image_with_trivial_frame(pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ (C - offset)))
    rec = pycolmap.triangulate_points(rec, db, set_dir / "images", work / "limit" / "triangulated",
                                      clear_points=True, refine_intrinsics=False)
    proj = {iid: rec.cameras[im.camera_id].calibration_matrix() @ im.cam_from_world().matrix()
            for iid, im in rec.images.items()}
    tracks = [[(el.image_id, rec.images[el.image_id].points2D[el.point2D_idx].xy) for el in p.track.elements]
              for p in rec.points3D.values()]
    out = {}
    for iid, im in rec.images.items():
        x2, X3 = [], []
        for tr in tracks:
            mine = [xy for i, xy in tr if i == iid]
            others = [(i, xy) for i, xy in tr if i != iid]
            if not mine or len(others) < 2:
                continue
            A = np.concatenate([[xy[0] * proj[i][2] - proj[i][0], xy[1] * proj[i][2] - proj[i][1]] for i, xy in others])
            X = np.linalg.svd(A)[2][-1]
            X = X[:3] / X[3]
            x = [proj[i] @ np.append(X, 1) for i, _ in others]
            if max(np.linalg.norm(xi[:2] / xi[2] - xy) for xi, (_, xy) in zip(x, others)) <= 1.0:
                x2.append(mine[0])
                X3.append(X)
        if len(X3) < 6:
            continue
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = 2.0
        r = pycolmap.estimate_and_refine_absolute_pose(np.array(x2), np.array(X3), rec.cameras[im.camera_id], est)
        if r is None:
            continue
        p = r["cam_from_world"]
        R, C = truth[im.name]
        Ce = -p.rotation.matrix().T @ p.translation + offset
        out[im.name] = {"pos_m": float(np.linalg.norm(Ce - C)), "rot_deg": rotation_deg(R, p.rotation.matrix()),
                        "n_points": len(X3), "n_inliers": int(r["num_inliers"])}
    return {"per_photo": out, "seconds": time.time() - t, "set_dir": set_dir}


def limit_median(limit: dict | None, set_dir: Path, every: int, held: bool = True) -> float | None:
    """The images' limit's median over the held-out photos (``held``) or the reference photos."""
    if not limit:
        return None
    names = set_photos(set_dir)
    v = [limit["per_photo"][n]["pos_m"] for i, n in enumerate(names)
         if (i % every == 1) == held and n in limit["per_photo"]]
    return float(np.median(v)) if v else None


# ---------------------------------------------------------------------------------------------- gtkit
def set_toml(project: Path, items: list[str]) -> None:
    """``section.key=value`` (TOML value, else a string) into project.toml (read, set, written again)."""
    import tomli_w

    cfg = tomllib.loads((project / "project.toml").read_text())
    for item in items:
        key, _, val = item.partition("=")
        try:
            v = tomllib.loads(f"v = {val}")["v"]
        except tomllib.TOMLDecodeError:
            v = val
        *path, last = key.strip().split(".")
        d = cfg
        for p in path:
            d = d.setdefault(p, {})
        d[last] = v
    (project / "project.toml").write_text(tomli_w.dumps(cfg))


def last_error(out: str, err: str) -> str:
    lines = [ln.strip() for ln in (err + "\n" + out).splitlines() if ln.strip()]
    for pat in (r"^(ERROR|Traceback|\w+Error)", r"^problem"):
        hit = [ln for ln in lines if re.match(pat, ln)]
        if hit:
            return hit[-1]
    return lines[-1] if lines else ""


def summary(set_dir: Path, project: Path, poses: str | None = None) -> dict:
    r = subprocess.run([sys.executable, str(SPLIT), "eval", str(set_dir), str(project)] + ([poses] if poses else []),
                       capture_output=True, text=True)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("summary ")), None)
    if line is None:
        return {"eval_error": (r.stderr.strip().splitlines() or ["no summary line"])[-1]}
    keys = ("n_photos", "median_pos_m", "median_rot_deg", "worst_pos_m", "n_with_sigma", "within_2sigma",
            "ref_median_pos_m")
    return {k: (None if v == "-" else float(v)) for k, v in zip(keys, line.split()[1:])}


def exact_medians(set_dir: Path, project: Path) -> tuple[float | None, float | None]:
    """(query median, reference block median) in metres, unrounded, by the eval's own functions: its
    summary line prints 0.1 mm, and fountain-P11 with K known read 0.0030 <= 1.5 x 0.0020 for 3.05 mm
    against 1.5 x 1.97 = 2.95 mm."""
    ts = runpy.run_path(str(SPLIT))
    truth = ts["_truth"](set_dir)
    out = []
    for rel in ("work/register/poses.txt", "work/sfm_reference/poses.txt"):
        err = [e[0] for e in ts["_errors"](ts["_poses"](project, rel), truth).values()]
        out.append(float(np.median(err)) if err else None)
    return out[0], out[1]


def gtkit_case(set_dir: Path, known: bool, rtk: bool, out: Path, toml_items: list[str], env: dict,
               every: int = 3) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    mk = subprocess.run([sys.executable, str(SPLIT), "make", str(set_dir), str(out)]
                        + (["--known-intrinsics"] if known else []) + (["--query-positions", "0.02"] if rtk else [])
                        + (["--every", str(every)] if every != 3 else []),
                        capture_output=True, text=True, check=True)
    init = shlex.split(next(ln for ln in mk.stdout.splitlines() if ln.startswith("gtkit init ")))
    project = Path(init[2])
    py = [sys.executable, "-m", "gtkit.cli"]
    r = subprocess.run(py + init[1:], capture_output=True, text=True, env=env, cwd=ROOT)
    res = {"project": str(project), "held_out": len(list((out / "q" / "seq").iterdir())), "tries": 1}
    if r.returncode:
        return {**res, "exit": r.returncode, "error": "init: " + last_error(r.stdout, r.stderr), "seconds": 0.0}
    if toml_items:
        set_toml(project, toml_items)
    for attempt in range(3):
        t = time.time()
        r = subprocess.run(py + ["run", str(project), "--until", "report"], capture_output=True, text=True, env=env,
                           cwd=ROOT)
        res.update(exit=r.returncode, seconds=time.time() - t, tries=attempt + 1,
                   error=last_error(r.stdout, r.stderr) if r.returncode else "")
        (out / "gtkit_run.log").write_text(r.stdout + "\n--- stderr ---\n" + r.stderr)
        if r.returncode in (0, 1) or not HALF_EDITED.search(r.stderr) or attempt == 2:
            break
        print(f"  gtkit crashed like a half-edited file ({res['error'][:100]}); again in 60 s", file=sys.stderr)
        time.sleep(60)
    res.update(summary(set_dir, project))
    query, ref = exact_medians(set_dir, project)   # the verdict's 1.5x on unrounded figures
    if query is not None:
        res["median_pos_m"] = query
    res["ref_median_pos_m"] = ref   # unrounded, and there even where no query photo registered
    return res


# ---------------------------------------------------------------------------------------------- table
def verdict(r: dict, anc: dict | None, known: bool, limit_m: float | None = None) -> str:
    n, ns = int(r.get("n_photos") or 0), int(r.get("n_with_sigma") or 0)
    if not n:
        return "none registered"
    bad = []
    if ns < n:
        bad.append(f"no sigma {n - ns}/{n}")
    if ns and (r.get("within_2sigma") or 0) < 0.9:
        bad.append("2 sigma < 90 %")
    if anc and anc.get("median_m") is not None:
        if r["median_pos_m"] > anc["median_m"] + max(anc["spread_m"], 0.002):
            bad.append("worse than anchor")
    else:
        bad.append("no anchor")
    if known and r.get("ref_median_pos_m") and r["median_pos_m"] > 1.5 * r["ref_median_pos_m"]:
        beyond = limit_m is not None and limit_m > 1.5 * r["ref_median_pos_m"]
        bad.append("> 1.5x reference" + (" (so is the images' limit)" if beyond else ""))
    if n < r["held_out"]:
        bad.append(f"{r['held_out'] - n} not registered")
    return ", ".join(bad) or "ok"


def mm(v, nd=1):
    return "-" if v is None else f"{1000 * v:.{nd}f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="+", default=["fountain-P11", "entry-P10"],
                    help="set names under ../shared/data/real_truth/ or folders of the same layout")
    ap.add_argument("--cases", default="", help="e.g. knownK,rtk (words: freeK knownK nopos rtk; default all four)")
    ap.add_argument("--anchor-runs", type=int, default=3, help="anchor SfMs per set and intrinsics (seeds 0..N-1)")
    ap.add_argument("--set-toml", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="set in project.toml before gtkit run (repeatable)")
    ap.add_argument("--work", type=Path, default=None, help="projects and anchor SfMs kept here (default: a temp dir)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--no-limit", action="store_true", help="skip the images' limit (about 1 min per set)")
    ap.add_argument("--every", type=int, default=3,
                    help="held-out photos: i %% EVERY == 1 (truth_split.py make --every; default 3)")
    a = ap.parse_args(argv)
    words = {w for w in a.cases.split(",") if w}
    if words - {"freeK", "knownK", "nopos", "rtk"}:
        ap.error(f"--cases: unknown {sorted(words - {'freeK', 'knownK', 'nopos', 'rtk'})}")
    cases = [(k, p) for k, p in CASES if (k in words or not words & {"freeK", "knownK"})
             and (p in words or not words & {"nopos", "rtk"})]
    work = (a.work or Path(tempfile.mkdtemp(prefix="bench_real_truth_"))).resolve()
    env = dict(os.environ, PYTHONPATH=str(ROOT), GTKIT_PROGRESS="0")
    t0, rows, anchors, limits = time.time(), [], {}, {}
    for s in a.sets:
        set_dir = (Path(s) if Path(s).is_dir() else SHARED / "data" / "real_truth" / s).resolve()
        name = set_dir.name
        if not a.no_limit:
            print(f"{name}: the images' limit (every photo resected against the others at their surveyed poses) ...",
                  file=sys.stderr, flush=True)
            limits[name] = images_limit(set_dir, work / name)
        lim = limit_median(limits.get(name), set_dir, a.every)
        for k, p in cases:
            if a.anchor_runs and (name, k) not in anchors:
                print(f"{name} {k}: anchor, {a.anchor_runs} SfM runs ...", file=sys.stderr, flush=True)
                anchors[name, k] = anchor(set_dir, k == "knownK", a.anchor_runs, work / name / "anchor", every=a.every)
                if k == "freeK":   # COLMAP's defaults hold the principal point at the centre; refined too
                    anchors[name, "freeK+pp"] = anchor(set_dir, False, a.anchor_runs, work / name / "anchor", True,
                                                      a.every)
            # the verdict against the better of the anchors (the smaller held-out median)
            anc = min((v for (n2, k2), v in anchors.items() if n2 == name and k2.startswith(k) and v.get("median_m")),
                      key=lambda v: v["median_m"], default=anchors.get((name, k)))
            print(f"{name} {k} {p}: gtkit ...", file=sys.stderr, flush=True)
            r = gtkit_case(set_dir, k == "knownK", p == "rtk", work / name / f"{k}_{p}", a.set_toml, env, a.every)
            r.update(set=name, K=k, positions=p, limit_median_m=lim, verdict=verdict(r, anc, k == "knownK", lim))
            rows.append(r)
            print(f"  exit {r['exit']} in {r['seconds']:.0f} s, {int(r.get('n_photos') or 0)}/{r['held_out']} "
                  f"registered, query median {mm(r.get('median_pos_m'))} mm {r['error'][:150]}", file=sys.stderr,
                  flush=True)
    print("\n| set | K | query positions | gtkit exit | reference median (mm) | query median (mm) | query worst (mm) | "
          "photos registered / held out | with sigma | within 2 sigma (%) | anchor median (mm, spread) | "
          "images' limit (mm) | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        anc = min((v for (n2, k2), v in anchors.items() if n2 == r["set"] and k2.startswith(r["K"]) and v.get("median_m")),
                  key=lambda v: v["median_m"], default={})
        n = int(r.get("n_photos") or 0)
        w2 = "-" if not r.get("n_with_sigma") else f"{100 * r['within_2sigma']:.0f}"
        print(f"| {r['set']} | {'known' if r['K'] == 'knownK' else 'self-cal.'} | "
              f"{'0.02 m' if r['positions'] == 'rtk' else 'none'} | {r['exit']} | {mm(r.get('ref_median_pos_m'))} | "
              f"{mm(r.get('median_pos_m'))} | {mm(r.get('worst_pos_m'))} | {n} / {r['held_out']} | "
              f"{int(r.get('n_with_sigma') or 0)} / {n} | {w2} | {mm(anc.get('median_m'))} "
              f"({mm(anc.get('spread_m'))}) | {mm(r.get('limit_median_m'))} | {r['verdict']} |")
    print("\ngtkit exits with an error line:" + ("" if any(r["exit"] for r in rows) else " none"))
    for r in [r for r in rows if r["exit"]]:
        print(f"- {r['set']} {r['K']} {r['positions']}: exit {r['exit']}: {r['error'][:300]}")
    print("\nanchor (one pycolmap SfM of all photos, similarity on the reference centres):")
    print("| set | K | held-out median per run (mm) | median (mm) | spread (mm) | reference median (mm) | "
          "photos not in the largest model | s |")
    print("|---|---|---|---|---|---|---|---|")
    for (name, k), anc in anchors.items():
        miss = sorted({m for x in anc["runs"] for m in x.get("missing", [])})
        print(f"| {name} | {k} | {', '.join(mm(x.get('query_median_m'), 2) for x in anc['runs'])} | "
              f"{mm(anc['median_m'], 2)} | {mm(anc['spread_m'], 2)} | {mm(anc['reference_median_m'], 2)} | "
              f"{', '.join(miss) or 'none'} | {anc['seconds']:.0f} |")
    if limits:
        print("\nthe images' limit per photo (mm; * held out): each photo resected against points triangulated from "
              "all the other photos at their surveyed poses, K known")
        for name, lim in limits.items():
            names = set_photos(lim["set_dir"])
            print(f"- {name}: " + ", ".join(f"{n}{'*' if i % a.every == 1 else ''} {mm(lim['per_photo'][n]['pos_m'])}"
                                          for i, n in enumerate(names) if n in lim["per_photo"])
                  + f" ({lim['seconds']:.0f} s)")
    print("\ngtkit run wall time (s, measured under whatever load the machine had): "
          + ", ".join(f"{r['set']} {r['K']} {r['positions']} {r['seconds']:.0f}"
                      + (f" ({r['tries']} tries)" if r["tries"] > 1 else "") for r in rows))
    print(f"whole benchmark: {time.time() - t0:.0f} s; work folder {work}")
    if a.json:
        a.json.write_text(json.dumps({"rows": rows, "anchors": [{"set": n, "K": k, **v} for (n, k), v in anchors.items()],
                                      "limits": {n: v["per_photo"] for n, v in limits.items()},
                                      "argv": sys.argv[1:], "seconds": time.time() - t0}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
