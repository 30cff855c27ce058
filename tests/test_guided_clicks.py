"""Guided clicks (gtkit.sfm.guided_clicks) and the calibrated sigma of the registration (issue 35).

Measured on the hand-built synthetic site of test_register (seconds, no images): the guidance puts a
click in the sequence's least held photo before one in its best held photo, and re-running the
registration with each click confirms the order and the size of the predicted sigma drop; the GT
report carries the guidance line with its numbers; the systematic swing is added only where the
smooth-surface test found a bias. The annotator test (offscreen Qt) is in this file too."""
from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pycolmap
import pytest

from gtkit.evaluate import gt_report as report
from gtkit.io.tiepoints import Observation, TiePoint, read_tiepoints, write_tiepoints
from gtkit.settings import resolve
from gtkit.sfm import guided_clicks as gc
from gtkit.sfm import register
from conftest import stage_settings

from test_register import make_site  # the synthetic site, shared


def _sequence_sigma(proj) -> float:
    reg = json.loads((proj.paths.stage("register") / "registration.json").read_text())
    s = [v["sigma_pos_m"] for v in reg["images"].values()]
    return float(np.sqrt(np.mean(np.square(s))))


def _click_at_centre(name: str, truth: dict, refs: dict) -> gc.Candidate:
    """A tie point on the ground (z = 4 m) under the photo's image centre, clicked at its true
    projections in the photo and in the two reference photos that see it nearest their centres."""
    p = truth[name]
    d = p.R.T @ np.array([0.0, 0.0, 1.0])
    X = p.center + d * (4.0 - p.center[2]) / d[2]
    seen = []
    for rn, (rp, rc) in refs.items():
        uv, front = rc.project(rp.transform(X[None]))
        if front[0] and rc.in_image(uv[0], 40):
            seen.append((float(np.linalg.norm(uv[0] - [rc.width / 2, rc.height / 2])), rn, tuple(uv[0])))
    seen.sort()
    from gtkit.camera import Camera  # the query camera of test_register's site
    q_cam = Camera("SIMPLE_RADIAL", 1600, 1200, (920.0, 800.0, 600.0, -0.02))
    uv = q_cam.project(p.transform(X[None]))[0][0]
    return gc.Candidate(name, (float(uv[0]), float(uv[1])), X, [(rn, xy) for _, rn, xy in seen[:2]], "extra")


def test_guidance_puts_a_click_in_the_least_held_photo_first_and_the_registration_confirms_it(tmp_path):
    proj, truth, _ = make_site(tmp_path / "site", seed=3, n_ties=5)   # ties clicked around the first photos only
    register.run(proj, stage_settings("register", proj))
    out = proj.paths.stage("register")
    rec = pycolmap.Reconstruction(out / "model")
    st = gc.load_states(out / gc.COVARIANCE_FILE, rec)["seq1"]
    assert st.sigma() == pytest.approx(_sequence_sigma(proj), rel=1e-6)   # the same sigma the stage reports
    sig = st.photo_sigmas()
    worst, best = st.names[int(np.argmax(sig))], st.names[int(np.argmin(sig))]
    assert sig.max() > 1.3 * sig.min(), sig
    refs = gc.reference_views(pycolmap.Reconstruction(proj.paths.stage("sfm_reference") / "model"))
    cands = {n: _click_at_centre(n, truth, refs) for n in (worst, best)}
    predicted = {n: st.sigma() - gc.greedy(st, [c], refs, 1)[0][1] for n, c in cands.items()}
    assert gc.greedy(st, list(cands.values()), refs, 1)[0][0].photo == worst
    assert predicted[worst] > 1.5 * predicted[best] > 0, predicted
    # measured: the registration re-run with each click alone
    before, ties = _sequence_sigma(proj), read_tiepoints(proj.paths.tiepoints)
    measured = {}
    for n, c in cands.items():
        write_tiepoints(proj.paths.tiepoints, ties + [TiePoint("extra", [Observation(n, *c.xy)] +
                                                                [Observation(r, *xy) for r, xy in c.reference])])
        register.run(proj, stage_settings("register", proj), force=True)
        measured[n] = before - _sequence_sigma(proj)
    assert measured[worst] > 1.5 * measured[best] > 0, measured
    for n in cands:   # first order: the predicted drop is the drop the BA finds
        assert measured[n] == pytest.approx(predicted[n], rel=0.3), (measured, predicted)


def test_the_first_order_update_is_the_information_form_inverse():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(40, 12))
    cov = np.linalg.inv(A.T @ A)
    L = rng.normal(size=(6, 2))
    U, Si = gc._update(cov, 1, L)
    E = np.zeros((6, 12))
    E[:, 6:] = np.eye(6)
    want = np.linalg.inv(np.linalg.inv(cov) + E.T @ L @ L.T @ E)
    assert np.allclose(cov - U @ Si @ U.T, want, atol=1e-10)


def test_the_gt_report_says_how_many_clicks_bring_each_sequence_to_its_target(tmp_path):
    proj, truth, _ = make_site(tmp_path / "site", seed=4, n_ties=5)
    register.run(proj, stage_settings("register", proj))
    now = _sequence_sigma(proj)
    s = resolve(register.RegisterSettings(), "register", proj, {"guidance.target_m": round(0.8 * now, 4)})
    register.run(proj, s, force=True)
    g = json.loads((proj.paths.stage("register") / gc.GUIDANCE_FILE).read_text())["sequences"]["seq1"]
    assert g["sigma_m"] == pytest.approx(now, rel=1e-6) and 1 <= g["clicks_to_target"] <= 10, g
    assert g["suggestions"][g["clicks_to_target"] - 1]["sigma_after_m"] <= g["target_m"]
    assert all(a["sigma_after_m"] > b["sigma_after_m"] for a, b in zip(g["suggestions"], g["suggestions"][1:]))
    for sug in g["suggestions"]:
        assert sug["photo"] in truth and len(sug["reference"]) == 2 and sug["box"][0] < sug["x"] < sug["box"][2]
    report.run(proj, stage_settings("report", proj))
    md = (proj.paths.reports / "gt_report.md").read_text()
    m = re.search(r"seq1: (\d+) more clicks? in photos (\S.*) expected to bring sigma from ([0-9.]+) to ([0-9.]+) m", md)
    assert m, md
    assert int(m.group(1)) == g["clicks_to_target"] and float(m.group(3)) > float(m.group(4)) > 0
    assert json.loads((proj.paths.reports / "gt_report.json").read_text())["guided_clicks"]["seq1"]["clicks_to_target"] \
        == g["clicks_to_target"]


def test_a_sequence_clicks_barely_lower_is_said_so_and_is_not_sent_to_the_annotator(tmp_path):
    """Small seeds 33-40 with automatic ties: all 63-100 clicks of a sequence lowered its sigma by
    0.1-3.3 % (benchmarks/click_information.py). A sequence above its target that the suggested clicks
    barely lower is said to be held by its automatic ties (not "N more clicks"), and the annotator
    suggests no click in it; one that a click lowers keeps its suggestion."""
    from gtkit.camera import Camera
    from gtkit.pose import Pose
    from gtkit.project import Paths
    from gui.tiepoint_page import read_guidance

    cam = Camera.pinhole(1000, 800, 600.0)
    refs = {"reference/R.jpg": (Pose(np.eye(3), np.array([20.0, 0.0, 100.0])), cam),
            "reference/S.jpg": (Pose(np.eye(3), np.array([-20.0, 0.0, 100.0])), cam)}
    pose = Pose(np.eye(3), np.array([0.0, 0.0, 100.0]))
    X = np.array([0.0, 0.0, 0.0])
    click = gc.Candidate("queries/seqX/0001_W.jpg", tuple(cam.project(pose.transform(X[None]))[0][0]), X,
                         [(n, tuple(c.project(p.transform(X[None]))[0][0])) for n, (p, c) in refs.items()], "a")
    settings = gc.GuidanceSettings(target_m=0.01, max_clicks=1)
    out = {}
    # held: 3 cm a translation axis (many ties); loose: rotation held, 1 m across the view (a click sees 0.17 m)
    for q, cov in (("held", np.diag([1e-8] * 3 + [0.03 ** 2] * 3)), ("loose", np.diag([1e-8] * 3 + [1.0, 1.0, 1e-4]))):
        st = gc.SequenceState(q, [click.photo], [pose], [cam], cov, np.zeros(1))
        out[q] = gc.sequence_guidance(st, [click], refs, settings)
    held, loose = out["held"], out["loose"]
    assert held["sigma_m"] > settings.target_m and len(held["suggestions"]) == 1
    assert held["sigma_after_suggestions_m"] > (1 - settings.min_useful_drop) * held["sigma_m"] and not held["clicks_help"]
    assert loose["sigma_after_suggestions_m"] < 0.5 * loose["sigma_m"] and loose["clicks_help"]
    assert "clicking will not bring it to the target" in gc.summary_line("held", held)
    assert gc.summary_line("loose", loose).startswith("loose: 1 more click in photos 0001_W")
    paths = Paths(tmp_path / "site")
    paths.stage("register").mkdir(parents=True)
    (paths.stage("register") / gc.GUIDANCE_FILE).write_text(json.dumps({"sequences": out}))
    assert [s["sequence"] for s in read_guidance(paths)] == ["loose"]


def test_the_systematic_swing_is_added_only_where_the_ties_were_found_biased(tmp_path):
    """The synthetic site has no automatic ties, so no sequence is judged biased: the stated sigma is
    the BA's (small seeds 13-15: BA sigma 0.023 / 0.025 / 0.013 m a camera axis against RMS errors of
    0.025 / 0.026 / 0.015 m); ``systematic_swing_where = "all"`` restores the swing everywhere."""
    proj, truth, _ = make_site(tmp_path / "site", seed=1)
    reg = register.run(proj, stage_settings("register", proj))
    assert all("swing_m" not in v["sigma_terms"] for v in reg["images"].values())   # (issue 48's terms aside)
    s = resolve(register.RegisterSettings(), "register", proj, {"systematic_swing_where": "all"})
    reg = register.run(proj, s, force=True)
    assert all(v["sigma_terms"]["swing_m"] > 0 for v in reg["images"].values())
    rep = report.run(proj, stage_settings("report", proj))
    assert 0.0 <= rep["share_within_2sigma_ellipsoid"] <= 1.0 and rep["share_within_2sigma"] >= rep["share_within_2sigma_ellipsoid"] - 0.2


def test_the_annotator_shows_the_next_guided_click(qtbot, tmp_path):
    pytest.importorskip("pytestqt")
    from PySide6.QtWidgets import QApplication

    from gui.demo import make_demo_project
    from gui.main_window import MainWindow

    root = make_demo_project(tmp_path / "site", n_query=2).paths.root
    q, r = "queries/seq1/0001_W.jpg", "reference/R01_001_B.jpg"
    box = [100.0, 80.0, 220.0, 170.0]
    guide = {"format": "gtkit-guided-clicks", "version": 1, "sequences": {"seq1": {
        "registered": True, "sigma_m": 0.12, "target_m": 0.05, "at_target": False, "clicks_to_target": 1, "floor_m": 0.0,
        "suggestions": [{"photo": q, "x": 160.0, "y": 125.0, "box": box, "reference": [{"photo": r, "x": 200.0, "y": 150.0}],
                         "sigma_after_m": 0.05}]}}}
    (root / "work" / "register").mkdir(parents=True, exist_ok=True)
    (root / "work" / "register" / gc.GUIDANCE_FILE).write_text(json.dumps(guide))
    w = MainWindow(root)
    qtbot.addWidget(w)
    w.show()
    QApplication.processEvents()
    page = w.tiepoints
    assert "0001_W" in page.guide_label.text() and "0.120 -> 0.050 m" in page.guide_label.text()
    assert page.next_guided()["photo"] == q
    assert page.query == q and page.reference == r
    rect = page.guide_box.rect()
    assert page.guide_box.scene() is page.qview.scene()
    assert (rect.x(), rect.y(), rect.right(), rect.bottom()) == pytest.approx(tuple(box))
    assert (page.qview.markers["g:next"].x(), page.qview.markers["g:next"].y()) == (160.0, 125.0)
    assert (page.rview.markers["g:next"].x(), page.rview.markers["g:next"].y()) == (200.0, 150.0)
    # a tie point placed inside the box completes the suggestion
    page.place(q, 150.0, 120.0)
    page.place(r, 198.0, 151.0)
    assert page.guide_pending() == [] and "all done" in page.guide_label.text()
    assert page.next_guided() is None and page.guide_box is None


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_sigma_calibration_on_the_tiny_sample(tiny_sample, tmp_path):
    """The whole pseudo-GT job on the tiny sample (about 90 s on 2 cores): the stated sigmas hold at
    least 75 % of the query position errors within 2 sigma (radius), and the report carries both
    shares. Measured with this code on the tiny preset's seed: 90 % (radius), 70 % (ellipsoid); its
    pseudo-GT is coarse (0.39 m median) with one sequence off by 0.55 m. The pooled small-seed figures
    are in docs/benchmarks.md ("Guided clicks and calibrated sigma")."""
    from pipelines.pseudo_gt import main as pseudo_gt

    root = tmp_path / "tiny"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "exports", "reports"))
    pseudo_gt(str(root))
    rep = json.loads((root / "reports" / "gt_report.json").read_text())
    assert rep["n_registered"] == rep["n_images"] > 0
    assert 0.75 <= rep["share_within_2sigma"] <= 1.0, rep["share_within_2sigma"]
    assert rep["share_within_2sigma_ellipsoid"] is not None
    assert set(rep["guided_clicks"]) == set(rep["sequences"])
    assert "**Guided clicks**" in (root / "reports" / "gt_report.md").read_text()
