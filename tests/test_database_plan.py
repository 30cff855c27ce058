"""Issue 58: `gtkit run` finishes on a site whose queries are not flown 50-200 m up.

The shared fountain set held out (terrestrial: queries 2.8 m above the ground, looking horizontally,
no GPS altitude, no gimbal angles) got the paper's 100-150 m grid, kept 0 of 48 views, and localize
stopped the run with exit 2 after the pseudo-GT and exports were written. Now:

- the grid follows what the project knows of photos whose sensors say nothing: their ``geo.txt``
  position and pseudo-GT pose (height above the model's ground, pitch off nadir); a UAV project's
  photos (GPS altitude, gimbal) plan it as before and its database does not wait on its pseudo-GT;
- views within 10 degrees of the horizon stand at their grid position (their look-at point lies
  11 H away at 85 degrees);
- a database that keeps no view is one line saying why, and localization is skipped with one line;
- a validation stage (render_db, localize) that fails is a problem (exit 1), not the run's end: the
  coordinate exports after it are still written.

The fountain end to end (about 4 minutes on 2 cores): tests/test_real_truth_run.py, GTKIT_SLOW=1."""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from gtkit import stages
from gtkit.cli import main as gtkit
from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.io.poses import write_poses
from gtkit.localize import database
from gtkit.localize.flight import flight_inputs
from gtkit.localize.grid import make_views
from gtkit.pose import Pose
from gtkit.project import Project, mark_stage_done
from test_localize_own_site import _FlatGround, _flight

GROUND = 20.0
EXT = (-30.0, -30.0, 30.0, 30.0)


def _terrestrial(tmp_path: Path, geo: bool) -> Project:
    """Four phone photos (no GPS, no gimbal) 2.8 m above flat ground at z 20, looking 2 deg above
    the horizon, with pseudo-GT poses; with ``geo``, their positions in geo.txt too (1.6 m up)."""
    frame = GeoFrame("EPSG:32632", (500000.0, 5000000.0, 0.0))
    p = Project.create(tmp_path / "site", frame)
    rgb = np.zeros((48, 64, 3), np.uint8)
    poses, lines = {}, ["EPSG:32632"]
    for k in range(4):
        name = f"queries/seq/{k:04d}.jpg"
        write_jpeg_with_meta(p.paths.images / name, rgb, focal_35mm=28.0, make="phone", model="phone")
        c = np.array([5.0 * k - 7.5, -10.0, GROUND + 2.8])
        poses[name] = Pose.from_dji(20.0 * k, 2.0, 0.0, c)
        lines.append(f"{k:04d}.jpg {500000.0 + c[0]:.3f} {5000000.0 + c[1]:.3f} {GROUND + 1.6:.3f}")
    write_poses(p.paths.pseudo_gt_poses, poses)
    if geo:
        p.paths.geo_txt.write_text("\n".join(lines) + "\n")
    p.config["sfm"] = {"query_pattern": "*"}
    p.save()
    return Project.load(p.paths.root)


def test_grid_planned_from_the_queries_pseudo_gt_and_geo_txt(tmp_path):
    p = _terrestrial(tmp_path / "pgt", geo=False)
    s, info = database.resolve_grid(p, database.RenderDbSettings(), _FlatGround(GROUND), EXT, GROUND)
    assert s.heights == (3.0,) and s.paper_pitches == (85.0,), (s.heights, s.paper_pitches)
    assert info["source"]["heights"] == "queries (4 photos' height above the model's ground: 4 from pseudo-GT pose)"
    assert info["source"]["paper_pitches"] == "queries (4 photos' pitch off nadir: 4 from pseudo-GT pose)"
    assert 1.0 < s.intervals[0] < 2.5            # H / 2 at 60 deg, scaled with the field of view
    # geo.txt positions (the user's) come before the pseudo-GT for the height
    p = _terrestrial(tmp_path / "geo", geo=True)
    s, info = database.resolve_grid(p, database.RenderDbSettings(), _FlatGround(GROUND), EXT, GROUND)
    assert s.heights == (2.0,) and info["source"]["heights"].endswith("4 from geo.txt)"), info["source"]
    # what the grid follows is an input of render-db only where the sensors are silent
    names = sorted(f"queries/seq/{k:04d}.jpg" for k in range(4))
    assert set(flight_inputs(p, names)) == {"geo_txt", "pseudo_gt_poses"}
    uav = _flight(tmp_path / "uav", [44.0, 45.0, 46.0], pitch=-50.0)
    assert flight_inputs(uav, sorted(str(f.relative_to(uav.paths.images)) for f in
                                     uav.paths.query_images.rglob("*.jpg"))) == {}
    s, info = database.resolve_grid(uav, database.RenderDbSettings(), _FlatGround(GROUND), EXT, GROUND)
    assert info["source"]["heights"] == "queries (3 photos' GPS altitude above the model's ground)"
    assert info["source"]["paper_pitches"] == "queries (3 photos' gimbal pitch)"


def test_views_near_the_horizon_stand_at_their_grid_position():
    level = make_views(EXT, GROUND, (3.0,), (20.0,), (85.0,), 90.0, "look_at")
    assert level and all(EXT[0] <= v.center[0] <= EXT[2] and EXT[1] <= v.center[1] <= EXT[3] for v in level)
    oblique = make_views(EXT, GROUND, (3.0,), (20.0,), (45.0,), 90.0, "look_at")     # 3 m back, as before
    assert max(abs(a.center[1] - b.center[1]) for a, b in zip(oblique, make_views(
        EXT, GROUND, (3.0,), (20.0,), (45.0,), 90.0, "camera"))) == 3.0


def _tiny_copy(tiny_sample, tmp_path) -> Path:
    root = tmp_path / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    return root


def test_a_database_without_views_skips_localization_in_one_line(tiny_sample, tmp_path, monkeypatch, capsys):
    root = _tiny_copy(tiny_sample, tmp_path)

    def no_view_kept(project, s, executor=None, chunk=8, force=False, *, localize_settings):
        out = project.paths.stage("render_db")
        out.mkdir(parents=True, exist_ok=True)
        mark_stage_done(out, s, {}, n_views=48, n_kept=0, grid={"heights": [100.0, 150.0], "paper_pitches": [0.0, 45.0],
                                                               "source": {"heights": "default (no query GPS altitude)"}})
        return out

    monkeypatch.setattr(database, "run", no_view_kept)
    capsys.readouterr()
    assert gtkit(["run", str(root), "--from", "render_db", "--until", "localize"]) == 0
    out = capsys.readouterr().out
    assert ("[render_db] skipped: no database view sees enough of the model (>= 0.5 of the view): none of the 48 "
            "views planned at heights [100.0, 150.0] m (default (no query GPS altitude))") in out
    assert "[localize] skipped: the rendered database holds no view (see render_db's line)" in out
    assert "problem" not in out and "error" not in out.lower()


def test_a_failed_validation_stage_is_a_problem_not_the_runs_end(tiny_sample, tmp_path, monkeypatch, capsys):
    root = _tiny_copy(tiny_sample, tmp_path)

    def boom(project, s, ctx):
        raise GtkitError("the database subset chosen by the settings is empty")

    monkeypatch.setitem(stages.STAGE, "localize", replace(stages.STAGE["localize"], run=boom))
    capsys.readouterr()
    assert gtkit(["run", str(root), "--from", "localize"]) == 1
    out = capsys.readouterr().out
    assert "[localize] failed: the database subset chosen by the settings is empty" in out
    assert "[export_coords] ran in" in out and (root / "exports" / "coordinates").is_dir()   # the run went on
    assert "problem       stage localize failed: the database subset chosen by the settings is empty" in out
    # a deliverable's stage still stops the run (exit 2)
    monkeypatch.setitem(stages.STAGE, "export_coords", replace(stages.STAGE["export_coords"], run=boom))
    assert gtkit(["run", str(root), "--from", "export_coords"]) == 2
