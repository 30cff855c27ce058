"""Tracking on the small sample site: rig calibration vs truth/rig.json, targets vs truth/targets.csv.

Uses the session's shared ``small_sample`` (generated once); a copy is modified.
"""
import json
import shutil

import pytest

from gtkit.cli import main
from gtkit.evaluate.tracking import evaluate_rig, evaluate_tracking, simulate_detections
from gtkit.project import Project
from gtkit.track import calibrate
from gtkit.track.rig import RigCalibrationSettings
from gtkit.track.tracker import TrackSettings, run as track


@pytest.fixture(scope="module")
def site(small_sample, tmp_path_factory):
    root = tmp_path_factory.mktemp("track") / "site"
    shutil.copytree(small_sample, root, ignore=shutil.ignore_patterns("work", "exports", "reports"))
    return Project.load(root)


def test_rig_calibration_on_the_sample_zoom_camera(site):
    rig = calibrate.run(site, RigCalibrationSettings(max_pairs=14))
    err = evaluate_rig(site.paths)
    print("rig vs truth", err)
    assert rig.info["n_pairs"] >= 5
    assert err["rotation_err_deg"] < 0.1          # true misalignment is ~0.46 deg
    assert abs(err["focal_err_pct"]) < 0.5


def test_targets_on_the_sample_site_with_true_poses(site):
    P = site.paths
    if not P.rig.is_file():
        calibrate.run(site, RigCalibrationSettings(max_pairs=14))
    assert main(["export", "dsm", str(P.root)]) == 0
    n = simulate_detections(P, P.detections, sigma_px=1.0, mode="point")
    assert n >= 5
    s = track(site, TrackSettings(poses=str(P.truth / "poses.txt")))
    rep = evaluate_tracking(P)
    print("tracking (true poses, true foot pixel)", {k: rep[k] for k in ("n_targets", "n_failed",
                                                                         "median_err_h_m", "median_err_3d_m")})
    assert s["n_located"] == rep["n_targets"] - rep["n_failed"]
    assert rep["n_failed"] <= 0.2 * rep["n_targets"]
    # the floor set by the DSM (reference model) and the calibrated rig: well below a metre
    assert rep["median_err_h_m"] < 1.0 and rep["median_err_3d_m"] < 1.0
    assert json.loads(P.tracking_report.read_text())["n_targets"] == n
    failed = [r for r in rep["per_detection"] if r["status"] != "ok"]
    assert all("err_h_m" not in r for r in failed)
