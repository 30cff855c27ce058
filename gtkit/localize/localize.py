"""``localize``: the online stage of UAVLoc (UAVD4L §3.2) for every query photo.

Per query: local features -> global descriptor -> rotation prior filter (gamma_o) and optional
GPS radius -> top-k database views -> matching against each -> lifting through the rendered
depth -> gravity-guided P3P RANSAC (gamma_eps) -> refined pose, or a failure with its reason.

Two additions to the paper's method (both recorded per query in ``status.json``; ablation
``paper`` switches both off, ``no-gps`` runs GPS-denied as the paper does):

- Position prior (``position_prior``): when the photo has GPS, altitude and gimbal angles, the
  candidate views are ranked by the overlap predicted from those sensors
  (:func:`gtkit.localize.prior.predicted_overlap`: the share of the ground the prior pose sees that a
  view sees) plus ``prior_vlad_weight`` x the global-descriptor score; views predicted to see none of
  it follow, by descriptor score (``position_prior`` in the status). Global descriptors alone fail on
  repetitive fields and swing with the codebook (R@1 57 % on the small sample, seed 0; 100 % with the
  predicted overlap). ``"footprint"`` is the earlier rule (views whose look-at point lies within
  ``gps_footprint_radius_m`` of the query's first, then descriptor score), kept as an ablation.
  A photo with GPS but no gimbal angles (consumer cameras) gets the views near its GPS position
  first (``no_attitude_radius_m``), by descriptor score.
- Photos without gimbal angles are localized too: no rotation prior filter, plain P3P RANSAC (no
  gravity check); ``status.json`` lists them (``no_attitude``) and says so per query.

Which photos are queries: ``[sfm] query_pattern`` (:func:`gtkit.queries.query_photos`); their
intrinsics: :func:`gtkit.queries.query_cameras` (cameras.txt, else the sequence's SfM, else the
reference block's calibration of the same camera, else the EXIF focal), each query's source in
``status.json`` (``intrinsics``; ``intrinsics_sources`` counts them).
- Fallback (``fallback_rounds``): when PnP fails on the top-k views, the next top-k of the ranking
  are tried (``fallback_round``, ``fallback_retrieved``, ``failed_rounds``). Retrieval metrics
  score the first top-k only.

Features: ``sift`` + ``nn-ratio`` by default; ``xfeat`` + ``lighterglue`` (ablation ``xfeat``,
extra ``gtkit[learned]``). Global retrieval is VLAD on the extractor's own descriptors (RootSIFT,
or XFeat's unit 64-d ones), so the learned run extracts one set of features per image.

Offline parts, cached under ``work/localize_db/<extractor conf>/`` and shared by every run and
ablation: database features (``features.h5``, one group per view), the VLAD codebook and the
database's global descriptors. By default (``db_features = "reachable"``) only the views some
query's sensor priors can bring into its ranking get features and a descriptor
(:func:`reachable_views`; the same ranking as with every view); the rest are extracted when a later
query can reach them.

Outputs under ``work/localize/`` (or ``work/localize-<ablation>/``): ``poses.txt`` (only the
queries that were localized; never a prior or a database pose), ``status.json`` (per query:
ok, reason, retrieved views with scores, matches/inliers, seconds by step), ``pairs.txt``
(query, retrieved view, rank), ``covariances.txt`` (6x6 pose covariance of every localized
query, :func:`gtkit.localize.pnp.pose_covariance`; the tracker reads it), ``stage.json``.

Size: the stage's per-query steps (retrieval with priors, matching, lifting, PnP, the fallback
rounds) share one query record and its reasons; its parts live beside it (features, prior, pnp,
lift, reach), and what stays here is the loop that ties them to one result per query.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..conventions import dji_to_rotation, gravity_in_camera
from ..errors import GtkitError
from ..io.atomic import atomic_path, write_json, write_text
from ..io.poses import POSES, write_covariances, write_poses
from ..pose import Pose
from ..project import (STAGE_RECORD, Project, file_fingerprint, mark_stage_done, read_stage_record, relative_paths,
                       settings_dict, settings_key, stage_done, start_stage_clock)
from .database import PAPER_PITCHES, Database, load_database
from .executors import ExecutorSettings, SerialExecutor, iter_map, make_executor, run_map
from .pnp import PnPSettings
from .reach import codebook_views, query_names, reachable_views, select_views, sensor_priors, view_arrays
from .settings import XFEAT_FEATURES, FeatureSettings, LocalizeSettings  # noqa: F401 - re-exported

log = logging.getLogger(__name__)
STEPS = ("features", "retrieval", "matching", "lifting", "pnp")
MIN_QUERY_KEYPOINTS = 20


# Ablations (the paper's tables): each names its own output folder work/localize-<name>/.
ABLATIONS: dict[str, dict] = {
    "default": {},
    "paper": {"position_prior": None, "fallback_rounds": 0,                   # the paper's method as published
              "db_paper_pitches": PAPER_PITCHES},                              # (its database: 0 and 45 deg)
    "no-gps": {"position_prior": None},                                       # GPS-denied (paper setting)
    "footprint-prior": {"position_prior": "footprint"},                       # the look-at radius rule (before)
    "no-fallback": {"fallback_rounds": 0},
    "no-rot-prior": {"rotation_prior": False},
    "no-gravity": {"pnp": {"gravity_deg": None}},
    "gravity-2deg": {"pnp": {"gravity_deg": 2.0}},                                   # the paper's gamma_eps
    "no-priors": {"rotation_prior": False, "pnp": {"gravity_deg": None}},
    "top1": {"top_k": 1},
    "render-1h-p45": {"db_highest_only": True, "db_paper_pitches": (45.0,)},   # paper: H=150, pitch 45
    "render-2h-p45": {"db_paper_pitches": (45.0,)},                           # paper: H=150 & 100, pitch 45
    "render-paper": {"db_paper_pitches": PAPER_PITCHES},                      # the paper's pitches, no 70 deg level
    # learned features (extra gtkit[learned]): XFeat + LighterGlue, retrieval = VLAD on XFeat descriptors
    "xfeat": {"features": XFEAT_FEATURES, "matcher": "lighterglue"},
}


def settings_for(ablation: str = "default", base: LocalizeSettings = LocalizeSettings()) -> LocalizeSettings:
    if ablation not in ABLATIONS:
        raise GtkitError(f"unknown ablation {ablation!r} (choose from {', '.join(ABLATIONS)})")
    over = dict(ABLATIONS[ablation])
    if "pnp" in over:
        over["pnp"] = dataclasses.replace(base.pnp, **over["pnp"])
    return dataclasses.replace(base, **over)


def output_dir(project: Project, ablation: str = "default") -> Path:
    return project.paths.stage("localize" if ablation == "default" else f"localize-{ablation}")


def _settings_from_dict(d: dict) -> LocalizeSettings:
    d = dict(d)
    d["features"] = FeatureSettings(**d["features"])
    d["pnp"] = PnPSettings(**d["pnp"])
    for k in ("db_heights", "db_paper_pitches", "prior_angle_deg"):
        if d.get(k) is not None:
            d[k] = tuple(d[k])
    return LocalizeSettings(**d)


# --- offline: database features and global descriptors --------------------------------------

def _db_cache(project: Project, s: LocalizeSettings) -> Path:
    """Keyed by the feature settings *and* the database's render settings, so a re-rendered
    database never meets features of its predecessor."""
    rec = project.paths.stage("render_db") / "settings.json"
    db_key = json.loads(rec.read_text()) if rec.is_file() else {}
    from .features import CODE_VERSION

    key = settings_key({"features": settings_dict(s.features), "render_db": db_key,
                        "code": CODE_VERSION.get(s.features.extractor, 1)})
    return project.paths.stage("localize_db") / f"{s.features.extractor}-{key[:8]}"


def _extractor(fs: FeatureSettings, db: bool):
    from .features import make_extractor

    kw = {"max_keypoints": fs.max_keypoints_db if db else fs.max_keypoints, "max_side": fs.max_side}
    if fs.extractor == "sift":
        kw["contrast_threshold"] = fs.contrast_threshold
    return make_extractor(fs.extractor, **kw)


def _matcher(s: LocalizeSettings):
    from .features import make_matcher

    return make_matcher(s.matcher, **({"ratio": s.ratio} if s.matcher == "nn-ratio" else {}))


_W: dict = {}


def _extract_db_views(task):
    """Features of a chunk of database views -> ([(name, Features | None)], CPU seconds of the chunk).
    ``one_thread``: the executor runs one worker a core, so OpenCV's own threads would only
    oversubscribe the cores."""
    import cv2

    fs_d, items, one_thread = task
    c0 = time.process_time()
    if one_thread:
        cv2.setNumThreads(1)
    fs = FeatureSettings(**fs_d)
    key = ("dbx", fs)
    if _W.get("dbx_key") != key:
        _W["dbx"] = _extractor(fs, db=True)
        _W["dbx_key"] = key
    out = []
    for name, path in items:
        img = cv2.imread(path, cv2.IMREAD_COLOR)
        if img is None:
            out.append((name, None))
            continue
        out.append((name, _W["dbx"].extract(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))))
    return out, time.process_time() - c0


def prepare_database(project: Project, db: Database, s: LocalizeSettings, executor: ExecutorSettings,
                     views: set[str] | None = None) -> dict:
    """Database features + VLAD codebook + global descriptors, cached; returns seconds by step.

    ``views``: the views that need a global descriptor (None = every view of ``db``); features are
    extracted for those and for the codebook's views (:func:`codebook_views`), and kept in the feature
    store, so a later run extracts only views it has not seen."""
    import h5py

    from . import feature_store
    from .descriptors import Vlad

    cache = _db_cache(project, s)
    cache.mkdir(parents=True, exist_ok=True)
    feats = cache / "features.h5"
    times = {}
    t0 = time.perf_counter()
    described = sorted(v.name for v in db.views) if views is None else sorted(views)
    from .database import planned_names

    kept = {v.name for v in db.views}
    train = [n for n in codebook_views(planned_names(project), s) if n in kept]
    wanted = set(described) | set(train)
    done = feature_store.stored_views(feats)   # the feature file + the chunks a killed run finished
    todo = [v for v in db.views if v.name in wanted and v.name not in done]
    c0, worker_cpu = time.process_time(), 0.0
    if todo:
        ex = make_executor(executor)
        one_thread = not isinstance(ex, SerialExecutor)  # a worker a core (dask: one thread a worker)
        tasks = [(asdict(s.features), [(v.name, str(v.image)) for v in todo[i:i + 16]], one_thread)
                 for i in range(0, len(todo), 16)]
        try:
            for res, cpu in iter_map(ex, _extract_db_views, tasks, progress="db features"):
                worker_cpu += cpu if one_thread else 0.0  # serial: already in this process's time
                for name, f in res:
                    if f is None:
                        raise GtkitError("unreadable database image", db.root / "images" / f"{name}.jpg")
                feature_store.write_part(feats, dict(res))  # each chunk a whole file: a killed run resumes here
        finally:
            ex.close()
    feature_store.merge_parts(feats)
    times["db_features_s"] = time.perf_counter() - t0
    times["db_features_views"] = len(todo)
    times["db_views_described"] = len(described)
    times["db_views_total"] = len(db.views)
    # CPU seconds: this process (all its threads) + what each chunk took in its worker (worker
    # start-up not counted; the stage's cost record counts it for local processes)
    times["db_features_cpu_s"] = time.process_time() - c0 + worker_cpu
    times["db_features_kb_per_view"] = (feats.stat().st_size / 1024 / max(1, len(feature_store.stored_views(feats)))
                                        if feats.is_file() else None)
    t0, c0 = time.perf_counter(), time.process_time()
    # the codebook (keyed by its training views), then the global descriptors of the described views
    # (keyed by the codebook and their names)
    ckey = settings_key({"names": train, "words": s.vlad_words, "desc": s.descriptor})
    cfile = cache / f"codebook-{s.descriptor}{s.vlad_words}-{ckey[:8]}.npy"
    if cfile.is_file():
        vlad = Vlad.load(cfile)
    else:
        with h5py.File(feats, "r") as h5:
            rng = np.random.default_rng(0)
            per = max(50, 200_000 // max(1, len(train)))
            sample = []
            for n in train:
                d = h5[n]["desc"][()]
                if len(d):
                    sample.append(d[rng.choice(len(d), min(per, len(d)), replace=False)])
        if not sample:
            raise GtkitError("database views have no features (textureless model?)", feats)
        vlad = Vlad.train(np.concatenate(sample), k=s.vlad_words)
        vlad.save(cfile)
    gkey = settings_key({"codebook": ckey, "names": described})
    gfile = cache / f"global-{s.descriptor}{s.vlad_words}-{gkey[:8]}.npz"
    # the descriptor matrix (views x words x 128 float32: 32 KB a view at 64 words, 0.85 GB for 26k
    # views) is kept apart as .npy, memory-mapped by every worker (one copy in the page cache, not one
    # a worker); the .npz (codebook, names) is written last and marks the pair complete
    gmat = gfile.with_name(gfile.stem + "-G.npy")
    if not (gfile.is_file() and gmat.is_file()):
        with h5py.File(feats, "r") as h5:
            G = (np.concatenate([vlad.describe_many([h5[n]["desc"][()] for n in described[i:i + 64]])
                                 for i in range(0, len(described), 64)]).astype(np.float32)
                 if described else np.zeros((0, vlad.dim), np.float32))
        with atomic_path(gmat) as tmp, open(tmp, "wb") as f:
            np.save(f, G)
        with atomic_path(gfile) as tmp, open(tmp, "wb") as f:
            np.savez(f, centers=vlad.centers, names=np.array(described))
    times["db_global_s"] = time.perf_counter() - t0
    times["db_global_cpu_s"] = time.process_time() - c0
    return {"cache": str(cache), "features": str(feats), "global": str(gfile), "global_matrix": str(gmat), **times}


# --- per query (runs in workers) ------------------------------------------------------------

def _camera(line: str) -> Camera:
    f = line.split()
    return Camera(f[0], int(f[1]), int(f[2]), tuple(float(x) for x in f[3:]))


def _context(ctx: dict):
    """Per-process cache of what every query needs (database, descriptors, extractor, matcher)."""
    key = json.dumps(ctx, sort_keys=True)
    if _W.get("ctx_key") != key:
        import h5py

        from .descriptors import Vlad

        s = _settings_from_dict(ctx["settings"])
        proj = Project.load(ctx["root"])
        db = select_views(load_database(proj), s)
        g = np.load(ctx["global"])
        index = {n: i for i, n in enumerate(g["names"].tolist())}
        rows = np.array([index.get(v.name, -1) for v in db.views], dtype=int)
        described = np.flatnonzero(rows >= 0)       # the views with a global descriptor (db_features)
        G = np.load(ctx["global_matrix"], mmap_mode="r")
        G = G if np.array_equal(rows, np.arange(len(G))) else np.ascontiguousarray(G[rows[described]])  # a copy
        if "h5" in _W:
            _W["h5"].close()
        cameras = ctx.get("cameras")            # resolved once by run(); else here
        if cameras is None:
            from ..queries import query_cameras

            cameras = {n: [c.camera.to_line(), c.source] for n, c in query_cameras(proj, query_names(proj, s)).items()}
        _W.update(ctx_key=key, s=s, project=proj, db=db, vlad=Vlad(g["centers"]), G=G, described=described,
                  has_descriptor=rows >= 0,
                  **view_arrays(db),
                  h5=h5py.File(ctx["features"], "r"), extractor=_extractor(s.features, db=False),
                  matcher=_matcher(s), cams={n: _camera(line) for n, (line, _src) in cameras.items()},
                  cam_sources={n: src for n, (_line, src) in cameras.items()})
    return _W


def rank_candidates(score: np.ndarray, keep: np.ndarray, near: np.ndarray | None, n: int) -> np.ndarray:
    """Indices of up to ``n`` views passing ``keep``, best ``score`` first; when ``near`` (the
    position prior) is given, every view passing it comes before any that does not."""
    s = np.where(keep, score, -np.inf)
    idx = np.flatnonzero(keep)
    if near is None:
        return idx[np.argsort(-s[idx], kind="stable")][:n]
    first = idx[near[idx]]
    rest = idx[~near[idx]]
    return np.concatenate([first[np.argsort(-s[first], kind="stable")],
                           rest[np.argsort(-s[rest], kind="stable")]])[:n].astype(int)


def localize_query(task) -> dict:
    """Localize one query; never raises for a bad query (the reason goes into the result)."""
    ctx, name = task
    t0 = time.perf_counter()
    W = _context(ctx)  # once per worker process: database, descriptors, extractor, matcher
    t_start, c_start = time.perf_counter(), time.process_time()
    try:
        out = _localize_query(W, name)
    except GtkitError as e:
        out = {"name": name, "ok": False, "reason": str(e), "seconds": {}}
    except Exception as e:  # noqa: BLE001 - one bad query must not stop the run; the reason says what broke
        log.exception("localize: %s failed", name)
        out = {"name": name, "ok": False, "reason": f"internal error ({type(e).__name__}: {e})", "seconds": {}}
    out["seconds_total"] = time.perf_counter() - t_start
    out["cpu_seconds_total"] = time.process_time() - c_start  # this process's CPU time (all its threads)
    out["seconds_setup"] = t_start - t0
    return out


def release_worker_state() -> None:
    """Close what :func:`_context` holds open in this process (the feature file)."""
    if "h5" in _W:
        _W.pop("h5").close()
    _W.pop("ctx_key", None)


def _localize_query(W: dict, name: str) -> dict:
    import cv2

    from ..io.exif import read_photo_meta

    s: LocalizeSettings = W["s"]
    proj: Project = W["project"]
    db: Database = W["db"]
    sec = {k: 0.0 for k in STEPS}
    rec: dict = {"name": name, "ok": False, "reason": None, "seconds": sec}
    path = proj.paths.images / name
    cam: Camera = W["cams"][name]
    rec["intrinsics"] = W["cam_sources"][name]
    meta = read_photo_meta(path)
    prior_R = None
    rec["attitude"] = bool(meta.has_gimbal)
    if meta.has_gimbal:
        rec["prior_ypr"] = [meta.gimbal_yaw, meta.gimbal_pitch, meta.gimbal_roll]
        prior_R = dji_to_rotation(meta.gimbal_yaw, meta.gimbal_pitch, meta.gimbal_roll)
    elif s.rotation_prior or s.pnp.gravity_deg is not None:
        rec["note"] = ("no DJI gimbal angles: retrieval without the rotation prior, plain P3P RANSAC "
                       "(no gravity check)")
    # features
    t = time.perf_counter()
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise GtkitError("unreadable query image", path)
    if (bgr.shape[1], bgr.shape[0]) != (cam.width, cam.height):
        raise GtkitError(f"image is {bgr.shape[1]}x{bgr.shape[0]} but its intrinsics say {cam.width}x{cam.height}",
                         path)
    fq = W["extractor"].extract(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    sec["features"] = time.perf_counter() - t
    rec["n_keypoints"] = len(fq)
    if len(fq) < MIN_QUERY_KEYPOINTS:
        rec["reason"] = (f"too few keypoints in the query ({len(fq)} < {MIN_QUERY_KEYPOINTS}): "
                         "a textureless view (water, haze, blur?)")
        return rec
    # retrieval
    t = time.perf_counter()
    keep, near, pred, prior_rec = sensor_priors(W, s, proj, db, meta, cam, prior_R)
    rec["n_candidates"] = int(keep.sum())
    if not keep.any():
        sec["retrieval"] = time.perf_counter() - t
        rec["reason"] = (f"no database view within {s.gamma_o:g} deg of the IMU prior "
                         f"(yaw, pitch, roll = {', '.join(f'{a:.1f}' for a in rec.get('prior_ypr', []))})"
                         if s.rotation_prior and prior_R is not None else "no database view passes the priors")
        return rec
    if prior_rec is not None:
        rec["position_prior"] = prior_rec
    score = np.zeros(len(db.views))
    score[W["described"]] = W["G"] @ W["vlad"].describe(fq.desc)
    key = score if pred is None else pred + s.prior_vlad_weight * score
    keep = keep & W["has_descriptor"]    # a view without one is never ranked (db_features "reachable":
                                         # it could not have been)
    ranked = rank_candidates(key, keep, near, s.top_k * (1 + max(0, s.fallback_rounds)))
    sec["retrieval"] = time.perf_counter() - t
    rounds = [ranked[k:k + s.top_k] for k in range(0, len(ranked), s.top_k)]
    # round 0 = the top-k (what retrieval metrics score); later rounds = fallback views
    rec["retrieved"] = [[db.views[i].name, float(score[i])] for i in rounds[0]] if rounds else []
    failed = []
    for rnd, order in enumerate(rounds):
        if rnd:
            failed.append(rec["reason"])
            rec["reason"] = None
            rec.setdefault("fallback_retrieved", []).extend([db.views[i].name, float(score[i])] for i in order)
            log.info("localize: %s: top-%d failed (%s); falling back to the next %d views", name, s.top_k,
                     failed[-1], len(order))
        rec["fallback_round"] = rnd
        _match_and_solve(W, rec, fq, cam, prior_R, order, sec)
        if rec["ok"]:
            break
    if failed:
        rec["failed_rounds"] = failed
        if not rec["ok"]:
            rec["reason"] = f"{rec['reason']} (also with {len(failed)} fallback round(s) of {s.top_k} more views)"
    return rec


def render_missing_views(project: Project, s: LocalizeSettings, names: list[str], cameras: dict[str, Camera],
                         executor: ExecutorSettings) -> int:
    """Render the planned database views these settings reach that are not on disk (a database
    rendered for other priors, e.g. the project's, and an ablation without the position prior);
    returns how many were missing."""
    from . import database

    db, cand, planned = database.load_grid(project)
    if len(cand) == len(db.views):              # every view not dropped is rendered
        return 0
    _want, todo = database.reachable_not_rendered(project, planned, cand, {v.name for v in db.views}, db.camera,
                                                  db.root, s, names, cameras)
    if todo:
        rec = read_stage_record(project.paths.stage(database.STAGE)).settings
        log.info("localize: %d database views these settings reach are not rendered yet: rendering them", len(todo))
        database.run(project, database.render_settings(rec), executor, localize_settings=s)
    return len(todo)


def _match_and_solve(W: dict, rec: dict, fq, cam: Camera, prior_R, order, sec: dict) -> None:
    """Match the query with the views ``order``, lift, gravity-guided PnP; fills ``rec``."""
    from .features import read_features
    from .lift import lift
    from .pnp import gravity_pnp_ransac

    s: LocalizeSettings = W["s"]
    db: Database = W["db"]
    pin = cam.pinhole_part()
    uv_q, X_all, per_view = [], [], []
    for i in order:
        v = db.views[i]
        t = time.perf_counter()
        fd = read_features(W["h5"], v.name)
        m = W["matcher"].match(fq, fd)
        sec["matching"] += time.perf_counter() - t
        t = time.perf_counter()
        info = {"view": v.name, "n_matches": int(len(m))}
        depth = db.depth(v) if len(m) else None
        if len(m) and (depth is None or not np.isfinite(depth).any()):
            info["problem"] = "database view has no valid depth"
            info["n_lifted"] = 0
        elif len(m):
            X, ok = lift(fd.kp[m[:, 1]], depth, db.camera, v.pose, s.max_rel_jump)
            info["n_lifted"] = int(ok.sum())
            uv_q.append(fq.kp[m[ok, 0]])
            X_all.append(X[ok])
        else:
            info["n_lifted"] = 0
        per_view.append(info)
        sec["lifting"] += time.perf_counter() - t
    rec["views"] = rec.get("views", []) + per_view
    n_lift = int(sum(len(x) for x in X_all))
    rec["n_lifted"] = n_lift
    t = time.perf_counter()
    if n_lift == 0:
        probs = {i.get("problem") for i in per_view} - {None}
        rec["reason"] = ("no 2D-3D correspondences: " + ("; ".join(sorted(probs)) if probs else
                         f"{sum(i['n_matches'] for i in per_view)} matches with the retrieved views "
                         f"(query has {len(fq)} keypoints), none lifted"))
        return
    uv = np.concatenate(uv_q)
    X = np.concatenate(X_all)
    if cam.has_distortion:  # PnP on the undistorted pinhole part
        uv = cam.undistort_pixels(uv)
    g = gravity_in_camera(prior_R) if prior_R is not None else None
    r = gravity_pnp_ransac(uv, X, pin, g, s.pnp)
    sec["pnp"] += time.perf_counter() - t
    rec["pnp"] = r.summary()
    if not r.ok:
        rec["reason"] = r.reason
        return
    sigma = None if r.pose.covariance is None else float(np.sqrt(np.trace(r.pose.center_covariance())))
    if s.max_sigma_pos_m is not None and (sigma is None or sigma > s.max_sigma_pos_m):
        rec["reason"] = (f"pose too uncertain: position sigma {sigma:.2f} m > {s.max_sigma_pos_m:g} m "
                         f"({r.n_inliers} inliers of {r.n_matches} matches)" if sigma is not None else
                         "pose without a covariance (degenerate inliers)")
        rec.setdefault("rejected_poses", []).append({"q": r.pose.q.tolist(), "t": r.pose.t.tolist(),
                                                     "sigma_pos_m": sigma, "n_inliers": r.n_inliers})
        return
    rec["ok"] = True
    rec["q"] = r.pose.q.tolist()
    rec["t"] = r.pose.t.tolist()
    if r.pose.covariance is not None:
        rec["covariance"] = r.pose.covariance.reshape(-1).tolist()
        rec["sigma_pos_m"] = sigma
        rec["sigma_rot_deg"] = float(np.degrees(np.sqrt(np.trace(r.pose.covariance[:3, :3]))))


# --- the stage ----------------------------------------------------------------------------------

def _count(sources) -> dict[str, int]:
    """How many photos took their intrinsics from each kind of source."""
    from collections import Counter

    return dict(Counter(s.split(" (")[0] for s in sources))


def run(project: Project | str | Path, settings: LocalizeSettings, ablation: str = "default",
        executor: ExecutorSettings = ExecutorSettings(), force: bool = False) -> Path:
    """Localize every query; returns the output folder. Skips when settings and inputs match."""
    project = project if isinstance(project, Project) else Project.load(project)
    out = output_dir(project, ablation)
    dbdir = project.paths.stage("render_db")
    names = query_names(project, settings)
    if not names:
        from ..queries import query_pattern

        raise GtkitError(f"no query photos: nothing in images/queries/<seq>/ matches [sfm] query_pattern "
                         f"{query_pattern(project)!r}" + (f" and the subset {settings.query_subset!r}"
                                                          if settings.query_subset else ""), project.paths.query_images)
    from ..queries import query_cameras
    from .features import CODE_VERSION

    if settings.db_features not in ("reachable", "all"):
        raise GtkitError(f"[localize] db_features must be \"reachable\" or \"all\", not {settings.db_features!r}",
                         project.paths.root / "project.toml")
    qc = query_cameras(project, names)
    qcams = {n: [c.camera.to_line(), c.source] for n, c in qc.items()}
    cams = {n: _camera(line) for n, (line, _src) in qcams.items()}   # as the workers read them
    n_missing = render_missing_views(project, settings, names, cams, executor)
    inputs = {"render_db": file_fingerprint(dbdir / STAGE_RECORD), "queries": settings_key(names),
              "cameras": settings_key(qcams), "feature_code": CODE_VERSION.get(settings.features.extractor, 1)}
    if not force and stage_done(out, settings, inputs):
        log.info("localize: up to date (%s)", out)
        return out
    start_stage_clock(out)
    t_all = time.perf_counter()
    db_full = load_database(project)
    db = select_views(db_full, settings)
    if not db.views:
        have = sorted({(v.height, v.paper_pitch) for v in db_full.views})
        raise GtkitError("the database subset chosen by the settings is empty: the run needs heights "
                         f"{settings.db_heights or 'any'} and pitches {settings.db_paper_pitches or 'any'}, the "
                         f"database holds (height, pitch) {have}; render it with those levels "
                         "(gtkit render-db --heights ... --pitches ...)", dbdir)
    views = None
    if settings.db_features == "reachable":
        reach = reachable_views(project, db, settings, names, cams)
        views = {v.name for v, r in zip(db.views, reach) if r}
        log.info("localize: %d of %d database views are reachable from the queries' sensor priors",
                 len(views), len(db.views))
    offline = prepare_database(project, db_full, settings, executor, views=views)
    ctx = {"root": str(project.paths.root), "settings": settings_dict(settings),
           "features": offline["features"], "global": offline["global"], "global_matrix": offline["global_matrix"],
           "cameras": qcams}
    t0 = time.perf_counter()
    ex = make_executor(executor)
    try:
        results = run_map(ex, localize_query, [(ctx, n) for n in names], progress="localize")
    finally:
        ex.close()
        release_worker_state()
    wall = time.perf_counter() - t0
    poses = {r["name"]: Pose.from_qt(r["q"], r["t"]) for r in results if r["ok"]}
    covs = {r["name"]: np.array(r["covariance"]).reshape(6, 6) for r in results if r["ok"] and "covariance" in r}
    out.mkdir(parents=True, exist_ok=True)
    write_poses(out / POSES, poses, header=f"gtkit localize ({ablation}); failures are absent, "
                "see status.json")
    write_covariances(out / "covariances.txt", covs)
    pairs = [f"{r['name']} {v} {k + 1}" for r in results
             for k, (v, _s) in enumerate(r.get("retrieved", []) + r.get("fallback_retrieved", []))]
    write_text(out / "pairs.txt", "# query database_view rank\n" + "\n".join(pairs) + "\n")
    n_ok = len(poses)
    write_json(out / "status.json", relative_paths({  # portable: paths relative to the project root
        "ablation": ablation, "settings": settings_dict(settings), "n_queries": len(names), "n_localized": n_ok,
        "database_views": len(db.views), "database_views_rendered_for_this_run": n_missing, "offline": offline, "wall_s": wall, "total_s": time.perf_counter() - t_all,
        "intrinsics_sources": _count(src for _line, src in qcams.values()),
        "no_attitude": sorted(r["name"] for r in results if r.get("attitude") is False),
        "executor": asdict(executor), "queries": results}, project.paths.root))
    mark_stage_done(out, settings, inputs, outputs=[Path(offline["cache"])], n_queries=len(names), n_localized=n_ok,
                    wall_s=round(wall, 2), db_features_s=round(offline["db_features_s"], 2),
                    db_features_views=offline["db_features_views"], db_views_described=offline["db_views_described"],
                    db_views_total=offline["db_views_total"], db_global_s=round(offline["db_global_s"], 2),
                    db_features_cpu_s=round(offline["db_features_cpu_s"], 2),
                    db_global_cpu_s=round(offline["db_global_cpu_s"], 2),
                    db_features_kb_per_view=None if offline["db_features_kb_per_view"] is None
                    else round(offline["db_features_kb_per_view"], 1))
    log.info("localize (%s): %d of %d queries localized in %.1f s", ablation, n_ok, len(names), wall)
    return out
