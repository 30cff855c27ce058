"""``gtkit evaluate results`` (issue 56): any method's poses (hloc, kapture, COLMAP) scored against the
pseudo-GT; known offsets are reported as such; the sigma-aware table counts the photos each threshold
can judge; against truth/ it gives the localization report's figures exactly.

The project is the tiny sample with a test-written pseudo-GT (:func:`test_export_dataset.fake_pseudo_gt`).
GTKIT_SLOW=1 adds the real chain on the tiny sample: the main job, then the export and the scoring."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT
from gtkit.cli import main as gtkit
from gtkit.evaluate.results import evaluate_results
from gtkit.io.poses import read_poses, write_poses
from gtkit.pose import Pose
from test_export_dataset import REFUSED, UNVERIFIED, VAGUE, fake_pseudo_gt, small_rotation

SLOW = os.environ.get("GTKIT_SLOW") == "1"


@pytest.fixture(scope="module")
def site(tiny_sample, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("results") / "site"
    shutil.copytree(tiny_sample[0], root)
    fake_pseudo_gt(root)
    return root


def published(site) -> dict[str, Pose]:
    return {n: p for n, p in read_poses(site / "work" / "register" / "poses.txt").items() if n not in (UNVERIFIED, REFUSED)}


def perturbed(ref: dict[str, Pose], shifts: dict[str, np.ndarray], degs: dict[str, float], seed=1) -> dict[str, Pose]:
    """Each pose's centre moved by ``shifts[n]`` and its rotation turned by ``degs[n]`` about a random axis."""
    rng = np.random.default_rng(seed)
    return {n: Pose.from_center(small_rotation(rng, degs[n]) @ p.R, p.center + shifts[n]) for n, p in ref.items()}


def known_offsets(names):
    rng = np.random.default_rng(7)
    dist = dict(zip(names, [0.2, 0.9, 1.5, 2.5, 3.5, 4.5, 7.0]))
    degs = dict(zip(names, [0.1, 0.5, 0.8, 2.0, 2.5, 6.0, 0.3]))
    dirs = {n: (v := rng.normal(size=3)) / np.linalg.norm(v) for n in names}
    return {n: dist[n] * dirs[n] for n in names}, dist, degs


def test_a_perturbed_result_reports_its_offsets_in_every_format(site, tmp_path):
    ref = published(site)
    names = sorted(ref)
    shifts, dist, degs = known_offsets(names)
    est = perturbed(ref, shifts, degs)
    f = tmp_path / "method" / "poses.txt"
    write_poses(f, est)
    rep = evaluate_results(site, f, out_dir=tmp_path / "rep")
    for n in names:
        e = rep["per_photo"][n]
        assert abs(e["pos_err_m"] - dist[n]) < 1e-9 and abs(e["rot_err_deg"] - degs[n]) < 1e-9, (n, e)
    expect = {(m, d): sum(1 for n in names if dist[n] <= m and degs[n] <= d) / 7 for m, d in ((1, 1), (3, 3), (5, 5))}
    assert (rep["recall_1m1deg"], rep["recall_3m3deg"], rep["recall_5m5deg"]) == tuple(expect.values())
    assert rep["median_pos_err_m"] == pytest.approx(np.median(list(dist.values())), abs=1e-9)
    # sigma-aware: VAGUE's 2-sigma (3.46 m) is beyond (1 m, 1°) and (3 m, 3°): six photos judge those
    rows = {(r["threshold_m"], r["threshold_deg"]): r for r in rep["sigma_aware"]}
    assert [rows[t]["n_can_judge"] for t in ((1, 1), (3, 3), (5, 5))] == [6, 6, 7]
    judged = [n for n in names if n != VAGUE]
    assert rows[(1, 1)]["n_pass"] == sum(1 for n in judged if dist[n] <= 1 and degs[n] <= 1)
    md = Path(rep["markdown"]).read_text()
    assert "| (1 m, 1°) | 6 | 1 |" in md and Path(rep["plot"]).stat().st_size > 10_000
    # the same result as a COLMAP model and as a kapture folder: the same figures
    from gtkit.io.colmap_model import write_colmap_model
    from gtkit.io.poses import read_intrinsics

    cams = read_intrinsics(site / "work" / "register" / "intrinsics.txt")
    write_colmap_model(tmp_path / "colmap", est, {n: cams[n] for n in est}, binary=True)
    write_kapture(tmp_path / "kapture", est, cams)
    for other in (tmp_path / "colmap", tmp_path / "kapture"):
        r2 = evaluate_results(site, other, out_dir=tmp_path / "rep2")
        for n in names:
            assert abs(r2["per_photo"][n]["pos_err_m"] - dist[n]) < 1e-9, other
            assert abs(r2["per_photo"][n]["rot_err_deg"] - degs[n]) < 1e-9, other


def write_kapture(folder: Path, poses: dict[str, Pose], cams) -> None:
    import kapture
    import kapture.io.csv as kcsv

    k = kapture.Kapture(sensors=kapture.Sensors(), trajectories=kapture.Trajectories(), records_camera=kapture.RecordsCamera())
    for i, n in enumerate(sorted(poses)):
        c = cams[n]
        k.sensors[f"cam{i}"] = kapture.Camera(c.model, [c.width, c.height, *c.params])
        k.trajectories[i, f"cam{i}"] = kapture.PoseTransform(poses[n].q, poses[n].t)
        k.records_camera[i, f"cam{i}"] = n
    kcsv.kapture_to_dir(str(folder), k)


def test_a_constant_shift_is_the_mean_offset_and_missing_or_kept_out_photos_count_right(site, tmp_path):
    ref = published(site)
    names = sorted(ref)
    shift = np.array([1.0, -0.5, 0.25])
    est = perturbed(ref, {n: shift for n in names}, {n: 0.0 for n in names})
    del est[names[0]]                                               # not localized: a failure
    est[UNVERIFIED] = read_poses(site / "work" / "register" / "poses.txt")[UNVERIFIED]   # kept out: not judged
    f = tmp_path / "shifted.txt"
    write_poses(f, est)
    rep = evaluate_results(site, f, out_dir=tmp_path / "rep")
    assert np.abs(np.array(rep["mean_centre_offset_m"]) - shift).max() < 1e-9
    assert rep["n_localized"] == 6 and rep["per_photo"][names[0]]["missing"] is True
    assert rep["n_ignored_kept_out"] == 1 and rep["ignored_kept_out"] == [UNVERIFIED]
    assert rep["recall_1m1deg"] == 0.0 and rep["recall_3m3deg"] == 6 / 7


def test_scoring_an_exported_dataset_is_scoring_the_project(site, tmp_path, capsys):
    ref = published(site)
    shifts, _dist, degs = known_offsets(sorted(ref))
    f = tmp_path / "poses.txt"
    write_poses(f, perturbed(ref, shifts, degs))
    out = tmp_path / "ds"
    assert gtkit(["export", "dataset", str(site), str(out), "--format", "hloc"]) == 0
    a = evaluate_results(site, f, out_dir=tmp_path / "a")
    b = evaluate_results(out, f, out_dir=tmp_path / "b")
    for k in ("recall_1m1deg", "recall_3m3deg", "recall_5m5deg", "sigma_aware"):
        assert a[k] == b[k], k
    for k in ("median_pos_err_m", "median_rot_err_deg"):   # the dataset's poses went through text: 1e-13 apart
        assert abs(a[k] - b[k]) < 1e-9, k
    assert gtkit(["evaluate", "results", str(out), str(f)]) == 0
    assert "judged by 6/7" in capsys.readouterr().out
    assert len(list(tmp_path.glob("*_poses_evaluation/*_poses.md"))) == 1


def fake_localization(site: Path) -> None:
    """work/localize/ as gtkit localize writes it (poses.txt, status.json): the true poses moved by known
    offsets, one query not localized."""
    from gtkit.project import Project
    from gtkit.queries import query_photos

    truth = read_poses(site / "truth" / "poses.txt")
    names = query_photos(Project.load(site))
    rng = np.random.default_rng(3)
    est = {n: Pose.from_center(small_rotation(rng, d) @ truth[n].R, truth[n].center + rng.normal(scale=s, size=3))
           for n, s, d in zip(names, np.linspace(0.05, 4.0, len(names)), np.linspace(0.05, 4.0, len(names)))}
    est.pop(names[-1])
    d = site / "work" / "localize"
    write_poses(d / "poses.txt", est)
    (d / "status.json").write_text(json.dumps({"queries": [{"name": n, "ok": n in est, "seconds": {}, "seconds_total": 0.0}
                                                           for n in names]}))


def test_against_truth_reproduces_the_localization_report(site, tmp_path):
    from gtkit.evaluate import localization

    fake_localization(site)
    main = localization.evaluate(site, with_retrieval=False)
    rep = evaluate_results(site, site / "work" / "localize" / "poses.txt", against="truth", out_dir=tmp_path)
    for k in ("n_localized", "recall_1m1deg", "recall_3m3deg", "recall_5m5deg", "median_pos_err_m", "median_rot_err_deg"):
        assert rep[k] == main[k], (k, rep[k], main[k])
    assert rep["n_reference"] == main["n_queries"] and rep["sigma_aware"] is None


@pytest.mark.skipif(not SLOW, reason="the main job on the tiny sample, then export and scoring: GTKIT_SLOW=1")
def test_main_job_then_export_and_score_on_the_tiny_sample(tiny_sample, tmp_path):
    import kapture
    import kapture.io.csv as kcsv

    from gtkit.conventions import quat_to_rotmat

    root = tmp_path / "site"
    shutil.copytree(tiny_sample[0], root)
    r = subprocess.run([sys.executable, "-m", "pipelines.full", str(root)], cwd=ROOT, capture_output=True, text=True,
                       timeout=1800)
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((root / "reports" / "summary.json").read_text())["localization"]
    rep = evaluate_results(root, root / "work" / "localize" / "poses.txt", against="truth", out_dir=tmp_path / "t")
    for k in ("recall_1m1deg", "recall_3m3deg", "recall_5m5deg", "median_pos_err_m", "median_rot_err_deg"):
        assert rep[k] == summary[k], k
    out = tmp_path / "ds"
    assert gtkit(["export", "dataset", str(root), str(out)]) == 0
    gt = read_poses(root / "work" / "register" / "poses.txt")
    k = kcsv.kapture_from_dir(str(out / "kapture" / "query"))
    for ts, sid, name in kapture.flatten(k.records_camera):
        if name in gt:
            p = k.trajectories[ts, sid]
            assert np.abs(quat_to_rotmat(p.r_raw) - gt[name].R).max() < 1e-9
            assert np.abs(np.array(p.t_raw) - gt[name].t).max() < 1e-9
    pg = evaluate_results(out, root / "work" / "localize" / "poses.txt", out_dir=tmp_path / "p")
    assert pg["n_reference"] == json.loads((out / "dataset.json").read_text())["pseudo_gt"]["n_published"]
