"""The absolute accuracy a georegistered block claims comes from the evidence (issue 57): the
stated accuracy where given, else the fit's leave-one-out error (and check points), else the
source's typical accuracy; the claim names its source and covers the block's true offset.

"Covers": the block's median horizontal / vertical camera-centre offset from the truth within 3 x
the 1-sigma claim (gtkit.evaluate.gt_report.claim_covers)."""
import io
from contextlib import redirect_stdout

import numpy as np
import pytest

from gtkit.evaluate.gt_report import claim_covers
from gtkit.evaluate.poses import block_frame_errors
from gtkit.io.poses import read_poses
from gtkit.sfm.geometry import model_poses
from gtkit.sfm.accuracy_claim import accuracy_claim
from gtkit.sfm.georegister import GeoregisterSettings, georegister
from gtkit.synth.variants import level_block, level_block_gcps
from conftest import stage_settings
from test_georegister_consumer import _consumer_copy as _copy  # the tiny sample copied with variants


def _covered(rec, truth, claim) -> dict:
    e = block_frame_errors(model_poses(rec), truth)
    cov = claim_covers(e["horizontal_m"], e["vertical_m"], claim)
    assert cov["covered"], (cov, claim)
    return cov


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stated_accuracy_is_the_claim(seed):
    """Positions with accuracy columns (5 mm, 3 mm noise): the claim is the stated 5 mm, said so."""
    rec, pos, acc, truth = level_block(seed, n_photos=12)
    c = georegister(rec, pos, [], GeoregisterSettings(), acc, {})["claimed_accuracy"]
    assert c["source"] == "stated" and c["h_m"] == c["v_m"] == 0.005, c
    assert "the stated accuracy of 12 GPS positions" in c["line"]
    _covered(rec, truth, c)


def test_stated_gcp_accuracy_is_the_claim():
    """GCPs with a stated accuracy (the points file's columns, passed per GCP): the claim is theirs."""
    rec, _, _, truth = level_block(0)
    gcps = level_block_gcps(truth, n_gcps=8, seed=0)
    c = georegister(rec, {}, gcps, GeoregisterSettings(use="gcp"),
                    gcp_accuracy={g.name: (0.02, 0.04) for g in gcps})["claimed_accuracy"]
    assert c["source"] == "stated" and (c["h_m"], c["v_m"]) == (0.02, 0.04), c
    _covered(rec, truth, c)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_surveyed_positions_without_accuracy_columns_claim_their_fit(seed):
    """20 surveyed positions (8 mm noise) without accuracy columns: the claim comes from the fit's
    leave-one-out error (about 1 cm), not a consumer GPS's ~2 m / 5 m, and covers the truth."""
    rec, pos, _, truth = level_block(seed, n_photos=20, position_noise_m=0.008)
    c = georegister(rec, pos, [], GeoregisterSettings(), None, {})["claimed_accuracy"]
    assert c["source"] == "leave-one-out" and not c["weak"], c
    assert 0.005 < c["h_m"] < 0.02 and 0.005 < c["v_m"] < 0.02, c
    assert c["evidence"]["leave_one_out_h_m"] > 0.006   # the 8 mm noise, not the fit's smaller residuals
    _covered(rec, truth, c)


def test_contradicted_stated_accuracy_gives_way_to_the_fit():
    """Positions stated at 5 mm that scatter by 5 cm: the claim is the fit's, saying so."""
    rec, pos, acc, truth = level_block(1, n_photos=20, position_noise_m=0.05)
    c = georegister(rec, pos, [], GeoregisterSettings(), acc, {})["claimed_accuracy"]
    assert c["source"] in ("leave-one-out", "gravity-held fit") and "contradicts" in c["detail"], c
    assert c["h_m"] > 0.03, c
    _covered(rec, truth, c)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_check_points_enter_the_claim(seed):
    """8 GCPs on the wall (1 px clicks), 2 of them check points: the check points' error is part of the
    evidence, the claim is never under it and covers the cameras' offset."""
    rec, _, _, truth = level_block(seed)
    gcps = level_block_gcps(truth, n_gcps=8, seed=seed)
    for g in gcps[:2]:
        g.check = True
    geo = georegister(rec, {}, gcps, GeoregisterSettings(use="gcp"))
    c = geo["claimed_accuracy"]
    assert c["evidence"]["n_checkpoints"] == 2 and c["evidence"]["n_points"] == 6
    assert c["h_m"] >= c["evidence"]["checkpoints_h_m"] and c["v_m"] >= c["evidence"]["checkpoints_v_m"]
    assert c["h_m"] < 0.05 and c["v_m"] < 0.05, c
    _covered(rec, truth, c)


def test_few_points_are_weak_and_three_fall_back_to_typical():
    rng = np.random.default_rng(0)
    X = rng.uniform(-50, 50, (5, 3))
    tgt = X + rng.normal(0, 0.01, X.shape)
    common = dict(weights=None, cameras=X + [0, 0, 80.0], fit_mode="free", gps_quality=None, checkpoints=[])
    c5 = accuracy_claim(kinds=np.array(["gcp"] * 5), inliers=np.ones(5, bool), src=X, tgt=tgt,
                        stated=[None] * 5, **common)
    assert c5["source"] == "leave-one-out" and c5["weak"] and "weak: only 5 points" in c5["line"], c5
    c3 = accuracy_claim(kinds=np.array(["gcp"] * 3), inliers=np.ones(3, bool), src=X[:3], tgt=tgt[:3],
                        stated=[None] * 3, **common)
    assert c3["source"] == "typical" and c3["weak"] and "mark a check point" in c3["line"], c3
    g3 = accuracy_claim(kinds=np.array(["gps"] * 3), inliers=np.ones(3, bool), src=X[:3], tgt=tgt[:3],
                        stated=[None] * 3, **common)
    assert g3["source"] == "typical" and (g3["h_m"], g3["v_m"]) == (2.0, 5.0), g3


def test_consumer_gps_block_claims_a_gps_bias_that_covers_the_truth(tiny_sample, tmp_path):
    """The tiny sample with consumer GPS (~10 m, altitude drifting 60 m), no GCPs: the claim adds a
    GPS's typical bias to the positions' scatter, names it, covers the true offset; the reference
    report, `gtkit sfm`'s printout and the run summary print the same claim."""
    from gtkit.commands.run import print_summary
    from gtkit.project import Project
    from gtkit.run_site import collect
    from gtkit.commands.sfm import _print_reference
    from gtkit.sfm.blocks import run_reference

    root = _copy(tiny_sample, tmp_path, "consumer-gps", "no-gcps")
    r = run_reference(root, stage_settings("sfm_reference", root))
    c = r["georegistration"]["claimed_accuracy"]
    assert "typical GPS bias" in c["source"] and c["h_m"] >= 2.0 and c["v_m"] >= 5.0, c
    e = block_frame_errors(read_poses(root / "work/sfm_reference/poses.txt"), read_poses(root / "truth/poses.txt"))
    cov = claim_covers(e["horizontal_m"], e["vertical_m"], c)
    assert cov["covered"], cov
    md = (root / "reports/reference.md").read_text()
    assert "absolute accuracy the site can claim: ~" in md and "typical GPS bias" in md
    out = io.StringIO()
    with redirect_stdout(out):
        _print_reference(r)
        print_summary(collect(Project.load(root), []))
    assert out.getvalue().count(c["line"]) == 1 and c["short"] in out.getvalue(), out.getvalue()


def test_surveyed_geo_txt_without_accuracy_columns_on_the_sample(tiny_sample, tmp_path):
    """The tiny sample placed by a geo.txt of surveyed camera centres (8 mm noise) without accuracy
    columns, no EXIF GPS, no GCPs: the claim comes from the fit (centimetres, not ~2 m / 5 m of a GPS)
    and covers the block's true offset; the GT report states it and judges it against the truth."""
    from gtkit.evaluate import gt_report
    from gtkit.sfm.blocks import run_reference

    root = _copy(tiny_sample, tmp_path, "survey-geo", "no-gps", "no-gcps")
    lines = (root / "geo.txt").read_text().splitlines()
    rng = np.random.default_rng(5)
    out = [lines[0]]
    for ln in lines[1:]:
        f = ln.split()
        xyz = np.array(list(map(float, f[1:4]))) + rng.normal(0, 0.008, 3)
        out.append(f"{f[0]} {xyz[0]:.4f} {xyz[1]:.4f} {xyz[2]:.4f}")   # no accuracy columns
    (root / "geo.txt").write_text("\n".join(out) + "\n")
    r = run_reference(root, stage_settings("sfm_reference", root))
    c = r["georegistration"]["claimed_accuracy"]
    assert c["source"] == "leave-one-out" and c["h_m"] < 0.1 and c["v_m"] < 0.1, c
    e = block_frame_errors(read_poses(root / "work/sfm_reference/poses.txt"), read_poses(root / "truth/poses.txt"))
    assert claim_covers(e["horizontal_m"], e["vertical_m"], c)["covered"], (e, c)
    rep = gt_report.run(root, gt_report.ReportSettings())
    assert rep["claim_vs_truth"]["covered"], rep["claim_vs_truth"]
    md = (root / "reports/gt_report.md").read_text()
    assert "site's absolute accuracy (reference block, 1 sigma)" in md and "covered" in md
