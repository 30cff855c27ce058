"""Every way ``gtkit register`` can record a sequence (clicked, automatic, single photos, needs
clicks, error) read back by every reader of registration.json in words: the GT report, the run
summary, ``gtkit run``'s lines; and an unexpected failure of a stage reaching the user as one line
naming the stage and the file that holds its traceback (exit 2), never as a traceback."""
from __future__ import annotations

import dataclasses
import json

import pytest

from gtkit import run_site, stages
from gtkit.cli import main as gtkit
from gtkit.geo import GeoFrame
from gtkit.project import Project
from gtkit.sfm import registration_record as record
from gtkit.sfm import report

# one entry of each outcome, in the shapes gtkit/sfm/register.py writes them
SEQUENCES = {
    "clicked": {"status": "registered", "registered_by": "clicked tie points", "scale": 1.01, "n_tiepoints": 12,
                "n_sim3_inliers": 11, "sim3_rmse_m": 0.084, "n_tiepoints_final_ba": 11},
    "automatic": {"status": "registered", "registered_by": "automatic matches", "scale": 0.99, "n_tiepoints": 0,
                  "n_sim3_inliers": 0, "sim3_rmse_m": None, "clicks": "no clicked tie points",
                  "automatic": {"n_photos_agreeing": 7, "n_photos": 8, "n_sim3_inliers": 412, "n_point_pairs": 450,
                                "sim3_from": "point pairs"}, "n_tiepoints_final_ba": 0},
    "single": {"status": "registered", "registered_by": "single photos (its SfM made no model)", "scale": 1.0,
               "n_tiepoints": 0, "n_sim3_inliers": 0, "sim3_rmse_m": None, "n_tiepoints_final_ba": 0,
               "left_out_by_sfm": {"queries/single/DJI_0018.JPG": {"resected": True, "from": "automatic matches"},
                                   "queries/single/DJI_0023.JPG": {"resected": True, "from": "automatic matches"},
                                   "queries/single/DJI_0099.JPG": {"resected": False,
                                                                   "auto_reason": "12 matches, 30 needed"}}},
    "needs": {"status": "error", "needs_clicks": True, "clicks": "no clicked tie points",
              "error": "no clicked tie points; automatic matches: 2 of 9 photos agree; click 3 or more tie points"},
    "broken": {"status": "error", "needs_clicks": False,
               "error": "no query-block model (run `gtkit sfm DIR --block queries`)"},
}
EXPECTED = {"clicked": record.CLICKED, "automatic": record.AUTOMATIC, "single": record.SINGLE_PHOTOS,
            "needs": record.NEEDS_CLICKS, "broken": record.ERROR}


@pytest.fixture
def project(tmp_path):
    proj = Project.create(tmp_path / "site", GeoFrame("EPSG:32615", (576700.0, 5188160.0, 0.0)), "outcomes")
    reg = proj.paths.stage("register")
    reg.mkdir(parents=True)
    (reg / "registration.json").write_text(json.dumps(
        {"sequences": SEQUENCES, "n_registered": 3, "n_images": 30, "images": {}, "median_reproj_px": 0.4}))
    return proj


def test_every_outcome_is_named_and_described():
    for seq, s in SEQUENCES.items():
        assert record.outcome(s) == EXPECTED[seq]
        line = record.describe(s)
        assert "\n" not in line and "None" not in line, line
    assert record.describe(SEQUENCES["single"]).startswith(
        "registered as single photos (its SfM made no model): 2 of 3 photos placed one by one")
    assert "DJI_0099.JPG (12 matches, 30 needed)" in record.describe(SEQUENCES["single"])
    assert "Sim(3) RMSE 0.084 m" in record.describe(SEQUENCES["clicked"])
    assert "7/8 photos agree" in record.describe(SEQUENCES["automatic"])
    assert record.describe(SEQUENCES["needs"]).startswith("not registered (needs clicks): no clicked tie points")
    assert record.describe(SEQUENCES["broken"]).startswith("not registered: no query-block model")
    # an older record's entry (no registered_by) was a clicked one
    old = {k: v for k, v in SEQUENCES["clicked"].items() if k != "registered_by"}
    assert record.outcome(old) == record.CLICKED


def test_gt_report_reads_every_outcome_back(project):
    report.run(project)
    md = (project.paths.reports / "gt_report.md").read_text()
    for seq, s in SEQUENCES.items():
        assert f"- **{seq}**: {record.describe(s)}" in md
    assert "| 1 / 1 / 1 / 1 / 1 of 5 |" in md
    need = md.split("## Sequences that need clicks")[1].split("## Sequences")[0]
    assert "**needs**" in need and "**broken**" not in need


def test_run_summary_says_how_each_sequence_was_placed(project):
    s = run_site.collect(project, [], 0.0)
    pg = s["pseudo_gt"]
    assert set(pg["registered_by"]) == {"clicked", "automatic", "single"}
    assert pg["registered_by"] == {"clicked": record.CLICKED, "automatic": record.AUTOMATIC, "single": record.SINGLE_PHOTOS}
    assert pg["registered_how"]["single"].startswith("single photos (its SfM made no model): 2 of 3")
    assert set(pg["errors"]) == {"needs", "broken"}
    assert set(s["problems"]) == {f"pseudo-GT needs: {SEQUENCES['needs']['error']}",
                                  f"pseudo-GT broken: {SEQUENCES['broken']['error']}"}


def test_an_unexpected_failure_is_one_line_naming_the_stage_and_its_traceback_file(project, monkeypatch, capsys):
    def broken(project, settings, context):
        raise TypeError("unsupported format string passed to NoneType.__format__")

    monkeypatch.setitem(stages.STAGE, "report", dataclasses.replace(stages.STAGE["report"], run=broken))
    rc = gtkit(["run", str(project.paths.root), "--from", "report", "--until", "report"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and "Traceback" not in err[0], err
    where = project.paths.work / "errors" / "report.txt"
    assert err[0] == (f"gtkit: error: stage report failed (unexpected TypeError: unsupported format string passed to "
                      f"NoneType.__format__); the traceback is in {where} (please report it)")
    assert "Traceback (most recent call last)" in where.read_text() and "def broken" not in err[0]
    summary = json.loads((project.paths.reports / "run.json").read_text())
    assert summary["stages"]["report"]["status"] == "failed"


def test_an_unexpected_failure_of_a_command_is_one_line(project, monkeypatch, capsys):
    import gtkit.sfm.report as rep_mod

    monkeypatch.setattr(rep_mod, "collect", lambda project: {}["no such key"])
    rc = gtkit(["report", str(project.paths.root)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("gtkit: error: report failed unexpectedly (KeyError: 'no such key'); the traceback is in ")
    assert (project.paths.work / "errors" / "report.txt").is_file()


def test_a_damaged_stage_record_is_a_one_line_error_naming_it_not_a_stage_not_run(project):
    """The GT report reads the reference block's record; a truncated one (a disk filled mid-write by
    another tool) is named with what to do, never read as "the reference SfM has not run"."""
    from gtkit.errors import GtkitError

    blk = project.paths.stage("sfm_reference") / "block.json"
    blk.parent.mkdir(parents=True, exist_ok=True)
    blk.write_text('{"n_registered": 12, "intrinsics": {')
    with pytest.raises(GtkitError) as e:
        report.run(project)
    assert str(blk) in str(e.value) and "unreadable record" in str(e.value) and "\n" not in str(e.value)
