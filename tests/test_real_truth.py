"""Pseudo-GT held to independent truth on real photos (issue 55): the shared fountain-P11 set (11
terrestrial photos, 3072 x 2048, no EXIF, camera poses surveyed independently of any SfM), held out
as ``../shared/tools/truth_split.py`` makes it (two photos in three the reference with their
surveyed centres, every third a query sequence with RTK-like positions: 2 cm noise), then
``gtkit init`` + ``gtkit run --until report`` as a user runs them, defaults, no clicks, and the
shared tool's own judgement of the poses and sigma against the truth.

Asserted (the issue's done-when): every query photo registered has a sigma, at least 90 % lie within
2 sigma of the truth, and the query median is no worse than one plain SfM of all 11 photos with
positions for the reference only (the anchor, benchmarks/bench_real_truth.py: 4.0 mm median) within
its run-to-run spread (a few mm). Measured (stop 62: both blocks' features at 3200 px, the sigma
checked against the reference photos' positions; stop 63: the pose-prior BA converged): 3.0 mm median;
stop 64, the query photos co-estimated with the reference block: 3.4 mm, 4 of 4 within 2 sigma; stop 67,
the self-calibrated camera calibrated again with them: 3.8 mm, 4 of 4 (benchmarks/bench_real_truth.py,
docs/benchmarks.md "Real photos with independent truth"). About
50 s on 2 idle cores. Without positions and with the calibrated K: the benchmark,
and behind GTKIT_SLOW=1 here.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.bench_real_truth import exact_medians
from conftest import ROOT, SHARED

TRUTH_SPLIT = SHARED / "tools" / "truth_split.py"
FOUNTAIN = SHARED / "data" / "real_truth" / "fountain-P11"
pytestmark = pytest.mark.skipif(not (FOUNTAIN / "images").is_dir() or not TRUTH_SPLIT.is_file(),
                                reason="shared real-truth set or truth_split.py not available")
ANCHOR_MEDIAN_M = 0.0040     # one SfM of all photos, reference positions only (issue 55's table)
ANCHOR_SPREAD_M = 0.0020     # "within the anchor's own run-to-run spread, a few mm"


def _held_out(tmp: Path, *extra: str, toml: str = "", set_dir: Path = FOUNTAIN) -> dict:
    """truth_split make + gtkit init (+ ``toml`` appended to project.toml) + gtkit run --until report;
    the eval's summary as a dict."""
    out = tmp / "split"
    made = subprocess.run([sys.executable, str(TRUTH_SPLIT), "make", str(set_dir), str(out), *extra],
                          capture_output=True, text=True, check=True)
    init = made.stdout.strip().splitlines()[-1].split()[1:]     # "gtkit init PROJECT --reference ..."
    gtkit = [sys.executable, "-m", "gtkit.cli"]
    subprocess.run(gtkit + init, check=True, capture_output=True, cwd=ROOT)
    project = init[1]
    if toml:
        with open(Path(project) / "project.toml", "a") as f:
            f.write(toml)
    run = subprocess.run(gtkit + ["run", project, "--until", "report"], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    ev = subprocess.run([sys.executable, str(TRUTH_SPLIT), "eval", str(set_dir), project],
                        capture_output=True, text=True, check=True).stdout
    f = ev.strip().splitlines()[-1].split()
    assert f[0] == "summary", ev
    return {"n": int(f[1]), "median_m": float(f[2]), "worst_m": float(f[4]), "n_sigma": int(f[5]),
            "within_2sigma": float(f[6]), "ref_median_m": float(f[7]), "text": ev, "run": run.stdout,
            "exact": exact_medians(set_dir, Path(project))}


def _check(s: dict, n_held: int, anchor_m: float = ANCHOR_MEDIAN_M) -> None:
    assert s["n"] == n_held, s["text"]                                  # every held-out photo registered
    assert s["n_sigma"] == s["n"], s["text"]                            # ... each with a sigma
    assert s["within_2sigma"] >= 0.9, s["text"]
    assert s["median_m"] <= anchor_m + ANCHOR_SPREAD_M, s["text"]
    assert "unverified" not in s["run"].lower(), s["run"]


def test_fountain_held_out_with_rtk_positions(tmp_path):
    _check(_held_out(tmp_path, "--query-positions", "0.02"), 4)
    work = tmp_path / "split" / "project" / "work"
    # 7 reference photos of 3072 px: both blocks find their features at 3200 px (blocks.block_feature_settings)
    for stage in ("sfm_reference", "sfm_queries/seq"):
        rec = json.loads((work / stage / "stage.json").read_text())
        assert rec["settings"]["features"]["max_image_size"] == 3200, stage
    # ... and the sigma is checked against the reference photos' own positions (k^2, real_photo_terms)
    reg = json.loads((work / "register" / "registration.json").read_text())
    terms = [v["sigma_terms"] for v in reg["images"].values()]
    assert all((t.get("reference_k2_factor") or 0) > 1.0 and t.get("k2_factor") == t["reference_k2_factor"]
               for t in terms), terms
    # the 4 query photos co-estimated with the 7 reference photos (register.coestimate), each moved from
    # the joint adjustment's pose by less than its sigma, the move part of it; the report says so
    assert reg["coestimation"]["applied"] and reg["coestimation"]["n_photos"] == 4, reg["coestimation"]
    assert all(0 < v["coestimated_moved_m"] == v["sigma_terms"]["coestimation_m"] < v["sigma_pos_m"]
               for v in reg["images"].values()), reg["images"]
    md = (tmp_path / "split" / "project" / "reports" / "gt_report.md").read_text()
    assert "| query photos co-estimated with the reference block | 4 photos, moved" in md, md


@pytest.mark.skipif(os.environ.get("GTKIT_SLOW") != "1", reason="GTKIT_SLOW=1: the other cases of the benchmark")
@pytest.mark.parametrize("extra", [(), ("--known-intrinsics", "--query-positions", "0.02")],
                         ids=["no-metadata", "known-K-rtk"])
def test_fountain_held_out_other_cases(tmp_path, extra):
    s = _held_out(tmp_path, *extra)
    _check(s, 4)
    query, ref = s["exact"]
    if "--known-intrinsics" in extra and query > 1.5 * ref:
        # with the calibrated K: within 1.5 x the reference block's own median, the clause that is
        # not met (stop 68: 3.05 mm against 1.5 x 1.97 = 2.95; the images' own limit is 2.6 mm)
        pytest.xfail(f"issue 55's 1.5 x clause: query median {1000 * query:.2f} mm, reference {1000 * ref:.2f} mm")


@pytest.mark.skipif(os.environ.get("GTKIT_SLOW") != "1", reason="GTKIT_SLOW=1: a whole run without a model")
def test_fountain_without_a_model_still_has_a_pseudo_gt(tmp_path):
    """No photo has stereo neighbours (the model's baseline window made impossible, as on the issue's
    19-photo set): the model stage is skipped with its reason, the pseudo-GT ties stay on the
    reference SfM's points, and the report says the model was not used."""
    s = _held_out(tmp_path, "--query-positions", "0.02", toml="\n[model_build]\nbaseline_ratio = [0.0, 0.0001]\n")
    assert "no model can be built" in s["run"], s["run"]
    _check(s, 4)
    md = (tmp_path / "split" / "project" / "reports" / "gt_report.md").read_text()
    assert "not judged: no reference model" in md, md


@pytest.mark.skipif(os.environ.get("GTKIT_SLOW") != "1", reason="GTKIT_SLOW=1: the shared entry-P10 set held out")
def test_entry_held_out_self_calibrated(tmp_path):
    """entry-P10 (10 facade photos), every third held out without metadata, the camera calibrated by
    the 7 reference photos alone: the case nearest the anchor bound. Anchor: 13.10 mm (one SfM of all
    10 photos, principal point refined; spread 0.35 mm over 3 seeds). Measured: 14.5 mm, 3 of 3 within
    2 sigma (stop 64, co-estimated with the reference block; stop 63: 14.7 mm, the reference block's
    pose-prior BA run to convergence; 16.1 mm when it stopped at a 1e-7 cost change)."""
    s = _held_out(tmp_path, set_dir=SHARED / "data" / "real_truth" / "entry-P10")
    _check(s, 3, anchor_m=0.0131)


@pytest.mark.skipif(os.environ.get("GTKIT_SLOW") != "1", reason="GTKIT_SLOW=1: the shared entry-P10 set held out")
def test_entry_every_fourth_whose_positions_mislead_the_metadata_matching(tmp_path):
    """entry-P10, every fourth photo held out with RTK-like positions and K known: the 3 held-out photos
    lie on a near line (19 m long, 0.2 m off it), so their block's GPS fit can turn about that line by
    degrees and matching around those poses places 1 photo of 3. The photos' own keypoints, matched with
    every reference photo as for photos without metadata, place all three. Before (stop 65's bench):
    not registered, clicks asked for; after: 3.1 mm, 3 of 3 within 2 sigma (the same as without positions)."""
    s = _held_out(tmp_path, "--every", "4", "--known-intrinsics", "--query-positions", "0.02",
                  set_dir=SHARED / "data" / "real_truth" / "entry-P10")
    _check(s, 3, anchor_m=0.0060)     # the anchor: 5.97 mm (stop 64, one seed)
    reg = json.loads((tmp_path / "split" / "project" / "work" / "register" / "registration.json").read_text())
    auto = reg["sequences"]["seq"]["automatic"]
    assert "agree on one Sim(3)" in auto["metadata_guided_failed"] and auto["n_photos_agreeing"] == 3, auto


def _some_photos(src: Path, dst: Path, picked: slice) -> Path:
    """A real-truth set of the ``picked`` photos of ``src``'s sorted list (linked), in the same layout."""
    names = sorted(p.name for p in (src / "images").iterdir())[picked]
    (dst / "images").mkdir(parents=True)
    for name in names:
        (dst / "images" / name).symlink_to(src / "images" / name)
    (dst / "K.txt").write_text((src / "K.txt").read_text())
    for f in ("geo.txt", "truth.txt"):
        lines = (src / f).read_text().splitlines()
        keep = [ln for ln in lines if ln.split() and (ln.split()[0] in names or ln.startswith("EPSG"))]
        (dst / f).write_text("\n".join(keep) + "\n")
    return dst


def test_eight_facade_photos_whose_depth_maps_agree_nowhere_still_have_a_pseudo_gt(tmp_path):
    """entry-P10's first 8 photos (the issue's 8-photo case: 5 reference photos, 3 held out): the
    reference photos' stereo neighbours are too far apart for their depth maps to agree (fusion
    keeps 0 points). The model stage is skipped with that reason (it used to stop the main job), and
    the pseudo-GT is made on the reference SfM's points: 12.4 mm median against the anchor's 12.0 mm
    (one SfM of the 8 photos, self-calibrated), 3 of 3 within 2 sigma."""
    entry = SHARED / "data" / "real_truth" / "entry-P10"
    s = _held_out(tmp_path, "--query-positions", "0.02", set_dir=_some_photos(entry, tmp_path / "entry8", slice(8)))
    assert "no model can be built" in s["run"] and "depth maps do not agree" in s["run"], s["run"]
    _check(s, 3, anchor_m=0.0120)


def test_two_held_out_photos_too_far_apart_for_their_own_sfm_are_placed_by_their_keypoints(tmp_path):
    """fountain-P11's every second photo (6 photos, 36 deg apart): the 2 held-out photos, without
    metadata and without EXIF, share too little for their sequence's SfM to start ("no initial pair
    found"). Each is registered into the reference block by its own keypoints, matched with every
    reference photo, its camera the reference block's calibration of the same sensor. Before (stop 66):
    not registered ("no query-block model", a false cause: the camera had no EXIF focal), and with K
    known, clicks asked for ("no GPS to guide matching"). After: 1.7 mm median, 2 of 2 within 2 sigma;
    one SfM of all 6 photos gives 1.35 mm (principal point refined; benchmarks/bench_real_truth.py)."""
    s = _held_out(tmp_path, set_dir=_some_photos(FOUNTAIN, tmp_path / "fountain_wide", slice(0, None, 2)))
    _check(s, 2, anchor_m=0.00135)
    reg = json.loads((tmp_path / "split" / "project" / "work" / "register" / "registration.json").read_text())
    seq = reg["sequences"]["seq"]
    assert seq["registered_by"] == "single photos (its SfM made no model)", seq
    assert all(r["from"] == "automatic matches" for r in seq["left_out_by_sfm"].values()), seq


def test_three_reference_photos_that_misjudge_their_principal_point_are_recalibrated_with_the_queries(tmp_path):
    """entry-P10's every second photo split every second (3 reference photos, 2 held out, no metadata,
    self-calibrated): the 3 reference photos share 138 points and put their principal point 74 and 139 px
    off the calibrated one; placed with that calibration, the 2 query photos were 1.02 m off with a sigma
    of 0.31 m, reported as registered (stop 66). The query photos are of the same sensor: co-estimated
    with the block as that camera, whose calibration the block's BA refines from every photo (as one SfM
    of all 5 photos does), they are 5.7 mm off (one SfM of all 5 photos: 6.8 mm, principal point
    refined), within 2 sigma."""
    entry = SHARED / "data" / "real_truth" / "entry-P10"
    s = _held_out(tmp_path, "--every", "2", set_dir=_some_photos(entry, tmp_path / "entry_wide", slice(0, None, 2)))
    _check(s, 2, anchor_m=0.0068)
    reg = json.loads((tmp_path / "split" / "project" / "work" / "register" / "registration.json").read_text())
    co = reg["coestimation"]
    assert co["applied"] and co["calibrated"], co
    k = (SHARED / "data" / "real_truth" / "entry-P10" / "K.txt").read_text().split()
    pp = [float(v) for v in k[2:4]]
    for cam in co["calibrated"].values():   # COLMAP's pixel centre (0.5, 0.5) against K.txt's (0, 0)
        assert abs(cam["after"][1] - 0.5 - pp[0]) < 15 and abs(cam["after"][2] - 0.5 - pp[1]) < 15, cam


def test_three_reference_photos_off_their_positions_by_more_than_3_sigma_are_held_by_them(tmp_path):
    """entry-P10's every second photo split every second with the calibrated K (3 reference photos, 2 held
    out, no metadata): the 3-photo block lies 10-25 mm from its surveyed positions (sigma 7.9 mm from their
    scatter). pycolmap's pose-prior BA first aligns the block to its positions within 3 sigma; with 2 of 3
    inside, that failed and it used none of them, while the record said "held by 3 positions" (residual
    15.2 -> 15.2 mm). The co-estimation then left the photo beyond 3 sigma out of its priors and, with 2
    left, was refused: the query photos kept their joint poses, 22.7 mm off (one SfM of all 5 photos:
    8.4 mm). Now the alignment keeps every photo the block was georegistered to: the reference block is
    held (15.2 -> 7.5 mm from the truth), and so is the co-estimated block: 7.5 mm, within 2 sigma."""
    entry = SHARED / "data" / "real_truth" / "entry-P10"
    s = _held_out(tmp_path, "--every", "2", "--known-intrinsics",
                  set_dir=_some_photos(entry, tmp_path / "entry_wide", slice(0, None, 2)))
    _check(s, 2, anchor_m=0.0084)
    work = tmp_path / "split" / "project" / "work"
    held = json.loads((work / "sfm_reference" / "block.json").read_text())["held_by_positions"]
    assert held["applied"] and held["n_priors"] == 3 and "widened_from_m" in held["alignment"], held
    assert held["residual_median_m"]["after"] < held["residual_median_m"]["before"], held
    co = json.loads((work / "register" / "registration.json").read_text())["coestimation"]
    assert co["applied"] and co["prior_ba"]["n_priors"] == 3, co


@pytest.mark.skipif(os.environ.get("GTKIT_SLOW") != "1", reason="GTKIT_SLOW=1: fountain-P11 with other query photos")
def test_query_photos_of_another_camera_of_the_same_size_keep_their_own_calibration(tmp_path):
    """fountain-P11 whose held-out photos are another camera of the same size (each cropped to its
    central 90 % and enlarged back: a 10 % longer focal, no EXIF either), so the "same sensor" rule
    takes them for the reference camera. Co-estimated as that camera, the block's BA dragged its
    calibration far outside what the reference photos leave open (focal 2759 -> 2774 px, principal point
    59 px; 1,262 in its own variance, limit 18) and placed them 0.76 m off. The check keeps them as their
    own cameras, calibrated from the reference's points: 8.0 mm median, 4 of 4 within 2 sigma."""
    from PIL import Image

    src, dst = FOUNTAIN, tmp_path / "fountain_zoomed"
    (dst / "images").mkdir(parents=True)
    for i, name in enumerate(sorted(p.name for p in (src / "images").iterdir())):
        if i % 3 == 1:   # truth_split's held-out photos
            im = Image.open(src / "images" / name)
            w, h = im.size
            cw, ch = round(0.9 * w), round(0.9 * h)
            x0, y0 = (w - cw) // 2, (h - ch) // 2
            im.crop((x0, y0, x0 + cw, y0 + ch)).resize((w, h), Image.LANCZOS).save(dst / "images" / name, quality=95)
        else:
            (dst / "images" / name).symlink_to(src / "images" / name)
    for f in ("K.txt", "geo.txt", "truth.txt"):
        (dst / f).write_text((src / f).read_text())
    s = _held_out(tmp_path, set_dir=dst)
    _check(s, 4, anchor_m=0.010)   # no anchor applies (one SfM with one camera for both); the stop-67 figure
    reg = json.loads((tmp_path / "split" / "project" / "work" / "register" / "registration.json").read_text())
    co = reg["coestimation"]
    assert co["applied"] and not co["calibrated"] and "another camera" in co["not_joined_reference_camera"]["why"], co
