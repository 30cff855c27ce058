"""``gtkit export dataset`` (issue 56): the pseudo-GT as kapture, COLMAP and hloc files that their own
readers read back, a sidecar with sigma and covariance, unverified / refused photos kept out, a
datasheet, atomic writes and a no-op re-export; ``gtkit import poses`` reads each format back.

The project is the tiny sample with a pseudo-GT written by the test (the true poses moved by a few
centimetres, with covariances), so the export is tested on known numbers without the SfM; its render
database is real (``gtkit render-db``, a tiny grid). The real chain (the main job, then the export) is
``tests/test_evaluate_results.py``'s slow test; the figures on small seeds 0-2 and Brighton are in the
issue note."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import DEMO_DB_ARGS, ROOT
from gtkit.cli import main as gtkit
from gtkit.io.poses import read_covariances, read_intrinsics, read_poses, write_covariances, write_intrinsics, write_poses
from gtkit.io.atomic import write_json
from gtkit.pose import Pose

UNVERIFIED = "queries/seq3/0003_W.jpg"      # registered, no covariance
REFUSED = "queries/seq1/0004_W.jpg"         # review.json: reject
NOT_REGISTERED = "queries/seq2/0003_W.jpg"  # not in the pose file
VAGUE = "queries/seq2/0002_W.jpg"           # sigma 1 m per axis: 2-sigma beyond (1 m, 1°) and (3 m, 3°)


def small_rotation(rng, deg):
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    return Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()


def fake_pseudo_gt(root: Path) -> dict[str, Pose]:
    """work/register/ as gtkit register writes it: the true wide poses moved by ~3 cm / 0.01 deg."""
    truth, intr = read_poses(root / "truth" / "poses.txt"), read_intrinsics(root / "truth" / "intrinsics.txt")
    rng = np.random.default_rng(56)
    wide = sorted(n for n in truth if n.endswith("_W.jpg") and n != NOT_REGISTERED)
    poses = {}
    for n in wide:
        R = small_rotation(rng, 0.01) @ truth[n].R
        poses[n] = Pose.from_center(R, truth[n].center + rng.normal(scale=0.03, size=3))
    d = root / "work" / "register"
    write_poses(d / "poses.txt", poses, header="pseudo-GT poses of the query photos (test)")
    write_intrinsics(d / "intrinsics.txt", {n: intr[n] for n in wide})
    covs = {n: np.diag([(2e-4) ** 2] * 3 + [0.03 ** 2] * 3) for n in wide if n != UNVERIFIED}
    covs[VAGUE] = np.diag([(2e-4) ** 2] * 3 + [1.0] * 3)
    write_covariances(d / "covariances.txt", covs)
    images = {n: {"sequence": n.split("/")[1]} for n in wide}
    images[UNVERIFIED]["unverified"] = "its sequence's BA is undetermined (test)"   # as gtkit register says it
    write_json(d / "registration.json", {"n_registered": len(wide) - 1, "n_unverified": 1, "images": images,
                                         "sequences": {q: {"status": "registered", "registered_by": "automatic matches"}
                                                       for q in ("seq1", "seq2", "seq3")}})
    write_json(root / "review.json", {"format": "gtkit-review", "version": 1, "images": {REFUSED: {"status": "reject"}}})
    from gtkit.track.rig import Rig, ZoomSetting

    tr = json.loads((root / "truth" / "rig.json").read_text())
    zoom = next(n for n in sorted(intr) if n.endswith("_Z.jpg"))
    R = np.array(tr["R"])
    Rig(R, -R.T @ np.array(tr["t"]), [ZoomSetting(intr[zoom], None)]).save(root / "work" / "rig" / "rig.json")
    return poses


@pytest.fixture(scope="module")
def site(tiny_sample, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("dataset") / "site"
    shutil.copytree(tiny_sample[0], root)
    fake_pseudo_gt(root)
    assert gtkit(["render-db", str(root), *DEMO_DB_ARGS]) == 0
    return root


@pytest.fixture(scope="module")
def exported(site) -> Path:
    out = site.parent / "published"
    assert gtkit(["export", "dataset", str(site), str(out)]) == 0
    return out


def published_names(site) -> list[str]:
    poses = read_poses(site / "work" / "register" / "poses.txt")
    return sorted(n for n in poses if n not in (UNVERIFIED, REFUSED))


def test_kapture_loader_reads_back_poses_intrinsics_rig_gnss_and_depth(site, exported):
    import kapture
    import kapture.io.csv as kcsv
    from kapture.io.records import depth_map_from_file, get_depth_map_fullpath

    from gtkit.conventions import quat_to_rotmat
    from gtkit.io.exif import read_photo_meta
    from gtkit.localize.database import load_database, read_depth
    from gtkit.project import Project
    from gtkit.track.rig import Rig

    gt = read_poses(site / "work" / "register" / "poses.txt")
    intr = read_intrinsics(site / "work" / "register" / "intrinsics.txt")
    k = kcsv.kapture_from_dir(str(exported / "kapture" / "query"))
    wide = {name: (ts, sid) for ts, sid, name in kapture.flatten(k.records_camera) if name.endswith("_W.jpg")}
    assert sorted(wide) == published_names(site)
    for name, (ts, sid) in wide.items():
        p = k.trajectories[ts, sid]
        assert np.abs(quat_to_rotmat(p.r_raw) - gt[name].R).max() < 1e-9
        assert np.abs(np.array(p.t_raw) - gt[name].t).max() < 1e-9
        w, h, *params = k.sensors[sid].camera_params
        assert (k.sensors[sid].camera_type.name, int(w), int(h), tuple(params)) == (
            intr[name].model, intr[name].width, intr[name].height, intr[name].params)
        g = k.records_gnss[ts, "gnss"]
        m = read_photo_meta(site / "images" / name)
        assert (g.x, g.y, g.z) == (m.lon, m.lat, m.altitude)
    rig = Rig.load(site / "work" / "rig" / "rig.json")
    zooms = {name: sid for _ts, sid, name in kapture.flatten(k.records_camera) if name.endswith("_Z.jpg")}
    assert sorted(zooms) == [n.replace("_W.", "_Z.") for n in published_names(site)]
    zoom_from_wide = k.rigs["uav", next(iter(zooms.values()))]
    assert np.abs(quat_to_rotmat(zoom_from_wide.r_raw) - rig.R_zw).max() < 1e-12
    assert np.abs(np.array(zoom_from_wide.t_raw) + rig.R_zw @ rig.offset).max() < 1e-12
    m = kcsv.kapture_from_dir(str(exported / "kapture" / "mapping"))
    db = load_database(Project.load(site))
    depths = {name: ts for ts, _sid, name in kapture.flatten(m.records_depth)}
    assert len(depths) == len(db.views) > 0
    for v in db.views:
        dm = depth_map_from_file(get_depth_map_fullpath(str(exported / "kapture" / "mapping"), f"render_db/{v.name}.depth"),
                                 (db.camera.width, db.camera.height))
        assert np.array_equal(dm, np.nan_to_num(read_depth(v.depth_path), nan=0.0))
        p = m.trajectories[depths[f"render_db/{v.name}.depth"], "render_depth"]
        assert np.abs(np.array(p.t_raw) - v.pose.t).max() < 1e-9
    ref = read_poses(site / "work" / "sfm_reference" / "poses.txt") if (site / "work" / "sfm_reference").is_dir() else {}
    assert sum(1 for _ in kapture.flatten(m.records_camera)) == len(db.views) + len(ref)


def test_colmap_model_and_hloc_files_read_back(site, exported):
    import pycolmap

    gt = read_poses(site / "work" / "register" / "poses.txt")
    rec = pycolmap.Reconstruction(str(exported / "colmap" / "queries"))
    assert sorted(im.name for im in rec.images.values()) == published_names(site)
    for im in rec.images.values():
        cfw = im.cam_from_world()
        assert np.abs(cfw.rotation.matrix() - gt[im.name].R).max() < 1e-9
        assert np.abs(np.asarray(cfw.translation) - gt[im.name].t).max() < 1e-9
    hloc = read_poses(exported / "hloc" / "pseudo_gt_poses.txt")
    assert sorted(hloc) == published_names(site)
    assert max(max(np.abs(hloc[n].R - gt[n].R).max(), np.abs(hloc[n].t - gt[n].t).max()) for n in hloc) < 1e-12
    from gtkit.dataset.formats import read_uncertainty

    unc = read_uncertainty(exported / "pseudo_gt_uncertainty.txt")
    covs = read_covariances(site / "work" / "register" / "covariances.txt")
    assert sorted(unc) == published_names(site)
    for n, (sp, sr, c) in unc.items():
        assert np.array_equal(c, covs[n])
        assert sp == pytest.approx(np.sqrt(np.trace(Pose(gt[n].R, gt[n].t, c).center_covariance())), rel=1e-12)
        assert sr == pytest.approx(np.degrees(np.sqrt(np.trace(c[:3, :3]))), rel=1e-12)


def test_unverified_refused_and_unregistered_photos_are_kept_out_and_listed(exported):
    from gtkit.dataset.formats import read_kept_out

    kept = read_kept_out(exported / "kept_out.txt")
    assert {n: k for n, (k, _why) in kept.items()} == {UNVERIFIED: "unverified", REFUSED: "refused",
                                                       NOT_REGISTERED: "not registered"}
    assert "its sequence's BA is undetermined (test)" in kept[UNVERIFIED][1]
    sheet = json.loads((exported / "dataset.json").read_text())
    assert sheet["pseudo_gt"]["n_published"] == 7 and sheet["pseudo_gt"]["n_kept_out"] == 3
    assert sheet["pseudo_gt"]["photos_that_can_judge"] == {"1m1deg": 6, "3m3deg": 6, "5m5deg": 7}
    for f in ("hloc/pseudo_gt_poses.txt", "kapture/query/sensors/records_camera.txt", "colmap/queries/images.txt",
              "pseudo_gt_uncertainty.txt"):
        body = (exported / f).read_text()
        assert not any(n in body for n in kept), f
    md = (exported / "DATASET.md").read_text()
    assert "## Evaluation protocol" in md and "(1 m, 1°) 6 of 7" in md
    assert (exported / "plots" / "trajectories.jpg").stat().st_size > 10_000
    assert (exported / "plots" / "sigma.png").stat().st_size > 10_000


def test_import_poses_reads_each_format_back(site, exported, tmp_path):
    root = tmp_path / "site"
    shutil.copytree(site, root, symlinks=True)
    gt = read_poses(root / "work" / "register" / "poses.txt")
    covs = read_covariances(root / "work" / "register" / "covariances.txt")
    for src in ("hloc/pseudo_gt_poses.txt", "colmap/queries", "kapture/query"):
        assert gtkit(["import", "poses", str(root), str(exported / src)]) == 0, src
        got = read_poses(root / "work" / "import" / "poses.txt")
        assert sorted(got) == published_names(site), src
        worst = max(max(np.abs(got[n].R - gt[n].R).max(), np.abs(got[n].t - gt[n].t).max()) for n in got)
        assert worst < 1e-9, (src, worst)
        imported = read_covariances(root / "work" / "import" / "covariances.txt")
        assert sorted(imported) == sorted(got) and all(np.array_equal(imported[n], covs[n]) for n in got)
        cams = read_intrinsics(root / "work" / "import" / "intrinsics.txt")
        assert all(cams[n] == read_intrinsics(root / "work" / "register" / "intrinsics.txt")[n] for n in got)
    ds = tmp_path / "ds"         # a method's result kept inside the dataset folder: no pseudo-GT covariance for it
    shutil.copytree(exported, ds, symlinks=True)
    (ds / "mine").mkdir()
    shutil.copy(ds / "hloc" / "pseudo_gt_poses.txt", ds / "mine" / "poses.txt")
    assert gtkit(["import", "poses", str(root), str(ds / "mine" / "poses.txt"), "--intrinsics",
                  str(ds / "hloc" / "queries_with_intrinsics.txt")]) == 0
    assert not (root / "work" / "import" / "covariances.txt").exists()


def test_reexport_of_an_unchanged_project_writes_nothing(site, exported, capsys):
    before = {p: p.lstat().st_mtime_ns for p in exported.rglob("*")}
    assert gtkit(["export", "dataset", str(site), str(exported)]) == 0
    assert "up to date" in capsys.readouterr().out
    assert {p: p.lstat().st_mtime_ns for p in exported.rglob("*")} == before


def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gtkit.cli", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "GTKIT_NO_CHILD": "1"})


def one_line(r) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout[-500:], r.stderr[-2000:])
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def test_bad_input_is_one_line_and_nothing_is_half_written(site, exported, tiny_sample, tmp_path):
    bare = tmp_path / "bare"     # the sample as generated: no pseudo-GT (a copy: the command takes its lock)
    shutil.copytree(tiny_sample[0], bare, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    line = one_line(run_cli("export", "dataset", bare, tmp_path / "a"))
    assert "work/register/poses.txt" in line and "no pseudo-GT" in line, line
    assert not (tmp_path / "a").exists()
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    line = one_line(run_cli("export", "dataset", site, other))
    assert str(other) in line and "holds something else" in line, line
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
    (tmp_path / "r.csv").write_text("name,x\n")
    line = one_line(run_cli("evaluate", "results", exported, tmp_path / "r.csv"))
    assert "r.csv" in line and "unknown results format" in line, line
    stranger = tmp_path / "stranger.txt"
    stranger.write_text((exported / "hloc" / "pseudo_gt_poses.txt").read_text() + "queries/seq9/0001_W.jpg 1 0 0 0 0 0 0\n")
    line = one_line(run_cli("evaluate", "results", exported, stranger))
    assert "stranger.txt" in line and "queries/seq9/0001_W.jpg" in line, line
    assert not list(tmp_path.glob(".*partial*")) and not list(site.parent.glob(".*partial*"))


def test_a_failed_export_leaves_the_previous_dataset_whole(site, exported, monkeypatch, tmp_path):
    from gtkit.dataset import datasheet
    from gtkit.dataset.stage import DatasetSettings, run
    from gtkit.errors import GtkitError

    out = tmp_path / "ds"
    run(site, out, DatasetSettings(formats=("hloc",)))
    before = sorted(p.relative_to(out) for p in out.rglob("*"))

    def broken(*_a, **_k):
        raise GtkitError("disk full (test)")

    monkeypatch.setattr(datasheet, "plots", broken)
    with pytest.raises(GtkitError):
        run(site, out, DatasetSettings(formats=("hloc", "colmap")))
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert not list(tmp_path.glob(".*partial*"))


def test_without_depth_the_mapping_has_the_views_alone(site, tmp_path):
    import kapture
    import kapture.io.csv as kcsv

    out = tmp_path / "nodepth"
    assert gtkit(["export", "dataset", str(site), str(out), "--format", "kapture", "--no-depth"]) == 0
    m = kcsv.kapture_from_dir(str(out / "kapture" / "mapping"))
    assert m.records_depth is None and "render_depth" not in m.sensors
    assert sum(1 for _ in kapture.flatten(m.records_camera)) > 0
    assert not list(out.rglob("*.depth")) and not (out / "hloc").exists() and not (out / "colmap").exists()
    assert json.loads((out / "dataset.json").read_text())["parts"]["kapture_mapping"]["n_depth_maps"] == 0


def test_protocol_thresholds_are_the_localization_reports():
    from gtkit.evaluate.poses import THRESHOLDS
    from gtkit.dataset.datasheet import THRESHOLDS as SHEET

    assert SHEET == THRESHOLDS
