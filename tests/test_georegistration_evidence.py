"""Georegistration decided by evidence on every kind of block (issue 45): surveyed positions are
never overruled by the aerial prior, a level (facade) block held by its positions is plausible,
GCP clicks made on half-size photos are found and scaled, and every refusal is one line.

Function level: ``level_block`` (gtkit.synth.variants), a facade capture as SfM hands it over
(level photos along a short arc or a line, surveyed centres at 5 mm, no attitude) in an arbitrary
frame. Sample level (tiny preset, ~1 min): the ``facade-proxy`` variant (the world turned so the
photos look level at a wall, mm positions in geo.txt) and ``gcp-half`` + ``no-gps``."""
import os
import shutil

import numpy as np
import pytest

from gtkit.evaluate.poses import block_frame_errors
from gtkit.io.poses import read_poses
from gtkit.sfm.gcp_click_scale import detect_click_scale
from gtkit.sfm.georegister import GeoregisterSettings, georegister
from gtkit.sfm.geometry import RegistrationError, model_cameras, model_poses
from gtkit.sfm.plausibility import check_block
from gtkit.synth.variants import apply_variant, level_block, level_block_gcps
from conftest import stage_settings

SLOW = os.environ.get("GTKIT_SLOW") == "1"


def _errors(rec, truth):
    est = model_poses(rec)
    rot = [np.degrees(np.arccos(np.clip((np.trace(est[n].R.T @ truth[n].R) - 1) / 2, -1, 1))) for n in truth]
    pos = [np.linalg.norm(est[n].center - truth[n].center) for n in truth]
    return float(np.max(rot)), float(np.median(pos))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_facade_arc_is_placed_by_its_surveyed_positions(seed):
    """8 level photos along a 50 deg arc 6 m from a wall, centres surveyed (5 mm): placed by the
    positions (a free Sim(3)), not turned by the aerial prior (it was 88 deg before issue 45), and
    plausible (level photos held by their positions)."""
    rec, pos, acc, truth = level_block(seed)
    r = georegister(rec, pos, [], GeoregisterSettings(), acc, {})
    rot, d = _errors(rec, truth)
    assert r["fit"]["mode"] == "free", r["fit"]["why"]
    assert "aerial prior does not apply" in r["fit"]["why"]
    assert rot < 1.0 and d < 0.005, (rot, d)
    assert r["used"] == "gps"
    assert r["plausibility"]["capture"] == "level" and r["plausibility"]["held_by"] == "8 GPS positions"


def test_facade_line_takes_only_its_roll_from_gravity():
    """Photos along a straight line: the positions hold everything but the roll about their own
    line; that axis comes from the level prior (photos upright), the rest from the positions."""
    rec, pos, acc, truth = level_block(0, straight=True)
    r = georegister(rec, pos, [], GeoregisterSettings(), acc, {})
    rot, d = _errors(rec, truth)
    assert r["fit"]["mode"] == "combined", r["fit"]["why"]
    assert "roll about the positions' line" in r["fit"]["why"]
    hold = r["fit"]["decision"]["positions_hold"]
    assert hold["about_line_deg"] > 5 * hold["across_line_deg"]
    assert rot < 2.0 and d < 0.01, (rot, d)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_facade_with_consumer_positions_is_refused_not_laid_flat(seed):
    """11 level photos 8 m from a wall, positions off by 0.5 m with no stated accuracy: they cannot
    hold the tilt, and the aerial prior must not make a floor of the wall (the cameras lie in a
    plane that the level prior holds level): refused in one line naming what holds it."""
    rec, pos, acc, truth = level_block(seed, position_noise_m=0.5, n_photos=11, distance_m=8.0)
    with pytest.raises(RegistrationError) as e:
        georegister(rec, pos, [], GeoregisterSettings(), None, {})
    msg = str(e.value)
    assert "look level" in msg and "GPS positions hold it only to" in msg and "\n" not in msg and len(msg) < 300, msg


def test_level_block_without_evidence_is_refused_naming_it_and_with_it_is_plausible():
    rec, pos, acc, truth = level_block(0)
    georegister(rec, pos, [], GeoregisterSettings(), acc, {})
    f = check_block(rec, {}, held_by="8 GPS positions")
    assert f["capture"] == "level"
    with pytest.raises(RegistrationError) as e:
        check_block(rec, {})
    msg = str(e.value)
    assert "look level" in msg and "no positions or GCPs hold" in msg and "\n" not in msg


def test_surveyed_positions_against_the_aerial_prior_on_a_block_that_looks_down_refuse_with_both_figures():
    """Surveyed positions that tilt a looking-down block 20 deg from the aerial prior: a true
    disagreement (neither can be the whole truth): refused in one line with both figures."""
    from gtkit.sfm.georegister import choose_gps_fit
    from gtkit.sfm.geometry import robust_sim3
    from gtkit.sfm.gravity import Up

    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.linspace(0, 100, 6), np.linspace(0, 80, 5))
    C = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, 60.0)]
    a = np.radians(20.0)
    Rt = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    tgt = C @ Rt.T + rng.normal(0, 0.01, C.shape)        # the positions: the block tilted 20 deg
    free = robust_sim3(C, tgt, 0.05)
    up = Up(np.array([0.0, 0.0, 1.0]), "aerial prior", len(C), 0.5, 0.1)
    with pytest.raises(RegistrationError) as e:
        choose_gps_fit(free, None, object(), up, C, tgt, "auto", rec=None, stated_m=0.01)
    msg = str(e.value)
    assert "\n" not in msg and "20.0 deg" in msg and "aerial prior" in msg and "tilt_from" in msg
    # the same positions without a stated accuracy (consumer GPS): gravity holds the tilt
    ch = choose_gps_fit(free, None, object(), up, C, tgt, "auto", rec=None, stated_m=None)
    assert ch.choice == "gravity" and "state no accuracy" in ch.why


@pytest.mark.parametrize("scale_setting", ["auto", "off"])
def test_half_scale_gcp_clicks_are_found(scale_setting):
    """GCP clicks made on half-size copies of 3072 x 2048 photos: detected (all inside 1536 x 1024,
    reprojection drops by ~2 when doubled); "auto" doubles them and the GCPs place the block (mm);
    "off" refuses in one line naming the scale and the setting that applies it."""
    rec, pos, acc, truth = level_block(1)
    gcps = level_block_gcps(truth, scale=0.5)
    cs = detect_click_scale(gcps, model_cameras(rec), model_poses(rec))
    assert cs is not None and cs.factor == 2.0 and cs.confirmed, cs
    assert cs.after_px < cs.before_px / 10, cs
    s = GeoregisterSettings(use="gcp", gcp_click_scale=scale_setting)
    if scale_setting == "auto":
        r = georegister(rec, {}, gcps, s, None, None)
        rot, d = _errors(rec, truth)
        assert r["gcp_click_scale"]["applied"] and r["gcp_click_scale"]["factor"] == 2.0
        assert r["used"] == "gcp" and r["n_inliers"] >= 5
        assert rot < 0.5 and d < 0.05, (rot, d)   # 2-px clicks (1 px at half size), 6 GCPs on 8 x 4 m
    else:
        with pytest.raises(RegistrationError) as e:
            georegister(rec, {}, gcps, s, None, None)
        msg = str(e.value)
        assert "\n" not in msg and "1/2-size photos" in msg and 'gcp_click_scale = "2"' in msg, msg
        assert len(msg) < 400, len(msg)


def test_full_size_clicks_are_not_scaled():
    rec, pos, acc, truth = level_block(2)
    gcps = level_block_gcps(truth)
    assert detect_click_scale(gcps, model_cameras(rec), model_poses(rec)) is None
    r = georegister(rec, pos, gcps, GeoregisterSettings(), acc, None)
    assert r["gcp_click_scale"] is None and r["used"] == "gps+gcp"
    assert r["gcp_click_threshold"]["max_px"] >= 4.0 * 3692 / 2000 - 0.1   # 4 px per 2,000 px of diagonal


def test_gcps_without_clicks_in_the_model_one_line_per_cause():
    """10 GCPs whose clicks are in photos of another model: one clause, not one per GCP."""
    rec, pos, acc, truth = level_block(0)
    gcps = level_block_gcps(truth, n_gcps=10)
    for g in gcps:
        for c in g.clicks:
            c.image = "other/" + c.image
    with pytest.raises(RegistrationError) as e:
        georegister(rec, {}, gcps, GeoregisterSettings(use="gcp"), None, None)
    msg = str(e.value)
    assert "no GCP has 2 clicks in this model's 8 photos (10 GCPs)" in msg, msg
    assert "\n" not in msg and len(msg) < 300, (len(msg), msg)


def _copy(tiny_sample, tmp_path, *variants, seed=0):
    root, _, _ = tiny_sample
    dst = tmp_path / "site"
    shutil.copytree(root, dst, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    for v in variants:
        apply_variant(dst, v, seed=seed)
    return dst


def test_facade_proxy_sample_is_placed_by_its_positions(tiny_sample, tmp_path):
    """The tiny sample turned into a wall (photos looking level at it), surveyed centres in geo.txt
    (5 mm, accuracy columns), no EXIF GPS / attitude, no GCPs: SfM + georegistration place it by
    the positions (it was turned ~90 deg by the aerial prior before issue 45), within mm and a
    fraction of a degree of the truth, and the report does not call it level-refused."""
    from gtkit.sfm.blocks import run_reference

    root = _copy(tiny_sample, tmp_path, "facade-proxy")
    r = run_reference(root, stage_settings("sfm_reference", root))   # defaults: the pose-prior BA after it is undone where it moves the block off
    geo = r["georegistration"]
    assert "error" not in geo, geo
    assert geo["used"] == "gps" and geo["plausibility"]["capture"] == "level"
    e = block_frame_errors(read_poses(root / "work/sfm_reference/poses.txt"), read_poses(root / "truth/poses.txt"))
    # the tiny sample's own SfM shape is ~7 cm (640 x 480 photos, 21 cm per pixel): no closer than that
    assert e["tilt_deg"] < 0.2 and e["horizontal_m"] < 0.15 and e["vertical_m"] < 0.15, e
    assert e["shape_m"] < 0.15, e


@pytest.mark.skipif(not SLOW, reason="GTKIT_SLOW=1: the tiny sample with half-size GCP clicks (~1 min)")
def test_half_scale_clicks_on_the_sample(tiny_sample, tmp_path):
    from gtkit.sfm.blocks import run_reference

    root = _copy(tiny_sample, tmp_path, "no-gps", "gcp-half")
    r = run_reference(root, stage_settings("sfm_reference", root))
    geo = r["georegistration"]
    assert "error" not in geo, geo
    assert geo["gcp_click_scale"]["applied"] and geo["gcp_click_scale"]["factor"] == 2.0
    assert geo["used"] == "gcp"
    e = block_frame_errors(read_poses(root / "work/sfm_reference/poses.txt"), read_poses(root / "truth/poses.txt"))
    assert e["tilt_deg"] < 1.0 and e["horizontal_m"] < 1.0, e


def test_pose_prior_ba_keeps_surveyed_positions(tiny_sample, tmp_path):
    """The pose-prior BA that follows a free georegistration keeps a surveyed block on its positions (its
    alignment RANSAC's threshold at 3 sigma of the positions: left at 0 it moved this block 0.069 -> 5.46 m
    off them, the suite's xfail until issue 55)."""
    from gtkit.sfm.blocks import run_reference

    root = _copy(tiny_sample, tmp_path, "facade-proxy")
    r = run_reference(root, stage_settings("sfm_reference", root))
    h = r["held_by_positions"]   # blocks.py undoes a BA that moves the block off ("reverted"): still a failure here
    assert h["applied"] and h["residual_median_m"]["after"] <= h["residual_median_m"]["before"] + 0.01, h


def test_click_threshold_follows_the_clicks_and_the_photo_size():
    """Clicks 5 px off (1 sigma) on 3072 x 2048 photos: a fixed 4 px throws away good clicks (down to
    2 of 8 per GCP) and doubles the GCP error; the threshold from the clicks' own consistency (3
    robust sigmas, >= 4 px per 2,000 px of diagonal) keeps every click and places the block closer."""
    out = {}
    for thr in (4.0, None):
        rec, pos, acc, truth = level_block(0)
        gcps = level_block_gcps(truth, n_gcps=8, click_px=5.0)
        r = georegister(rec, {}, gcps, GeoregisterSettings(use="gcp", gcp_max_px=thr), None, None)
        kept = [v["clicks_used"] / v["clicks_total"] for v in r["gcp_residuals"].values() if v["status"] == "ok"]
        out[thr] = (r, min(kept), _errors(rec, truth))
    r, kept, (rot, d) = out[None]
    assert r["gcp_click_threshold"]["max_px"] > 4.0 * 3692 / 2000 and r["gcp_click_threshold"]["click_sigma_px"] > 3.0
    assert kept == 1.0 and out[4.0][1] < 0.5
    assert r["gcp_rmse_m"] < 0.7 * out[4.0][0]["gcp_rmse_m"], (r["gcp_rmse_m"], out[4.0][0]["gcp_rmse_m"])
    assert rot < 1.0 and d < 0.1, (rot, d)
