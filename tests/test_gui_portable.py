"""Portable projects: a finished project copied to a new folder, the original deleted, opens,
resumes and reviews its own poses.

The finished project is the GUI demo site (10 reference photos, 3 query photos) taken through
render-db (a tiny grid), localize, overlay, export mesh, report and an annotator session that
reviews the localized poses. Measured on the copy: no project file names the original folder,
render-db / localize / export mesh are up to date (their records and outputs untouched), the
report runs, and the annotator (offscreen) reviews the copy's own pose file with sub-pixel
alignment. Also: records and sessions written before paths were stored relative still work.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("pytestqt")
from PySide6.QtCore import Qt  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

from gtkit.cli import main  # noqa: E402

from conftest import DEMO_DB_ARGS as DB_ARGS  # noqa: E402

TEXT = {".json", ".txt", ".toml", ".md", ".csv", ".geojson", ".mtl", ".svg"}


@pytest.fixture(scope="module")
def finished(finished_demo):
    return finished_demo


def _records(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): p.read_text() for p in sorted(root.rglob("stage.json"))}


def _named_everywhere(root: Path, text: str) -> list[str]:
    return [str(p.relative_to(root)) for p in root.rglob("*")
            if p.is_file() and p.suffix in TEXT and text in p.read_text(errors="replace")]


def test_copied_project_resumes_and_reviews_its_own_poses(finished, tmp_path, qtbot, capsys):
    src = tmp_path / "moved" / "site"
    shutil.copytree(finished, src)
    copy = tmp_path / "elsewhere" / "site_copy"
    shutil.copytree(src, copy)
    shutil.rmtree(src)  # the original is gone (copied to src first: the module fixture stays intact)
    assert (copy / "work/annotate/session.json").is_file() and (copy / "reports/overlays/alignment.json").is_file()
    # no project file names the folder the project was made in
    assert _named_everywhere(copy, str(finished)) == []
    session = json.loads((copy / "work/annotate/session.json").read_text())
    assert session["review"]["pose_file"] == "work/localize/poses.txt"
    verdicts = json.loads((copy / "review.json").read_text())
    assert [v["pose_file"] for v in verdicts["images"].values()] == ["work/localize/poses.txt"]
    assert json.loads((copy / "exports/mesh/model.obj.offset.json").read_text())["source"] == "model/reference.obj"
    # finished stages stay finished: records and outputs untouched
    records = _records(copy)
    assert {"work/render_db/stage.json", "work/localize/stage.json", "work/export_mesh_obj/stage.json"} <= set(records)
    outputs = {p: (copy / p).stat().st_mtime_ns for p in ("work/localize/poses.txt", "work/localize/status.json",
                                                           "exports/mesh/model.obj", "work/render_db/views.json")}
    capsys.readouterr()
    assert main(["render-db", str(copy), *DB_ARGS]) == 0
    assert main(["localize", str(copy), "--executor", "serial"]) == 0
    assert main(["export", "mesh", str(copy)]) == 0
    assert _records(copy) == records
    assert {p: (copy / p).stat().st_mtime_ns for p in outputs} == outputs
    # the report runs on the copy and names only the copy
    assert main(["report", str(copy)]) == 0
    assert (copy / "reports/gt_report.json").is_file() and _named_everywhere(copy, str(finished)) == []
    # the annotator reviews the copy's own poses
    from gui.main_window import MainWindow

    w = MainWindow(copy)
    qtbot.addWidget(w)
    w.show()
    QApplication.processEvents()
    assert Path(w.review.pose_file).resolve() == (copy / "work/localize/poses.txt").resolve()
    qtbot.keyClick(w, Qt.Key.Key_2, Qt.KeyboardModifier.ControlModifier)
    rv = w.review
    assert rv.image is not None and rv._cache[5].misalignment_px < 1.0
    w.save_session()
    w.close()
    assert json.loads((copy / "work/annotate/session.json").read_text())["review"]["pose_file"] == \
        "work/localize/poses.txt"


def test_records_and_sessions_with_absolute_paths_still_work(finished, tmp_path, qtbot):
    """Projects made before paths were stored relative: a stage record keyed on absolute paths
    counts as finished where it was made; an absolute pose file of a deleted folder is found in
    the copy by its path inside the project."""
    from gtkit.export.mesh_export import STAGE, MeshExportSettings
    from gtkit.export.sources import stage_inputs
    from gtkit.project import Project, resolve_path, settings_dict, settings_key, stage_done

    site = tmp_path / "site"
    shutil.copytree(finished, site)
    proj = Project.load(site)
    src, out = site / "model/reference.obj", site / "exports/mesh/model.obj"
    s = MeshExportSettings()
    inputs = stage_inputs(proj, src, None, None, out)  # absolute paths, as the old records stored them
    rec = site / "work" / f"{STAGE}_obj" / "stage.json"
    legacy = {"key": settings_key({"settings": settings_dict(s), "inputs": inputs}), "settings": settings_dict(s),
              "inputs": inputs, "summary": {"path": str(out)}}
    rec.write_text(json.dumps(legacy))
    assert str(site) in rec.read_text()
    assert stage_done(rec.parent, s, inputs)
    assert not stage_done(rec.parent, MeshExportSettings(decimate=100), inputs)
    # an old session naming the pose file by the absolute path of a folder that no longer exists
    gone = "/no/such/folder/site/work/localize/poses.txt"
    assert resolve_path(gone, site) == site / "work/localize/poses.txt"
    assert resolve_path("work/localize/poses.txt", site) == site / "work/localize/poses.txt"
    sess = site / "work/annotate/session.json"
    d = json.loads(sess.read_text())
    d["review"]["pose_file"] = gone
    sess.write_text(json.dumps(d))
    from gui.main_window import MainWindow

    w = MainWindow(site)
    qtbot.addWidget(w)
    assert Path(w.review.pose_file) == site / "work/localize/poses.txt"
    w.close()
