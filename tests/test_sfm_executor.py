"""The reference SfM's feature extraction and matching as tasks on a Dask LocalCluster write the same
database as the in-process run, and the mapper then gives the same poses."""
import shutil

import numpy as np
import pycolmap
import pytest

from gtkit.io.poses import read_poses
from gtkit.localize.executors import ExecutorSettings
from gtkit.sfm.blocks import SfmSettings, run_reference

pytest.importorskip("dask.distributed")


def _database(root):
    with pycolmap.Database.open(root / "work/sfm_reference/database.db") as db:
        ims = {im.image_id: im for im in db.read_all_images()}
        names = {i: im.name for i, im in ims.items()}

        def pair(pid):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            return names[a], names[b]

        pid, ms = db.read_all_matches()
        gid, gs = db.read_two_view_geometries()
        return {"ids": {im.name: (i, im.camera_id) for i, im in ims.items()},
                "cameras": {c.camera_id: (c.model.name, tuple(c.params)) for c in db.read_all_cameras()},
                "keypoints": {im.name: np.asarray(db.read_keypoints(i)) for i, im in ims.items()},
                "descriptors": {im.name: np.asarray(db.read_descriptors(i).data) for i, im in ims.items()},
                "matches": {pair(p): np.asarray(m) for p, m in zip(pid, ms)},
                "geometries": {pair(p): (int(g.config), np.asarray(g.inlier_matches)) for p, g in zip(gid, gs)}}


def test_features_and_matching_on_a_dask_cluster_give_the_local_database_and_poses(tiny_sample, tmp_path):
    src = tiny_sample[0]
    s = SfmSettings()
    s.features.max_image_size = 400      # test-sized: the tiny sample's 45 photos at 400 px, 600 keypoints
    s.features.max_num_features = 600
    # mapper and BA on one thread: on 2 threads the same database gave camera centres 2.7e-7 m apart in
    # one CI run and 5.8 mm in another (thread order); on one thread 0 m, twice
    s.num_threads = 1
    roots, summaries = {}, {}
    for kind, ex in (("here", None), ("dask", ExecutorSettings("dask", 2))):
        roots[kind] = tmp_path / kind
        shutil.copytree(src, roots[kind], ignore=shutil.ignore_patterns("work", "exports", "reports", "model", "queries"))
        summaries[kind] = run_reference(roots[kind], s, executor=ex)
    a, b = _database(roots["here"]), _database(roots["dask"])
    assert a["ids"] == b["ids"] and a["cameras"] == b["cameras"]
    assert sum(len(k) for k in a["keypoints"].values()) > 45 * 300
    for n in a["keypoints"]:
        assert np.array_equal(a["keypoints"][n], b["keypoints"][n]) and np.array_equal(a["descriptors"][n], b["descriptors"][n])
    assert len(a["matches"]) > 100 and a["matches"].keys() == b["matches"].keys()
    assert all(np.array_equal(a["matches"][k], b["matches"][k]) for k in a["matches"])
    assert a["geometries"].keys() == b["geometries"].keys()
    assert all(a["geometries"][k][0] == b["geometries"][k][0] and np.array_equal(a["geometries"][k][1], b["geometries"][k][1])
               for k in a["geometries"])
    # same registration, same camera centres
    pa, pb = (read_poses(roots[k] / "work/sfm_reference/poses.txt") for k in ("here", "dask"))
    assert summaries["here"]["n_registered"] == summaries["dask"]["n_registered"] == 45 and pa.keys() == pb.keys()
    diff = max(float(np.linalg.norm(pa[n].center - pb[n].center)) for n in pa)
    print(f"dask vs in-process: {len(a['matches'])} matched pairs identical, max camera-centre difference {diff:.2e} m")
    assert diff < 1e-5


def test_an_unknown_mapper_is_one_clear_error_before_any_work(tiny_sample, tmp_path):
    from gtkit.errors import GtkitError
    from gtkit.project import Project

    root = tmp_path / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "exports", "reports", "model", "queries"))
    proj = Project.load(root)
    proj.config.setdefault("sfm", {})["mapper"] = "glomap"
    proj.save()
    with pytest.raises(GtkitError, match="unknown sfm.mapper 'glomap' \\(choose from incremental, global, auto\\)"):
        run_reference(root)
    assert not (root / "work/sfm_reference/database.db").exists()
