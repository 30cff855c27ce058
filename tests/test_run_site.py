"""``gtkit run SITE`` on a user's own project, measured against the truth of the sample it was made
from: the tiny sample's reference photos and one query sequence copied into plain folders,
``gtkit init`` with the surveyor's gcp_list.txt only (no cameras.txt, no tiepoints.json), the
sample's delivered model imported (``gtkit import model``; the build itself is tested in
test_model_build.py, and here only that ``gtkit run`` chooses it), then ``gtkit run``: reference
SfM, query SfM, registration without clicks, report, exports, overlays, render-db, localization.
A second run finds every stage up to date.
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from gtkit.cli import main as gtkit
from gtkit.io.poses import read_poses
from gtkit.project import Project
from gtkit import run_site, stages

SEQ = "seq1"
# small database views and small overlays keep the test short (settings a site can set in project.toml);
# the database grid follows the queries (heights, intervals, pitches from their GPS and gimbal)
FAST = """
[render_db]
width = 320
height = 240

[overlay]
modes = ["blend"]
max_side = 320
"""


def _user_project(sample: Path, tmp: Path, queries=(SEQ,), gcp=True, extra: str = "") -> Path:
    """A project as a user makes one: photos in plain folders, ``gtkit init``."""
    photos = tmp / "photos"
    shutil.copytree(sample / "images" / "reference", photos / "oblique")
    for q in queries:
        shutil.copytree(sample / "images" / "queries" / q, photos / q)
    root = tmp / "site"
    args = ["init", str(root), "--reference", str(photos / "oblique")]
    if queries:
        args += ["--queries", *[str(photos / q) for q in queries]]
    if gcp:
        args += ["--gcp", str(sample / "gcp_list.txt")]
    assert gtkit(args) == 0
    assert not (root / "cameras.txt").exists() and not (root / "tiepoints.json").exists()
    if extra:
        with open(root / "project.toml", "a") as f:
            f.write(extra)
    return root


def _centre_errors(est_file: Path, est_root: Path, sample: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Camera-centre (m, in the CRS: each project has its own local origin) and rotation (deg) errors
    of the poses in ``est_file`` against the sample's truth."""
    est, truth = read_poses(est_file), read_poses(sample / "truth" / "poses.txt")
    o_est = np.array(Project.load(est_root).frame.origin)
    o_true = np.array(Project.load(sample).frame.origin)
    names = sorted(n for n in est if n in truth)
    pos = np.array([np.linalg.norm((est[n].center + o_est) - (truth[n].center + o_true)) for n in names])
    rot = []
    for n in names:
        c = (np.trace(est[n].R @ truth[n].R.T) - 1) / 2
        rot.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return pos, np.array(rot), names


def test_run_on_a_users_own_site(tiny_sample, tmp_path, capsys):
    sample = tiny_sample[0]
    root = _user_project(sample, tmp_path, extra=FAST)
    assert gtkit(["import", "model", str(root), str(sample / "model" / "reference.obj")]) == 0
    # target boxes in the zoom photos, as the annotator saves them (here simulated from the sample's truth)
    from gtkit.evaluate.tracking import simulate_detections
    from gtkit.project import Paths

    simulate_detections(Paths(sample), tmp_path / "all.csv")
    rows = (tmp_path / "all.csv").read_text().splitlines()
    (root / "detections.csv").write_text("\n".join(r for r in rows if not r.startswith("queries/")
                                                   or r.startswith(f"queries/{SEQ}/")) + "\n")
    capsys.readouterr()

    t0 = time.time()
    rc = gtkit(["run", str(root), "--executor", "serial"])
    first_s = time.time() - t0
    out = capsys.readouterr().out
    assert rc == 0, out
    s = json.loads((root / "reports" / "run.json").read_text())
    st = s["stages"]
    with capsys.disabled():     # the measured times, in the test log (pytest -s)
        print(f"\nfirst run {first_s:.1f} s: " + ", ".join(f"{k} {v['status']} {v['seconds']}" for k, v in st.items()))

    # the model was imported, so none is built; the line says why
    assert st["model"]["status"] == "skipped" and "imported" in st["model"]["why"]
    assert "[model] skipped: a model was imported or delivered (model/reference.obj)" in out
    # detections but no cameras.txt: the rig calibration takes the wide camera's from it, so tracking
    # says so and the run goes on (with cameras.txt it runs: the report names that run)
    assert st["track"]["status"] == "skipped" and "no cameras.txt" in st["track"]["why"], st["track"]

    # reference block against the truth: every photo, centres within 0.3 m, rotations within 0.3 deg
    pos, rot, names = _centre_errors(root / "work/sfm_reference/poses.txt", root, sample)
    assert len(names) == s["reference"]["n_images"] == s["reference"]["n_registered"] == 45
    assert np.median(pos) < 0.3 and np.median(rot) < 0.3, (np.median(pos), np.median(rot))
    assert "GCPs" in s["reference"]["georegistered_with"]   # what the fit rests on, e.g. "4 GCPs + 45 GPS positions"
    assert s["reference"]["gcp_median_err_m"] is not None and s["reference"]["gcp_median_err_m"] < 0.5

    # query block and pseudo-GT without clicks (automatic matches): against the truth
    assert s["query_blocks"][SEQ]["n_registered"] >= 3
    pg = s["pseudo_gt"]
    assert pg["n_registered"] >= 3 and pg["registered_by"][SEQ] == "automatic matches", pg
    pos, rot, names = _centre_errors(root / "work/register/poses.txt", root, sample)
    assert len(names) == pg["n_registered"]
    assert np.median(pos) < 1.0 and np.median(rot) < 1.0, (np.median(pos), np.median(rot))
    assert pg["median_sigma_pos_m"] is not None

    # exports: the DSM's heights at the GCPs are the surveyed ones within 1 m (the model is the sample's)
    for f in ("exports/dsm.tif", "exports/ortho.tif", "exports/coordinates/cameras.csv",
              "exports/coordinates/targets.csv"):
        assert (root / f).is_file(), f
    from gtkit.export.dsm import Dsm
    from gtkit.io.odm import read_gcp_list

    proj = Project.load(root)
    dsm = Dsm.for_project(proj)
    for g in read_gcp_list(root / "gcp_list.txt", proj.frame):
        z = float(np.asarray(dsm.height_at(g.xyz[0], g.xyz[1])))
        assert abs(z - g.xyz[2]) < 1.0, (g.name, z, g.xyz[2])

    # overlays of the pseudo-GT and reference poses on the model
    assert s["overlays"]["n_images"] >= 45 + 3 and s["overlays"]["median_misalignment_px"] < 2.0

    # localization without cameras.txt: against the truth
    loc = s["localization"]
    assert loc["n_queries"] == 4 and loc["n_localized"] >= 3, loc
    pos, rot, names = _centre_errors(root / "work/localize/poses.txt", root, sample)
    assert np.median(pos) < 3.0 and np.median(rot) < 3.0, (np.median(pos), np.median(rot))

    # the summary printed states the same
    assert "45/45 photos registered" in out and f"{loc['n_localized']}/4 query photos localized" in out

    # a second run: nothing expensive, the same figures
    t0 = time.time()
    assert gtkit(["run", str(root), "--executor", "serial"]) == 0
    second_s = time.time() - t0
    out2 = capsys.readouterr().out
    s2 = json.loads((root / "reports" / "run.json").read_text())
    with capsys.disabled():
        print(f"second run {second_s:.1f} s (first {first_s:.1f} s)")
    ran = {k: v["status"] for k, v in s2["stages"].items() if v["status"] not in ("up to date", "skipped")}
    assert ran == {"report": "ran"}, ran          # the report has no record: it is rewritten (cheap)
    assert second_s < 30 and second_s < first_s / 4, (second_s, first_s)
    for k in ("reference", "model", "query_blocks", "pseudo_gt", "overlays", "localization", "exports"):
        assert s2[k] == s[k], k
    strip = [ln for ln in out.splitlines() if ln.startswith(("reference ", "pseudo-GT ", "localization "))]
    assert strip and all(ln in out2 for ln in strip)


def test_run_skips_what_the_project_cannot_do_and_says_why(tiny_sample, tmp_path, capsys):
    """Reference photos and GCPs only, from the query stage on: each stage that has no input says why."""
    root = _user_project(tiny_sample[0], tmp_path, queries=())
    capsys.readouterr()
    assert gtkit(["run", str(root), "--from", "sfm_queries"]) == 0
    out = capsys.readouterr().out
    s = json.loads((root / "reports" / "run.json").read_text())
    st = s["stages"]
    assert st["sfm_reference"]["status"] == st["model"]["status"] == "not selected"
    assert "[sfm_queries] skipped: no query sequences" in out
    assert "[register] skipped: no query sequences" in out
    for k in ("export_dsm", "export_ortho", "export_mesh", "overlays", "render_db"):
        assert st[k]["status"] == "skipped" and "no reference model" in st[k]["why"], (k, st[k])
    assert st["export_coords"]["status"] == "ran"          # the GCPs, as targets
    assert (root / "exports/coordinates/targets.csv").is_file()
    assert st["localize"]["status"] == "skipped" and st["track"]["status"] == "skipped"


def test_run_stops_at_a_failing_stage_naming_it(tiny_sample, tmp_path, capsys):
    root = _user_project(tiny_sample[0], tmp_path, extra='\n[sfm]\nmapper = "sometimes"\n')
    capsys.readouterr()
    assert gtkit(["run", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gtkit: error: stage sfm_reference failed:"), err
    assert "sometimes" in err[0]
    s = json.loads((root / "reports" / "run.json").read_text())
    assert s["stages"]["sfm_reference"]["status"] == "failed" and "model" not in s["stages"]


def test_run_builds_a_model_only_when_none_was_imported(tiny_sample, tmp_path, monkeypatch):
    """The choice of the model stage (the build itself: test_model_build.py)."""
    import gtkit.model.build as build

    root = _user_project(tiny_sample[0], tmp_path, queries=(), gcp=False)
    calls = []
    monkeypatch.setattr(build, "run", lambda project, settings, **kw: calls.append(settings) or {"triangles": 1})
    proj = Project.load(root)
    assert run_site.model_state(proj) == ("none", None)
    model = stages.STAGE["model"]
    assert model.run(proj, stages.settings_for(model, proj), stages.Context()) == {"triangles": 1, "photos": None,
                                                                                    "depth_maps": None}
    assert len(calls) == 1
    assert gtkit(["import", "model", str(root), str(tiny_sample[0] / "model" / "reference.obj")]) == 0
    proj = Project.load(root)
    assert run_site.model_state(proj)[0] == "imported"
    with pytest.raises(stages.Skip, match="a model was imported or delivered"):
        model.run(proj, stages.settings_for(model, proj), stages.Context())
    assert len(calls) == 1


def test_stage_selection():
    sel = run_site.selected(run_site.RunOptions("register", "overlays", ("export_mesh",)))
    assert sel == ["register", "report", "export_dsm", "export_ortho", "overlays"]
    from gtkit.errors import GtkitError

    with pytest.raises(GtkitError, match="unknown stage 'mesh'"):
        run_site.selected(run_site.RunOptions(skip=("mesh",)))
    with pytest.raises(GtkitError, match="comes after"):
        run_site.selected(run_site.RunOptions("localize", "register"))


def test_sequences_that_could_not_be_placed_are_problems(tiny_sample, tmp_path, capsys):
    """The summary lists what a stage could not do without stopping (a sequence's SfM, a sequence
    registration needs clicks for); `gtkit run` then exits 1. Read from the stages' own files."""
    from gtkit.commands.run import print_summary
    from gtkit.io.atomic import write_json

    root = _user_project(tiny_sample[0], tmp_path, queries=("seq1", "seq2"), gcp=False)
    write_json(root / "work/sfm_queries/summary.json", {
        "seq1": {"n_registered": 4, "n_images": 4}, "seq2": {"error": "no photos matching *_W.*", "n_images": 0}})
    write_json(root / "work/register/registration.json", {
        "n_registered": 0, "n_images": 4, "images": {},
        "sequences": {"seq1": {"status": "error", "error": "no clicked tie points; automatic matches: too few",
                               "needs_clicks": True}}})
    s = run_site.collect(Project.load(root), [run_site.StageResult("register", "ran", 1.0)])
    assert s["problems"] == ["query block seq2: no photos matching *_W.*",
                             "pseudo-GT seq1: no clicked tie points; automatic matches: too few"]
    print_summary(s)
    out = capsys.readouterr().out
    assert "query block   seq2: ERROR no photos matching" in out and "problem       pseudo-GT seq1" in out
