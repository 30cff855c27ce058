"""The localization chain end to end on a small synthetic site with known truth: render-db,
localize (local processes and Dask), evaluate; failure cases; resume."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from gtkit.cli import main
from gtkit.errors import GtkitError
from gtkit.io.poses import read_poses
from gtkit.localize import database, feature_store, localize
from gtkit.localize.executors import ExecutorSettings, make_executor, run_map
from test_localize_scene import build_site, default_queries

WATER = "queries/seq2/0001_W.jpg"
OFF60 = "queries/seq2/0002_W.jpg"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("loc") / "site"
    build_site(root, default_queries())
    # the test grid in project.toml, as a user sets it, so that every entry point renders the same one
    from gtkit.project import Project

    proj = Project.load(root)
    proj.config["render_db"] = {"heights": [120.0], "intervals": [100.0], "paper_pitches": [0.0, 45.0], "yaw_step": 90.0,
                                "width": 480, "height": 360, "hfov_deg": 60.0}
    proj.save()
    assert main(["render-db", str(root), "--executor", "serial"]) == 0
    return root


def _db_settings():
    return database.RenderDbSettings(heights=(120.0,), intervals=(100.0,), paper_pitches=(0.0, 45.0), yaw_step=90.0,
                                     width=480, height=360, hfov_deg=60.0)


def test_render_db_depth_is_metric_and_resume_is_per_view(site):
    out = site / "work" / "render_db"
    views = json.loads((out / "views.json").read_text())
    assert len(views["views"]) == 5 * 4 * 8          # 450 m x 300 m extent, 100 m grid, 2 pitches x 4 yaws
    kept = [v for v in views["views"] if v["kept"]]
    assert 0 < len(kept) < len(views["views"])        # outward-looking edge views are dropped
    assert abs(views["ground_level_z"]) < 1e-3        # the plane is at z = 0
    assert len(read_poses(out / "poses.txt")) == len(kept)
    # nadir views over the plane see depth = 120 m along the optical axis (boxes aside)
    nadir = [v for v in kept if v["paper_pitch"] == 0.0]
    d = database.read_depth(out / "depth" / f"{nadir[0]['name']}.npz")
    assert d.dtype == np.float32 and abs(float(np.nanmedian(d)) - 120.0) < 0.01
    # resume: three views lost -> exactly those three are rendered again, identically
    lost = [v["name"] for v in kept[:3]]
    before = {n: database.read_depth(out / "depth" / f"{n}.npz") for n in lost}
    for n in lost:
        (out / "depth" / f"{n}.npz").unlink()
    (out / "stage.json").unlink()
    database.run(site, _db_settings(), ExecutorSettings("serial"), localize_settings=localize.LocalizeSettings())
    rec = json.loads((out / "stage.json").read_text())
    assert rec["summary"]["n_rendered"] == 3
    for n in lost:
        assert np.array_equal(database.read_depth(out / "depth" / f"{n}.npz"), before[n], equal_nan=True)


def test_changing_the_pitch_levels_keeps_the_views_and_features_on_disk(site, tmp_path):
    """Pitch levels and the keep threshold choose which views exist; a view of a given name looks
    the same whatever they are, so changing them renders nothing again and keeps the feature cache."""
    from gtkit.project import Project, settings_dict

    copy = tmp_path / "site"
    shutil.copytree(site, copy, ignore=shutil.ignore_patterns("localize*", "reports"))
    out = copy / "work" / "render_db"
    s0 = _db_settings()
    key0 = localize._db_cache(Project.load(copy), localize.LocalizeSettings())
    nadir = replace(s0, paper_pitches=(0.0,), min_valid_fraction=0.6)
    database.run(copy, nadir, ExecutorSettings("serial"), localize_settings=localize.LocalizeSettings())
    rec = json.loads((out / "stage.json").read_text())["summary"]
    assert rec["n_rendered"] == 0 and rec["n_views"] == 5 * 4 * 4
    assert {v["paper_pitch"] for v in json.loads((out / "views.json").read_text())["views"]} == {0.0}
    database.run(copy, s0, ExecutorSettings("serial"), localize_settings=localize.LocalizeSettings())            # back: the 45 deg views are still there
    rec = json.loads((out / "stage.json").read_text())["summary"]
    assert rec["n_rendered"] == 0 and rec["n_views"] == 5 * 4 * 8
    assert localize._db_cache(Project.load(copy), localize.LocalizeSettings()) == key0
    # what changes a view's pixels does start the database (and its features) again
    record = json.loads((out / "settings.json").read_text())
    assert database.view_record(settings_dict(replace(s0, hfov_deg=50.0)), record["inputs"]) != record
    assert database.view_record(settings_dict(replace(s0, paper_pitches=(70.0,))), record["inputs"]) == record


def test_database_features_resume_after_the_process_is_killed(site, tmp_path):
    """Database features are kept chunk by chunk, each chunk a whole file: a run killed (SIGKILL)
    mid-way leaves no half-written file, and the next run extracts only the views still missing.
    (Appending to one HDF5 file in place was not safe: a kill during a metadata write left a file
    that opened but failed on a lookup, "addr overflow".)"""
    import os
    import signal
    import subprocess
    import sys
    import time

    from gtkit.project import Project

    copy = tmp_path / "site"
    shutil.copytree(site, copy, ignore=shutil.ignore_patterns("localize*", "reports"))
    code = ("from gtkit.project import Project\n"
            "from gtkit.localize import localize\n"
            "from gtkit.localize.database import load_database\n"
            "from gtkit.localize.executors import ExecutorSettings\n"
            f"p = Project.load({str(copy)!r})\n"
            "localize.prepare_database(p, load_database(p), localize.LocalizeSettings(), ExecutorSettings('serial'))\n")
    feats = localize._db_cache(Project.load(copy), localize.LocalizeSettings()) / "features.h5"
    parts = feats.with_name("features.h5.parts")
    proc = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    t0 = time.time()
    while proc.poll() is None and time.time() - t0 < 120:
        if parts.is_dir() and len(list(parts.glob("*.h5"))) >= 2:     # a few chunks written
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.05)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the extraction finished before it could be killed"
    p = Project.load(copy)
    db = database.load_database(p)
    t = localize.prepare_database(p, db, localize.LocalizeSettings(), ExecutorSettings("serial"))
    assert 0 < t["db_features_views"] < len(db.views)
    assert not parts.exists()      # the chunks folded into the feature file
    assert feature_store.stored_views(feats) == {v.name for v in db.views}
    assert localize.prepare_database(p, db, localize.LocalizeSettings(), ExecutorSettings("serial"))["db_features_views"] == 0
    # the global descriptors: a matrix apart (.npy), memory-mapped by each worker; a lost matrix is
    # made again from the kept codebook, the same
    t = localize.prepare_database(p, db, localize.LocalizeSettings(), ExecutorSettings("serial"))
    G = np.load(t["global_matrix"], mmap_mode="r")
    assert isinstance(G, np.memmap) and G.shape == (len(db.views), 64 * 128)
    with np.load(t["global"]) as z:
        assert "G" not in z.files and len(z["names"]) == len(db.views)
    before = np.asarray(G).copy()
    del G
    os.unlink(t["global_matrix"])
    t2 = localize.prepare_database(p, db, localize.LocalizeSettings(), ExecutorSettings("serial"))
    assert t2["db_features_views"] == 0 and np.array_equal(np.load(t2["global_matrix"]), before)
    ctx = localize._context({"root": str(copy), "settings": localize.settings_dict(localize.LocalizeSettings()),
                             "features": t2["features"], "global": t2["global"], "global_matrix": t2["global_matrix"]})
    assert isinstance(ctx["G"], np.memmap)


def test_database_views_and_features_only_for_the_views_the_queries_can_reach(site, tmp_path):
    """render-db renders, and localize extracts features for, only the views some query's sensor
    priors can bring within its top_k x (1 + fallback_rounds) (views and db_features "reachable",
    the defaults): every query ranks the same views, in the same order, and gets the same pose as
    with every view rendered and described; an ablation that reaches more views renders them."""
    from gtkit.project import Project

    copy = tmp_path / "site"
    shutil.copytree(site, copy, ignore=shutil.ignore_patterns("localize*", "reports"))
    serial = ExecutorSettings("serial")
    p = Project.load(copy)
    part = database.load_database(p)                  # the fixture's render-db: the views the queries reach
    planned = json.loads((copy / "work" / "render_db" / "views.json").read_text())["views"]
    assert 0 < len(part.views) and len(database.planned_not_rendered(p)) > 0.2 * len(planned)
    s = localize.LocalizeSettings(top_k=2, fallback_rounds=1)
    out_p = localize.run(copy, s, ablation="partial", executor=serial)
    rec_p = json.loads((out_p / "status.json").read_text())
    assert rec_p["database_views_rendered_for_this_run"] == 0
    # every view rendered, then features for the reachable ones only, then for all
    database.run(copy, replace(_db_settings(), views="all"), serial, localize_settings=None)
    db = database.load_database(p)
    assert len(db.views) > len(part.views) and not database.planned_not_rendered(p)
    out_r = localize.run(copy, s, ablation="reachable", executor=serial)
    rec_r = json.loads((out_r / "status.json").read_text())
    off = rec_r["offline"]
    assert off["db_views_total"] == len(db.views)
    assert 0 < off["db_views_described"] < 0.8 * len(db.views)
    feats = localize._db_cache(p, s) / "features.h5"
    assert len(feature_store.stored_views(feats)) < len(db.views)
    out_a = localize.run(copy, replace(s, db_features="all"), ablation="all-views", executor=serial)
    rec_a = json.loads((out_a / "status.json").read_text())
    assert rec_a["offline"]["db_views_described"] == len(db.views)
    assert len(feature_store.stored_views(feats)) == len(db.views)
    a = {q["name"]: q for q in rec_a["queries"]}
    assert sum(q["ok"] for q in a.values()) >= 6
    for other in (rec_r, rec_p):
        r = {q["name"]: q for q in other["queries"]}
        for n, q in a.items():
            assert q.get("retrieved") == r[n].get("retrieved")
            assert q.get("fallback_retrieved") == r[n].get("fallback_retrieved")
            assert q.get("t") == r[n].get("t") and q.get("q") == r[n].get("q") and q["reason"] == r[n]["reason"]


def test_an_ablation_that_reaches_more_views_renders_them(site, tmp_path):
    """GPS-denied and without the rotation prior, a query may rank every view: localize renders the
    planned views the project's render-db left out, and the database keeps them."""
    from gtkit.project import Project

    copy = tmp_path / "site"
    shutil.copytree(site, copy, ignore=shutil.ignore_patterns("localize*", "reports"))
    p = Project.load(copy)
    n0 = len(database.load_database(p).views)
    missing0 = len(database.planned_not_rendered(p))
    s = localize.settings_for("no-gps", localize.LocalizeSettings(query_subset="queries/seq1/0001_W.jpg",
                                                                 rotation_prior=False))
    out = localize.run(copy, s, ablation="no-gps", executor=ExecutorSettings("serial"))
    rec = json.loads((out / "status.json").read_text())
    assert 0 < rec["database_views_rendered_for_this_run"] <= missing0
    assert len(database.load_database(p).views) > n0
    assert len(database.planned_not_rendered(p)) == missing0 - rec["database_views_rendered_for_this_run"] == 0


def test_local_workers_end_when_the_process_that_started_them_is_killed(tmp_path):
    """A run killed with SIGKILL leaves no worker processes behind (they would sit idle for good)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    pids = tmp_path / "pids.txt"
    code = ("import os, time\n"
            "from gtkit.localize.executors import ExecutorSettings, make_executor\n"
            "ex = make_executor(ExecutorSettings('local', 2))\n"
            "got = list(ex.map(time.sleep, [0.5, 0.5]))\n"      # both workers started
            "w = [p.pid for p in ex._pool._processes.values()]\n"
            f"open({str(pids)!r}, 'w').write(' '.join(map(str, w)))\n"
            "time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    t0 = time.time()
    while not (pids.is_file() and pids.read_text()) and time.time() - t0 < 60:
        time.sleep(0.1)
    workers = [int(p) for p in pids.read_text().split()]
    assert len(workers) == 2
    proc.send_signal(signal.SIGKILL)
    proc.wait()

    def alive(pid):
        try:
            with open(f"/proc/{pid}/stat") as f:   # an exited child not yet reaped by its new parent: Z
                return f.read().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False

    t0 = time.time()
    while any(alive(p) for p in workers) and time.time() - t0 < 10:
        time.sleep(0.1)
    left = [p for p in workers if alive(p)]
    for p in left:
        os.kill(p, signal.SIGKILL)
    assert not left, f"workers still running {time.time() - t0:.0f} s after their parent was killed"


def test_localize_and_evaluate_against_truth(site):
    assert main(["localize", str(site), "--executor", "local", "--workers", "2"]) == 0
    assert main(["evaluate", str(site), "--what", "localization"]) == 0
    rep = json.loads((site / "reports" / "localization.json").read_text())
    assert rep["n_queries"] == 8 and rep["n_localized"] == 6
    assert rep["recall_1m1deg"] == pytest.approx(6 / 8)       # every land query within 1 m, 1 deg
    assert rep["median_pos_err_m"] < 0.3 and rep["median_rot_err_deg"] < 0.1
    assert rep["retrieval_R1"] >= 5 / 8
    reasons = {f["name"]: f["reason"] for f in rep["failures"]}
    assert set(reasons) == {WATER, OFF60}
    assert "no database view within 30 deg of the IMU prior" in reasons[OFF60]
    assert "no 2D-3D correspondences" in reasons[WATER] or "too few" in reasons[WATER]
    est = read_poses(site / "work" / "localize" / "poses.txt")
    assert WATER not in est and OFF60 not in est                 # failures are absent, never a prior
    md = (site / "reports" / "localization.md").read_text()
    assert "| matching |" in md and "| pnp |" in md


def test_a_pose_less_certain_than_the_limit_is_never_reported(site):
    status = json.loads((site / "work" / "localize" / "status.json").read_text())
    ok = {q["name"]: q["sigma_pos_m"] for q in status["queries"] if q["ok"]}
    name = min(ok, key=ok.get)
    assert ok[name] < 2.5            # the default limit passes what the default run reported
    limit = 0.5 * ok[name]           # a limit below this query's own sigma: its pose must not be reported
    s = localize.LocalizeSettings(query_subset=name, max_sigma_pos_m=limit,
                                  fallback_rounds=1)
    out = localize.run(site, s, ablation="sigma-limit", executor=ExecutorSettings("serial"))
    q = json.loads((out / "status.json").read_text())["queries"][0]
    assert not q["ok"] and "pose too uncertain" in q["reason"] and "fallback round" in q["reason"]
    assert len(q["rejected_poses"]) == 2 and all(r["sigma_pos_m"] > limit for r in q["rejected_poses"])
    assert read_poses(out / "poses.txt") == {}


def test_db_views_without_depth_fail_the_query_and_the_run_goes_on(site):
    status = json.loads((site / "work" / "localize" / "status.json").read_text())
    q = next(x for x in status["queries"] if x["name"] == "queries/seq1/0001_W.jpg")
    ddir = site / "work" / "render_db" / "depth"
    backup = site / "depth_backup"
    backup.mkdir(exist_ok=True)
    broken = [v for v, _s in q["retrieved"]]
    try:
        for v in broken:
            f = ddir / f"{v}.npz"
            shutil.copy(f, backup / v.replace("/", "_"))
            d = database.read_depth(f)
            database.write_depth(f, np.full_like(d, np.nan), 1.0)
        s = localize.LocalizeSettings(query_subset="queries/seq1/000[12]_W.jpg", fallback_rounds=0)
        out = localize.run(site, s, ablation="broken-depth", executor=ExecutorSettings("serial"))
        s1 = localize.LocalizeSettings(query_subset="queries/seq1/0001_W.jpg")  # default: one fallback round
        out1 = localize.run(site, s1, ablation="broken-depth-fallback", executor=ExecutorSettings("serial"))
    finally:
        for v in broken:
            shutil.copy(backup / v.replace("/", "_"), ddir / f"{v}.npz")
    res = {x["name"]: x for x in json.loads((out / "status.json").read_text())["queries"]}
    bad = res["queries/seq1/0001_W.jpg"]
    assert not bad["ok"] and "database view has no valid depth" in bad["reason"]
    assert all(v["problem"] == "database view has no valid depth" for v in bad["views"])
    assert res["queries/seq1/0002_W.jpg"]["ok"]
    # with the fallback the same query is localized from the next views, and the report says so
    fb = json.loads((out1 / "status.json").read_text())["queries"][0]
    assert fb["ok"] and fb["fallback_round"] == 1
    assert "database view has no valid depth" in fb["failed_rounds"][0]
    assert [v["view"] for v in fb["views"][:len(broken)]] == broken
    assert {v for v, _s in fb["fallback_retrieved"]}.isdisjoint(broken)
    truth = read_poses(site / "truth" / "poses.txt")["queries/seq1/0001_W.jpg"]
    got = read_poses(out1 / "poses.txt")["queries/seq1/0001_W.jpg"]
    m, deg = got.error_to(truth)
    assert m < 1.0 and deg < 1.0, (m, deg)


def test_dask_local_cluster_renders_and_localizes_like_local_processes(site):
    pytest.importorskip("dask.distributed")
    out = site / "work" / "render_db"
    vj = json.loads((out / "views.json").read_text())
    views = [v for v in vj["views"] if v["kept"]][:2]
    before = [database.read_depth(out / "depth" / f"{v['name']}.npz") for v in views]
    ex = make_executor(ExecutorSettings("dask", 2))   # two spawned worker processes, one GL context each
    try:
        from dataclasses import asdict

        fields = ("name", "height", "paper_pitch", "yaw", "pitch", "roll", "center")
        tasks = [(str(site), asdict(_db_settings()), [{k: v[k] for k in fields}], vj["ground_level_z"],
                  json.loads((out / "settings.json").read_text())) for v in views]
        res = run_map(ex, database._render_chunk, tasks)
    finally:
        ex.close()
    assert [r[0][0] for r in res] == [v["name"] for v in views]
    for v, d in zip(views, before):
        assert np.array_equal(database.read_depth(out / "depth" / f"{v['name']}.npz"), d, equal_nan=True)
    s = localize.LocalizeSettings(query_subset="queries/seq1/000[12]_W.jpg")
    o = localize.run(site, s, ablation="dask-check", executor=ExecutorSettings("dask", 2))
    a = read_poses(o / "poses.txt")
    b = read_poses(site / "work" / "localize" / "poses.txt")
    assert len(a) == 2
    for n, p in a.items():
        dp, dr = p.error_to(b[n])
        assert dp < 1e-6 and dr < 1e-6                            # same seeds, same answer


def test_ablation_without_rotation_prior_via_pipeline(site, capsys):
    from pipelines.localize import main as pipeline

    base = ["--executor", "serial"]
    assert pipeline([str(site), "--ablations", "no-rot-prior", *base]) == 0
    table = capsys.readouterr().out
    assert "| default |" in table and "| no-rot-prior |" in table
    rep = json.loads((site / "reports" / "localization-no-rot-prior.json").read_text())
    # without the prior the 60-deg-off query is no longer stopped by the filter; land queries still localize
    assert rep["recall_1m1deg"] >= 6 / 8
    assert OFF60 not in {f["name"]: 1 for f in rep["failures"]} or \
        "no database view within" not in {f["name"]: f["reason"] for f in rep["failures"]}[OFF60]


def test_tiled_model_renders_the_same_database_views(site):
    """A tiled copy of the model (issue 9's format) streams only the tiles a view sees and gives
    the same depth as the whole mesh."""
    from gtkit.io.mesh import load_model
    from gtkit.io.tiled import write_tiled
    from gtkit.localize.grid import View
    from gtkit.project import Project

    proj = Project.load(site)
    mesh = load_model(site / "model" / "reference.obj", proj.frame)
    write_tiled(mesh, site / "model" / "tiles", proj.frame.crs_spec, proj.frame.origin, tile_size=100.0)
    out = site / "work" / "render_db"
    fields = ("name", "height", "paper_pitch", "yaw", "pitch", "roll")
    kept = [v for v in json.loads((out / "views.json").read_text())["views"] if v["kept"]]
    views = [View(**{k: v[k] for k in fields}, center=tuple(v["center"])) for v in kept[::12][:5]]
    r = database.open_model(site, "model/tiles", proj.frame, tile_budget_mb=64)
    try:
        for v in views:
            d = database.render_view(r, database.db_camera(_db_settings()), v).depth
            ref = database.read_depth(out / "depth" / f"{v.name}.npz")
            both = np.isfinite(d) & np.isfinite(ref)
            assert both.mean() > 0.49 and (np.isfinite(d) == np.isfinite(ref)).mean() > 0.999
            assert np.abs(d[both] - ref[both]).max() < 0.02
            assert len(r.resident) < 12                      # only part of the 15 tiles is on the GPU
    finally:
        r.release()


def test_a_worker_of_a_stopped_or_superseded_run_writes_no_view(site):
    """render-db's workers check, before writing each view, that the database's settings.json is still
    the record their run planned under: the workers of a killed run (they go on without their parent)
    or of a run whose settings another run changed must not put views of another model into the folder
    (measured: a killed run's orphaned workers wrote 8 views into the next run's cleared database)."""
    from dataclasses import asdict

    out = site / "work" / "render_db"
    vj = json.loads((out / "views.json").read_text())
    v = next(v for v in vj["views"] if v["kept"])
    fields = ("name", "height", "paper_pitch", "yaw", "pitch", "roll", "center")
    record = json.loads((out / "settings.json").read_text())
    stale = {**record, "settings": {**record["settings"], "model": "model/another.obj"}}
    depth = out / "depth" / f"{v['name']}.npz"
    before = depth.stat().st_mtime_ns
    task = (str(site), asdict(_db_settings()), [{k: v[k] for k in fields}], vj["ground_level_z"], stale)
    with pytest.raises(GtkitError, match="settings changed while rendering"):
        database._render_chunk(task)
    assert depth.stat().st_mtime_ns == before
    # the current record renders and writes the view again, the same depth
    d0 = database.read_depth(depth)
    assert database._render_chunk(task[:4] + (record,))[0][0] == v["name"]
    assert np.array_equal(database.read_depth(depth), d0, equal_nan=True)


def test_render_db_and_localize_settings_come_from_the_command_line_then_project_toml(tmp_path, capsys):
    """`gtkit render-db` and `gtkit localize` resolve their settings like every stage: flag >
    project.toml [render_db] / [localize] > default (for localize, the ablation's settings first)."""
    from gtkit.geo import GeoFrame
    from gtkit.project import Project

    proj = Project.create(tmp_path / "site", GeoFrame("EPSG:32650", (500000.0, 3300000.0, 0.0)))
    root = str(proj.paths.root)
    proj.config["render_db"] = {"texture_detail": "sharp"}
    proj.save()
    assert main(["render-db", root]) == 2
    err = capsys.readouterr().err
    assert "texture_detail must be one of views, stored, got 'sharp'" in err and err.count("\n") == 1
    assert main(["render-db", root, "--texture-detail", "stored"]) == 2       # the flag wins: on to the model
    assert "reference model not found" in capsys.readouterr().err
    proj.config["render_db"] = {"heigths": [100.0]}
    proj.save()
    assert main(["render-db", root]) == 2
    assert "unknown setting render_db.heigths" in capsys.readouterr().err
    proj.config["localize"] = {"top_kk": 5}
    proj.save()
    assert main(["localize", root]) == 2
    assert "unknown setting localize.top_kk" in capsys.readouterr().err
