"""One stage table behind every entry point (issue 47), on the tiny sample with real stages.

- The README's main job (``pipelines.full``) and ``gtkit run`` write the same files on a sample
  (the main job adds only its evaluation against truth).
- Parametrised over :data:`gtkit.stages.STAGES`: a setting changed in ``project.toml`` changes that
  stage's output through ``gtkit run --from S --until S`` and through the stage's own command, and
  (every stage's at once) through the main job. The output read back is the stage's product where
  that shows the setting (the DSM's and orthophoto's cell size read by rasterio, the overlay PNGs'
  size), else the settings its record says made it.

About 5 minutes on 2 cores (two main jobs on the tiny sample, each stage run twice more)."""
from __future__ import annotations

import json
import os
import shutil
import tomllib
from fnmatch import fnmatch
from pathlib import Path

import pytest
import tomli_w

from gtkit.cli import main as gtkit
from gtkit.stages import STAGES


def _record(root: Path, folder: str, dotted: str):
    rec = json.loads((root / "work" / folder / "stage.json").read_text())["settings"]
    for k in dotted.split("."):
        rec = rec[k]
    return rec


def _cell(tif: Path) -> float:
    import rasterio

    with rasterio.open(tif) as d:
        return round(float(d.res[0]), 6)


def _overlay_side(root: Path) -> int:
    from PIL import Image

    pngs = sorted((root / "reports" / "overlays").rglob("*.png"))
    newest = max(pngs, key=lambda p: p.stat().st_mtime_ns)
    return max(Image.open(newest).size)


# stage: ([(section, dotted key, three values in turn)], read(root) -> the values now in force, command)
CASES = {
    "sfm_reference": ([("sfm", "features.max_num_features", (2100, 2200, 2300))],
                      lambda r: [_record(r, "sfm_reference", "features.max_num_features")],
                      ["sfm", "{root}", "--block", "reference"]),
    "model": ([("model_build", "max_triangles", (60000, 70000, 80000))],
              lambda r: [_record(r, "model", "max_triangles")], ["model", "build", "{root}", "--use"]),
    "sfm_queries": ([("sfm", "features.max_image_size", (1000, 1100, 1200))],
                    lambda r: [_record(r, "sfm_queries/seq1", "features.max_image_size")],
                    ["sfm", "{root}", "--block", "queries"]),
    "register": ([("register", "tie_max_px", (5.0, 6.0, 7.0))], lambda r: [_record(r, "register", "tie_max_px")],
                 ["register", "{root}"]),
    "report": ([("report", "point_cloud_crs", ("EPSG:32651", "EPSG:32652", "EPSG:32653"))],
               lambda r: [json.loads((r / "reports" / "gt_report.json").read_text())["settings"]["point_cloud_crs"]],
               ["report", "{root}"]),
    "export_dsm": ([("export_dsm", "resolution", (1.5, 2.0, 2.5))], lambda r: [_cell(r / "exports" / "dsm.tif")],
                   ["export", "dsm", "{root}"]),
    "export_ortho": ([("export_ortho", "resolution", (1.5, 2.0, 2.5))],
                     lambda r: [_cell(r / "exports" / "ortho.tif")], ["export", "ortho", "{root}"]),
    "export_mesh": ([("export_mesh", "decimate", (3000, 4000, 5000))], lambda r: [_record(r, "export_mesh_obj", "decimate")],
                    ["export", "mesh", "{root}"]),
    "overlays": ([("overlay", "max_side", (200, 240, 280))], lambda r: [_overlay_side(r)], ["overlay", "{root}"]),
    "render_db": ([("render_db", "yaw_step", (60.0, 120.0, 180.0))], lambda r: [_record(r, "render_db", "yaw_step")],
                  ["render-db", "{root}"]),
    "localize": ([("localize", "top_k", (2, 4, 5))], lambda r: [_record(r, "localize", "top_k")],
                 ["localize", "{root}"]),
    "track": ([("rig", "max_pairs", (30, 35, 38)), ("track", "foot_point", ("bottom_centre", "centre", "bottom_centre"))],
              lambda r: [_record(r, "rig", "max_pairs"), _record(r, "track", "foot_point")],
              [["track", "calibrate", "{root}"], ["track", "{root}"]]),
    "export_coords": ([("export_coordinates", "include_gcps", (False, True, False))],
                      lambda r: [_record(r, "export_coordinates", "include_gcps")], ["export", "coords", "{root}"]),
}
SLOW = {"model"}     # a model build on the tiny sample takes minutes (GTKIT_SLOW=1)


def _set(root: Path, stage: str, turn: int) -> list:
    """Write the stage's ``turn``-th values into project.toml; returns them."""
    f = root / "project.toml"
    cfg = tomllib.loads(f.read_text())
    for section, dotted, values in CASES[stage][0]:
        d = cfg.setdefault(section, {})
        *parents, leaf = dotted.split(".")
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = values[turn]
    f.write_text(tomli_w.dumps(cfg))
    return [values[turn] for _s, _k, values in CASES[stage][0]]


def _main_job(root: Path) -> dict:
    from pipelines.full import main as main_job

    return main_job(root)


@pytest.fixture(scope="module")
def by_main_job(tiny_sample, tmp_path_factory):
    root = tmp_path_factory.mktemp("stages") / "main_job"
    shutil.copytree(tiny_sample[0], root)
    _main_job(root)
    return root


@pytest.fixture(scope="module")
def by_gtkit_run(tiny_sample, by_main_job, tmp_path_factory):
    """The same sample through ``gtkit run``, with the main job's simulated detections (its only
    input the run does not make: the sample's stand-in for a detector)."""
    root = tmp_path_factory.mktemp("stages") / "gtkit_run"
    shutil.copytree(tiny_sample[0], root)
    shutil.copy(by_main_job / "detections.csv", root / "detections.csv")
    assert gtkit(["run", str(root)]) == 0
    return root


EVALUATION_ONLY = {"reports/summary.json", "reports/localization.json", "reports/localization.md",
                   "reports/tracking.json", "reports/tracking.md", "reports/tracking.png"}


def _outputs(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for top in ("work", "exports", "reports") for p in (root / top).rglob("*")
            if p.is_file() and p.name != "log.txt"}


def test_the_main_job_and_gtkit_run_write_the_same_files(by_main_job, by_gtkit_run):
    a, b = _outputs(by_main_job), _outputs(by_gtkit_run)
    assert a - EVALUATION_ONLY == b, (sorted(a - EVALUATION_ONLY - b), sorted(b - a))
    assert EVALUATION_ONLY <= a
    for stage in STAGES:       # every stage ran (or was skipped) alike, for the same reason
        sa = json.loads((by_main_job / "reports/run.json").read_text())["stages"][stage.name]
        sb = json.loads((by_gtkit_run / "reports/run.json").read_text())["stages"][stage.name]
        assert (sa["status"], sa.get("why")) == (sb["status"], sb.get("why")), stage.name
    # the same photos posed by both, in the same exported files
    cams = [sorted(ln.split(",")[0] for ln in (r / "exports/coordinates/cameras.csv").read_text().splitlines()[1:])
            for r in (by_main_job, by_gtkit_run)]
    assert cams[0] == cams[1] and len(cams[0]) > 40


RUN_OWN = ("reports/run.json", "work/errors/", "work/.lock")   # gtkit run's summary, tracebacks, the project lock


def test_the_table_says_what_each_stage_writes(by_gtkit_run):
    """Every file of a run lies under the `writes` of a stage that ran (or is the run's own), and
    every path a stage that ran declares is there: the table is a true map of the project folder."""
    rows = json.loads((by_gtkit_run / "reports/run.json").read_text())["stages"]
    ran = [s for s in STAGES if rows[s.name]["status"] in ("ran", "up to date")]
    declared = [w for s in ran for w in s.writes] + list(RUN_OWN)
    stray = [f for f in _outputs(by_gtkit_run) if not any(fnmatch(f, w + "*" if w.endswith("/") else w)
                                                          for w in declared)]
    assert not stray, f"files no stage of the table declares: {sorted(stray)[:10]}"
    for s in ran:
        missing = [w for w in s.writes if not any(by_gtkit_run.glob(w.rstrip("/")))]
        assert not missing, (s.name, missing)


@pytest.fixture(scope="module")
def site(by_gtkit_run, tmp_path_factory):
    """A finished project the settings tests change (a copy: the comparison above keeps its own)."""
    root = tmp_path_factory.mktemp("stages") / "site"
    shutil.copytree(by_gtkit_run, root)
    return root


@pytest.mark.parametrize("stage", [s.name for s in STAGES])
def test_a_project_setting_reaches_the_stage_through_gtkit_run_and_its_command(site, stage):
    if stage in SLOW and os.environ.get("GTKIT_SLOW") != "1":
        pytest.skip("a model build takes minutes on the tiny sample: GTKIT_SLOW=1")
    assert set(CASES) == {s.name for s in STAGES}       # every stage of the table has its case
    _, read, command = CASES[stage]

    def by_run():
        assert gtkit(["run", str(site), "--from", stage, "--until", stage]) == 0

    def by_command():
        for cmd in command if isinstance(command[0], list) else [command]:
            assert gtkit([c.format(root=site) for c in cmd]) == 0

    # the sample's model is delivered: `gtkit run` builds one only once the built one is the project's
    order = [("its command", by_command), ("gtkit run", by_run)] if stage == "model" else \
        [("gtkit run", by_run), ("its command", by_command)]
    for turn, (how, entry) in enumerate(order):
        want = _set(site, stage, turn)
        entry()
        assert read(site) == want, f"{how}: {stage}"


def test_every_stage_setting_reaches_the_stage_through_the_main_job(site):
    stages = [s for s in CASES if s not in SLOW or os.environ.get("GTKIT_SLOW") == "1"]
    want = {s: _set(site, s, 2) for s in stages}
    _main_job(site)
    got = {s: CASES[s][1](site) for s in stages}
    assert got == want
