"""The whole pseudo-GT pipeline on the generated small sample site, against its truth.

Slow (SfM of 148 photos: about 5-10 minutes on 2 cores), but it is the product's core claim, so CI
runs it on the session's small sample. Measured (seed 0, 2026-11-22, before the reference block was
held by its positions and automatic tie points became 2D-3D; seeds 1-5 now: README "Figures over seeds"):
28/28 query photos, 0.072 m / 0.034 deg median vs truth, 0.24 px reprojection, 0.71 px per tie
point; with 20 % gross click mistakes 0.063 m / 0.031 deg and 49 of 54 bad tie points listed. Reproduce by hand with
``gtkit sample create DIR --preset small && python -m pipelines.pseudo_gt DIR``."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from gtkit.io.tiepoints import read_tiepoints, write_tiepoints
from gtkit.sfm import register
from conftest import stage_settings

# the fixture runs the whole pseudo-GT job on the small sample: 15 min under load here (the joint BA
# with its 2D-3D automatic tie points is most of it), over the suite's 900 s per test
pytestmark = [pytest.mark.slow, pytest.mark.timeout(2400)]


@pytest.fixture(scope="session")
def small(small_sample, tmp_path_factory):
    from pipelines.pseudo_gt import main as pseudo_gt

    root = tmp_path_factory.mktemp("pgt") / "small"
    shutil.copytree(small_sample, root, ignore=shutil.ignore_patterns("work", "exports", "reports"))
    return root, pseudo_gt(str(root))


def test_small_sample_meets_targets(small):
    root, out = small
    rep = json.loads((root / "reports" / "gt_report.json").read_text())
    assert rep["n_registered"] == rep["n_images"] > 0
    # seed 0 in CI at 9e401e9: 0.036 m / 0.015 deg (before the held reference and 2D-3D ties: 0.047 m);
    # seeds 1-5: median 0.048 m, worst 0.056 m (README "Figures over seeds")
    assert rep["median_pos_err_m"] <= 0.06 and rep["median_rot_err_deg"] <= 0.05, rep
    assert rep["median_reproj_px"] <= 1.0
    geo = rep["reference_block"]["georegistration"]
    assert geo["gcp_median_err_m"] is not None and geo["gcp_median_err_m"] < 0.10


def test_reference_block_held_by_its_positions(small):
    """The reference block's RTK positions hold it in its own BA: its cameras against the truth."""
    from gtkit.io.poses import read_poses

    root, _ = small
    held = json.loads((root / "work" / "sfm_reference" / "block.json").read_text())["held_by_positions"]
    assert held["applied"] and held["n_priors"] >= 100 and held["converged"], held
    # the sigma comes from the block's own residuals to the positions: the sample's RTK is 2.5 cm / 3.75 cm
    assert 0.01 <= held["sigma_h_m"] <= 0.06 and 0.01 <= held["sigma_v_m"] <= 0.08, held
    est, true = read_poses(root / "work" / "sfm_reference" / "poses.txt"), read_poses(root / "truth" / "poses.txt")
    err = np.array([np.linalg.norm(est[n].center - true[n].center) for n in est if n in true])
    assert len(err) >= 100 and np.median(err) <= 0.025 and np.percentile(err, 90) <= 0.045, np.percentile(err, [50, 90])


def test_every_query_photo_gets_automatic_tie_points(small):
    """Guided 2D-3D matching to the reference block's points reaches every registered wide photo,
    shallow ones at the block's edge included (the earlier angle-based pairing left whole sequences out)."""
    root, _ = small
    reg = json.loads((root / "work" / "register" / "registration.json").read_text())
    auto = {n: v["n_auto_tiepoints"] for n, v in reg["images"].items()}
    assert len(auto) == reg["n_registered"] > 0
    assert min(auto.values()) >= 30, sorted(auto.items(), key=lambda t: t[1])[:3]


def _perturb(tps, truth, share, keep=(), seed=0):
    """Gross click mistakes (50 px) in reference photos on ``share`` of the tie points ``tps`` (in place),
    none on the ids in ``keep``; returns every badly clicked id (the sample's own mistakes included)."""
    rng = np.random.default_rng(seed)
    bad = {t.id for t in tps if truth[t.id]["gross_mistake"]}
    for t in tps:
        if t.id in bad or rng.uniform() >= share or t.id in keep:
            continue
        refs = [o for o in t.observations if o.image.startswith("reference/")]
        o = refs[rng.integers(len(refs))]
        a = rng.uniform(0, 2 * np.pi)
        o.x, o.y = o.x + 50 * np.cos(a), o.y + 50 * np.sin(a)
        bad.add(t.id)
    return bad


@pytest.fixture(scope="module")
def faulty(small, tmp_path_factory):
    """One register run on a copy with three independent faults (one run, not three: each run of the
    small sample's register is 1.5 min): 20 % of the tie points of seq1 and seq2 have a gross click
    mistake in a reference photo; seq3 has only 2 clicked tie points left; seq2/0004_W (wide) is left
    out by its sequence's SfM with no click on it."""
    import pycolmap

    root, _ = small
    dst = tmp_path_factory.mktemp("faulty") / "p"
    shutil.copytree(root, dst, symlinks=True, ignore=shutil.ignore_patterns("register", "reports"))
    tps = read_tiepoints(dst / "tiepoints.json")
    truth = {t["id"]: t for t in json.loads((root / "truth" / "tiepoints_truth.json").read_text())["tiepoints"]}
    seq3 = [t for t in tps if any(o.image.startswith("queries/seq3/") and "_W" in o.image for o in t.observations)]
    bad = _perturb(tps, truth, 0.2, keep={t.id for t in seq3})
    tps = [t for t in tps if t not in seq3] + seq3[:2]
    name = "queries/seq2/0004_W.jpg"
    model = dst / "work" / "sfm_queries" / "seq2" / "model"
    rec = pycolmap.Reconstruction(model)
    rec.deregister_frame(rec.find_image_with_name(name).frame_id)
    rec.write(model)
    block = dst / "work" / "sfm_queries" / "seq2" / "block.json"
    b = json.loads(block.read_text())
    b["unregistered"] = {name: "left out for this test"}
    block.write_text(json.dumps(b))
    for t in tps:
        t.observations = [o for o in t.observations if o.image != name]
    write_tiepoints(dst / "tiepoints.json", [t for t in tps if t.observations])
    return dst, register.run(dst, stage_settings("register", dst)), [t.id for t in seq3[:2]], name, bad


def test_twenty_percent_gross_mistakes(faulty):
    from gtkit.evaluate import gt_report as report

    dst, res, _, _, bad = faulty
    rep = report.run(dst, stage_settings("report", dst))
    assert rep["n_registered"] == rep["n_images"]
    assert rep["median_pos_err_m"] <= 0.10 and rep["median_rot_err_deg"] <= 0.10, rep
    listed = set(res["bad_tiepoints"])
    wide = {t.id for t in read_tiepoints(dst / "tiepoints.json") if any("_W" in o.image for o in t.observations)}
    wide_bad = bad & wide   # zoom photos are in no block: their tie points are not used
    assert len(wide_bad) >= 0.18 * len(wide)
    assert len(wide_bad & listed) >= 0.8 * len(wide_bad), (len(wide_bad & listed), len(wide_bad))


def test_too_few_tiepoints_fails_that_sequence_only(faulty, tmp_path):
    dst, res, kept, _, _ = faulty
    # too few clicks: the sequence is placed by its photos' automatic matches instead, and says why
    s3 = res["sequences"]["seq3"]
    assert s3["status"] == "registered" and s3["registered_by"] == "automatic matches" and "only" in s3["clicks"], s3
    # its clicks still go into the joint BA, and are counted there as its own
    rows = {i: res["tiepoints"][i] for i in kept if i in res["tiepoints"]}
    assert rows and all(r["sequence"] == "seq3" for r in rows.values()), rows
    assert s3["n_tiepoints_final_ba"] == sum(r["in_final_ba"] for r in rows.values()), (s3, rows)
    # with that turned off, only that sequence fails, with the reason
    off = tmp_path / "off"
    shutil.copytree(dst, off, symlinks=True, ignore=shutil.ignore_patterns("register", "reports"))
    s = register.RegisterSettings()
    s.bootstrap.enabled = False
    res = register.run(off, s, force=True)
    assert res["sequences"]["seq3"]["status"] == "error" and "only" in res["sequences"]["seq3"]["error"]
    assert res["sequences"]["seq1"]["status"] == res["sequences"]["seq2"]["status"] == "registered"


def test_a_left_out_photo_without_clicks_is_resected_from_automatic_matches(small, faulty):
    """A wide photo its sequence's SfM left out and nobody clicked (small seed 17's seq2/0002: 8 clicks,
    5 consistent) is matched to the reference block's points around its metadata pose, then adjusted
    with the rest: it gets a pose, flagged as resected from automatic matches."""
    from gtkit.io.poses import read_poses

    root, _ = small
    dst, res, _, name, _ = faulty
    rec = res["sequences"]["seq2"]["left_out_by_sfm"][name]
    assert rec["resected"] and rec["from"] == "automatic matches" and rec["n_auto_matches"] >= 100, rec
    assert rec["n_clicks"] == 0 and res["images"][name]["resected"]["from"] == "automatic matches"
    est, true = read_poses(dst / "work" / "register" / "poses.txt"), read_poses(root / "truth" / "poses.txt")
    pos, rot = est[name].error_to(true[name])
    assert pos < 0.15 and rot < 0.1, (pos, rot)   # small seed 16 (seq2/0004): 0.083 m, 0.060 deg
