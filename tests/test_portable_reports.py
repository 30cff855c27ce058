"""Portable reports: every report a command writes names paths inside the project relative to it.

A finished project (the GUI demo site through render-db, localize, overlay, export mesh, report) is
copied, the report-writing commands run in the copy (evaluate, export dsm / ortho / coords, overlay,
report, info), and the copy is copied again with the first copy deleted: no file under reports/, no
GeoTIFF tag and not project.toml names the folder the commands ran in. The tracking reports
(`gtkit track evaluate`) are checked in tests/test_track_stage.py on a project with targets.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

pytest.importorskip("pytestqt")  # the finished_demo fixture drives the annotator once

from gtkit.cli import main  # noqa: E402

TEXT = {".json", ".txt", ".toml", ".md", ".csv", ".geojson", ".svg", ".html"}


def naming(root: Path, text: str, where=("reports", "exports", "project.toml")) -> list[str]:
    """Files under ``where`` (text files, and the tags of GeoTIFFs) that hold ``text``."""
    hits = []
    for w in where:
        base = root / w
        files = [base] if base.is_file() else sorted(p for p in base.rglob("*") if p.is_file())
        for p in files:
            if p.suffix in TEXT and text in p.read_text(errors="replace"):
                hits.append(str(p.relative_to(root)))
            elif p.suffix == ".tif" and text.encode() in p.read_bytes():
                hits.append(str(p.relative_to(root)))
    return hits


def test_reports_of_a_copied_project_name_no_absolute_path(finished_demo, tmp_path, capsys):
    first = tmp_path / "first" / "site"
    shutil.copytree(finished_demo, first)
    for argv in (["evaluate", str(first)], ["export", "dsm", str(first)], ["export", "ortho", str(first)],
                 ["export", "coords", str(first), "--poses", str(first / "work/localize/poses.txt")],
                 ["overlay", str(first), "--poses", str(first / "work/localize/poses.txt")],
                 ["report", str(first)], ["info", str(first)]):
        assert main(argv) == 0, argv
    capsys.readouterr()
    assert (first / "reports/localization.json").is_file() and (first / "exports/dsm.tif").is_file()
    moved = tmp_path / "elsewhere" / "site_copy"
    shutil.copytree(first, moved)
    shutil.rmtree(first)
    assert naming(moved, str(first)) == []
    assert naming(moved, str(finished_demo)) == []
