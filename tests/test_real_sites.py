"""What real photo sets bring, reproduced on the tiny sample site and measured against its truth:
photos without GPS, GCPs surveyed at one height, no focal length anywhere, check points, a block
that splits into several models; `gtkit init` from a folder of photos; settings from project.toml.

Each SfM here is the tiny preset (45 photos of 640x480): about a minute on 2 cores."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gtkit.cli import main as gtkit
from gtkit.errors import GtkitError
from gtkit.evaluate.poses import medians, pose_errors
from gtkit.geo import GeoFrame
from gtkit.io.odm import GCP, GCPClick
from gtkit.io.poses import read_intrinsics, read_poses
from gtkit.project import Project
from gtkit.settings import resolve
from gtkit.sfm.blocks import SfmSettings, run_reference
from gtkit.sfm.geometry import RegistrationError, robust_sim3
from gtkit.sfm.similarity import lo_ransac_similarity, umeyama
from gtkit.synth.variants import apply_variant
from conftest import stage_settings


def _variant(tiny_sample, tmp_path, *variants) -> Path:
    root = tmp_path / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    for v in variants:
        apply_variant(root, v)
    return root


def _errors(root: Path) -> dict:
    est, truth = read_poses(root / "work/sfm_reference/poses.txt"), read_poses(root / "truth/poses.txt")
    return medians(pose_errors(est, truth, [n for n in est if n in truth]))


# --- robust similarity: no coplanarity failure, metre-grade survey points kept -------------

def _random_sim(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    from scipy.spatial.transform import Rotation

    return 0.7, Rotation.from_quat(q).as_matrix(), np.array([500.0, -200.0, 30.0])


def test_similarity_from_coplanar_points_with_metre_noise_and_an_outlier():
    rng = np.random.default_rng(1)
    s, R, t = _random_sim(rng)
    tgt = np.c_[rng.uniform(-300, 300, (9, 2)), np.zeros(9)]          # every GCP at Z = 0
    src = ((tgt - t) @ R) / s                                          # exactly coplanar too
    noisy = tgt + rng.normal(0, 1.0, tgt.shape)                        # metre-grade coordinates
    noisy[4] += [40.0, 0.0, 0.0]                                       # and one gross mistake
    fit = robust_sim3(src, noisy, 5.0, adaptive=np.ones(9, bool))
    assert fit.inliers.sum() == 8 and not fit.inliers[4]
    err = np.linalg.norm(fit.tgt_from_src.matrix()[:, :3] - s * R)
    assert err < 0.02, err
    # a plain least-squares fit on the eight good points agrees
    ls = umeyama(src[fit.inliers], noisy[fit.inliers])
    assert abs(ls.scale - fit.tgt_from_src.scale) < 1e-9


def test_similarity_exact_and_degenerate():
    rng = np.random.default_rng(2)
    s, R, t = _random_sim(rng)
    src = rng.normal(size=(6, 3)) * 50
    tgt = s * src @ R.T + t
    fit = lo_ransac_similarity(src, tgt, np.full(6, 0.01))
    assert np.allclose(fit.sim.apply(src), tgt, atol=1e-6)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 0.0])
    with pytest.raises(RegistrationError, match="collinear"):
        robust_sim3(line, line * 2, 1.0)


def test_georegistration_errors_name_the_gcps():
    """Fewer than 3 usable GCPs: the message names each unusable GCP and why."""
    import pycolmap

    from gtkit.sfm.georegister import GeoregisterSettings, georegister

    gcps = [GCP(f"g{k}", np.array([k * 10.0, 0.0, 0.0]), [GCPClick("reference/a.jpg", 10, 10)]) for k in range(3)]
    with pytest.raises(RegistrationError, match=r"only 0 usable GCPs.*no GCP has 2 clicks in this model's 0 photos \(3 GCPs\)"):
        georegister(pycolmap.Reconstruction(), {}, gcps, GeoregisterSettings(use="gcp"))


# --- settings: flag > project.toml > default ----------------------------------------------

def test_settings_resolve_in_one_place(tmp_path):
    p = Project.create(tmp_path / "p", GeoFrame("EPSG:32650", (0.0, 0.0, 0.0)),
                       extra={"sfm": {"refine_intrinsics": "no", "features": {"max_num_features": 5000},
                                      "georegister": {"gcp_accuracy_m": 0.5, "checkpoints": ["gcp02"]}}})
    s = resolve(SfmSettings(), "sfm", Project.load(p.paths.root),
                {"features.max_num_features": 6000, "georegister.gps_inlier_m": None})
    assert s.refine_intrinsics == "no" and s.features.max_num_features == 6000
    assert s.georegister.gcp_accuracy_m == 0.5 and s.georegister.checkpoints == ["gcp02"]
    assert s.georegister.gps_inlier_m == SfmSettings().georegister.gps_inlier_m
    p.config["sfm"]["features"] = {"max_features": 1}
    p.save()
    with pytest.raises(GtkitError, match=r"project.toml: unknown setting sfm.features.max_features"):
        resolve(SfmSettings(), "sfm", Project.load(p.paths.root))
    p.config["sfm"] = {"refine_intrinsics": 3}
    p.save()
    with pytest.raises(GtkitError, match="must be a string"):
        resolve(SfmSettings(), "sfm", Project.load(p.paths.root))


def test_every_stage_command_reads_its_project_toml_section(tmp_path, capsys):
    """export, overlay and track resolve like sfm / register / model build / render-db / localize: a
    misspelt key in their project.toml section is refused by name, before any work."""
    p = Project.create(tmp_path / "p", GeoFrame("EPSG:32650", (0.0, 0.0, 0.0)))
    root = str(p.paths.root)
    for section, key, argv in (("export_dsm", "resolutoin", ["export", "dsm", root]),
                               ("export_ortho", "cogg", ["export", "ortho", root]),
                               ("export_mesh", "formats", ["export", "mesh", root]),
                               ("export_coordinates", "gcps", ["export", "coords", root]),
                               ("overlay", "max_sides", ["overlay", root]),
                               ("track", "foot", ["track", root])):
        p.config[section] = {key: 1}
        p.save()
        assert gtkit(argv) == 2, section
        err = capsys.readouterr().err
        assert f"unknown setting {section}.{key}" in err and err.count("\n") == 1, err
    p.config["export_dsm"] = {"fill_holes": 0, "cog": True}
    p.save()
    from gtkit.stages import settings_for

    s = settings_for("export_dsm", Project.load(root), {"resolution": 2.0, "cog": None, "fill_holes": None})
    assert (s.resolution, s.cog, s.fill_holes) == (2.0, True, 0)


# --- gtkit init -----------------------------------------------------------------------------

def test_init_makes_a_project_from_a_folder_of_photos(tiny_sample, tmp_path, capsys):
    src = _variant(tiny_sample, tmp_path, "no-gps")
    gcp = src / "gcp_list.txt"
    lines = gcp.read_text().splitlines()
    lines.append(lines[1].replace("reference/", "").replace(lines[1].split()[5].split("/")[-1], "missing_photo.jpg"))
    gcp.write_text("\n".join(lines) + "\n")
    dst = tmp_path / "new"
    assert gtkit(["init", str(dst), "--reference", str(src / "images/reference"), "--queries",
                  str(src / "images/queries/seq1"), str(src / "images/queries/seq2"), "--gcp", str(gcp)]) == 0
    out = capsys.readouterr().out
    assert "CRS EPSG:32650 (from gcp_list.txt (first line))" in out
    assert "reference photos: 45 (640x480); GPS 0" in out and "EXIF focal 45" in out
    assert "query sequence seq1: 8 photos (4 wide *_W, 4 zoom *_Z)" in out
    assert "GCPs: 4 with" in out and "missing_photo.jpg" in out
    assert "45 reference photos have no GPS" in out
    proj = Project.load(dst)
    assert proj.frame.crs_spec == "EPSG:32650"
    # origin at the data's centroid: the GCPs sit within the site around it
    from gtkit.io.odm import read_gcp_list

    xyz = np.array([g.xyz for g in read_gcp_list(proj.paths.gcp_list, proj.frame)])
    assert np.all(np.abs(xyz[:, :2]) < 150)
    assert len(list(proj.paths.reference_images.iterdir())) == 45
    assert (proj.paths.query_images / "seq2" / "0001_Z.jpg").is_symlink()
    # a second init into the same folder, and a folder without any way to decide the CRS, are refused
    assert gtkit(["init", str(dst), "--reference", str(src / "images/reference")]) == 2
    assert gtkit(["init", str(tmp_path / "x"), "--reference", str(src / "images/reference")]) == 2
    err = capsys.readouterr().err
    assert "already a gtkit project" in err and "cannot decide the project's CRS" in err
    assert not (tmp_path / "x").exists()


# --- end to end on variants -----------------------------------------------------------------

def test_no_gps_gcps_at_one_height(tiny_sample, tmp_path):
    """No GPS in any photo, every GCP at one height: retrieval pairs register every photo; the
    GCP-only georegistration succeeds (pycolmap's estimator returns None here) and reports the
    GCPs' metre-grade residuals. Measured (seeds 0-2): 45/45, GCP median 0.4-0.6 m."""
    root = _variant(tiny_sample, tmp_path, "no-gps", "flat-gcps")
    # project.toml settings reach the stage: retrieval pairs instead of exhaustive past 30 photos
    proj = Project.load(root)
    proj.config["sfm"] = {"matching": {"exhaustive_max_without_gps": 30, "retrieval_neighbors": 15}}
    proj.save()
    r = run_reference(root, stage_settings("sfm_reference", root))
    assert r["n_registered"] / r["n_images"] >= 0.93 and r["n_models"] == 1
    assert r["pairings"] == ["retrieval"] and r["n_gps"] == 0 and r["n_pairs"] < 45 * 44 / 2
    geo = r["georegistration"]
    assert geo["n_gps"] == 0 and geo["n_gcp_in_fit"] == 4 and geo["n_inliers"] == 4
    assert geo["gcp_median_err_m"] < 1.5
    rep = json.loads((root / "reports/reference.json").read_text())
    for k in ("n_images", "n_registered", "n_models", "mean_reproj_px", "intrinsics", "seconds"):
        assert k in rep
    for k in ("used", "n_inliers", "rmse_m", "gcp_median_err_m", "gcp_rmse_m", "checkpoint_median_err_m"):
        assert k in rep["georegistration"]
    e = _errors(root)
    assert e["median_pos_err_m"] < 3.0  # the GCPs' own heights are ~1 m off


def test_no_focal_self_calibrates_and_checkpoints_are_reported(tiny_sample, tmp_path):
    """No cameras.txt and no EXIF focal: focal and principal point are estimated; check points
    stay out of the fit and are reported apart."""
    root = _variant(tiny_sample, tmp_path, "no-focal", "checkpoints")
    r = run_reference(root, stage_settings("sfm_reference", root))
    assert r["n_registered"] == r["n_images"]
    truth = read_intrinsics(root / "truth/intrinsics.txt")
    f_true = np.median([c.fx for n, c in truth.items() if n.startswith("reference/")])
    cams = read_intrinsics(root / "work/sfm_reference/intrinsics.txt")
    f = np.median([c.fx for c in cams.values()])
    assert abs(f / f_true - 1) < 0.01, (f, f_true)
    (cam,) = r["intrinsics"].values()
    assert cam["refined"] == ["focal", "principal point", "distortion"]
    e = _errors(root)
    assert e["median_pos_err_m"] < 0.06 and e["median_rot_err_deg"] < 0.05, e
    geo = r["georegistration"]
    checks = {n for n, g in geo["gcp_residuals"].items() if g.get("check")}
    assert len(checks) == 2 and geo["n_gcp_in_fit"] == 2 and geo["n_checkpoints"] == 2
    assert not any(geo["gcp_residuals"][n]["in_fit"] for n in checks)
    assert geo["checkpoint_median_err_m"] is not None and geo["checkpoint_median_err_m"] < 0.5


def test_models_placed_in_the_world_are_merged_with_their_points():
    """Two models of one block (disjoint photos, image ids from one database), already in one frame:
    the merged block holds every photo at its pose and every 3D point with its track."""
    import pycolmap

    from gtkit.camera import Camera
    from gtkit.pose import Pose
    from gtkit.sfm.blocks import merge_models
    from gtkit.sfm.geometry import model_poses

    rng = np.random.default_rng(0)
    cam = Camera.pinhole(800, 600, 700.0)
    X = np.c_[rng.uniform(-40, 40, (300, 2)), rng.uniform(0, 5, 300)]
    models, all_poses = [], {}
    for part, (x0, ids) in enumerate(((-30.0, range(1, 5)), (30.0, range(5, 8)))):
        rec = pycolmap.Reconstruction()
        c = cam.to_pycolmap()
        c.camera_id = 1
        rec.add_camera_with_trivial_rig(c)
        tracks = {}
        for k, iid in enumerate(ids):
            pose = Pose.from_dji(0.0, -90.0, 0.0, [x0 + 8.0 * k, 0.0, 80.0])
            all_poses[f"reference/p{iid}.jpg"] = pose
            uv, ok = cam.project(pose.transform(X))
            ok &= cam.in_image(uv, 2)
            idx = np.flatnonzero(ok)
            for j, i in enumerate(idx):
                tracks.setdefault(i, []).append((iid, j))
            rec.add_image_with_trivial_frame(pycolmap.Image(name=f"reference/p{iid}.jpg", keypoints=uv[idx],
                                                            camera_id=1, image_id=iid), pose.to_pycolmap())
        for i, tr in tracks.items():
            if len(tr) >= 2:
                rec.add_point3D(X[i], pycolmap.Track([pycolmap.TrackElement(a, b) for a, b in tr]))
        models.append(rec)
    n_points = sum(m.num_points3D() for m in models)
    merged = merge_models(models)
    assert merged.num_reg_images() == 7 and merged.num_points3D() == n_points
    got = model_poses(merged)
    assert all(np.allclose(got[n].matrix, p.matrix, atol=1e-9) for n, p in all_poses.items())
    assert merged.compute_mean_reprojection_error() < 1e-6


def test_nadir_heldout_variant_is_a_mapping_flight_with_photos_held_out(tiny_sample, tmp_path):
    """``nadir-heldout`` (the hidden real site of issue 33: a nadir flight, every 5th photo held out
    as a query): only nadir reference photos stay, every 5th of them from the 3rd is a query of
    ``queries/heldout`` with its true pose under the new name, the sample's own sequences, clicks
    and cameras.txt are gone, and the project's query setting takes every photo (as init writes it)."""
    from gtkit.queries import query_photos

    before = read_poses(tiny_sample[0] / "truth/poses.txt")
    root = _variant(tiny_sample, tmp_path, "nadir-heldout")
    refs = sorted(p.name for p in (root / "images/reference").iterdir())
    nadir = sorted(n.split("/")[-1] for n in before if n.startswith("reference/") and n.endswith("_N.jpg"))
    held = nadir[2::5]
    assert held and refs == sorted(set(nadir) - set(held))
    assert sorted(p.name for p in (root / "images/queries").rglob("*.jpg")) == held
    assert not (root / "tiepoints.json").exists() and not (root / "cameras.txt").exists()
    truth = read_poses(root / "truth/poses.txt")
    for n in held:
        q = truth[f"queries/heldout/{n}"]
        assert np.allclose(q.center, before[f"reference/{n}"].center)
    assert sorted(query_photos(Project.load(root))) == [f"queries/heldout/{n}" for n in held]
