"""The annotator's GCPs tab (issue 46), offscreen and on a real X server (Xvfb + xdotool, as
tests/test_gui_x11.py). A surveyor's session is scripted: each photo the page opens for a GCP is
clicked at the GCP's true projection + the sample's click noise (0.5 px), with real input events on
the real widgets; the page moves on by itself. Measured: the clicks land in gcp_list.txt at the
clicked photo pixels, survive a kill of the annotator mid-session, and georegister the block (a
Sim(3) from the triangulated clicks to the coordinates, gtkit.sfm.georegister) as well as the
sample's own clicks do (camera centres vs truth)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from gtkit.io.odm import read_gcp_list
from gtkit.io.poses import read_intrinsics, read_poses
from gtkit.project import Project
from gtkit.sfm.georegister import GeoregisterSettings, georegister
from gtkit.synth.gcp_points_variant import apply_gcp_points_variant
from conftest import stage_settings

ROOT = Path(__file__).resolve().parents[1]
CLICK_SIGMA = 0.5     # the sample's GCP click noise (tiny preset: annotation.gcp_click_sigma_px)


@pytest.fixture(scope="module")
def gcp_site(tiny_sample, tmp_path_factory):
    """The tiny sample with GCP coordinates only (its clicks moved to truth/), the block placed by
    the photos' GPS. Read-only by convention: copy it."""
    from gtkit.sfm.blocks import run_reference

    root = tmp_path_factory.mktemp("gcp") / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    apply_gcp_points_variant(root, "gcp-points")
    run_reference(root, stage_settings("sfm_reference", root))
    return root


def _copy(site, tmp_path):
    dst = tmp_path / "site"
    shutil.copytree(site, dst)
    return dst


class Truth:
    def __init__(self, root):
        self.poses, self.cams = read_poses(root / "truth/poses.txt"), read_intrinsics(root / "truth/intrinsics.txt")
        frame = Project.load(root).frame
        self.sample = read_gcp_list(root / "truth/gcp_list_sample.txt", frame)
        self.xyz = {g.name: g.xyz for g in self.sample}
        self.frame = frame

    def px(self, gcp, photo):
        p, c = self.poses[photo], self.cams[photo]
        return c.project((p.R @ self.xyz[gcp] + p.t)[None])[0][0]


def centre_errors(root, gcps, model="model") -> float:
    """Median camera-centre error (m) vs truth of the reference block georegistered to ``gcps`` alone."""
    rec = pycolmap.Reconstruction(str(root / "work/sfm_reference" / model))
    georegister(rec, {}, gcps, GeoregisterSettings(use="gcp", check_plausibility=False))
    truth = read_poses(root / "truth/poses.txt")
    e = [np.linalg.norm(im.projection_center() - truth[im.name].center) for im in rec.images.values() if im.has_pose]
    return float(np.median(e))


def _gcps_of_file(root):
    from gtkit.sfm.blocks import list_images

    frame = Project.load(root).frame
    gcps = read_gcp_list(root / "gcp_list.txt", frame)
    names = list_images(root / "images/reference", root / "images")
    for g in gcps:
        for c in g.clicks:
            c.image = next((n for n in names if Path(n).name == c.image), c.image)
    return gcps


def test_gcp_page_offscreen_click_undo_restore(gcp_site, tmp_path):
    """Clicks with Qt events on the page's view: each lands in gcp_list.txt at once at the true
    pixel + noise (within 0.01 px), the page opens the next photo zoomed at the prediction (the
    GCP's true position within the view); Ctrl+Z / Delete / redo follow in the file; reopening
    resumes at the same GCP and photo."""
    from PySide6.QtCore import QPointF, Qt
    from PySide6.QtTest import QTest
    from PySide6.QtWidgets import QApplication

    from gui.app import make_app
    from gui.main_window import GCP_TAB, MainWindow

    root = _copy(gcp_site, tmp_path)
    truth = Truth(root)
    make_app()
    w = MainWindow(root)
    w.resize(1500, 900)
    w.show()
    w.tabs.setCurrentIndex(GCP_TAB)
    QApplication.processEvents()
    pg = w.gcps
    assert pg.gcp == "gcp01" and pg.table.topLevelItemCount() == 4
    rng = np.random.default_rng(1)
    done = []
    for _ in range(3):
        g, ph = pg.gcp, pg.photo
        uv = truth.px(g, ph)
        vis = pg.view.mapToScene(pg.view.viewport().rect()).boundingRect()
        assert vis.contains(QPointF(*uv)) and vis.width() < 200, (vis, uv)   # zoomed at the prediction
        uv = uv + rng.normal(0, CLICK_SIGMA, 2)
        QTest.mouseClick(pg.view.viewport(), Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                         pg.view.mapFromScene(QPointF(*uv)))
        done.append((g, ph, uv))
        on_disk = {(gg.name, c.image): (c.x, c.y) for gg in _gcps_of_file(root) for c in gg.clicks}
        assert len(on_disk) == len(done)
        assert np.allclose(on_disk[(g, ph)], uv, atol=1.0 / pg.view.zoom())   # the pixel under the event
        assert pg.photo != ph   # the next photo opened
    # the A key: the checkered target's centre found near the prediction, placed there
    g, ph = pg.gcp, pg.photo
    assert pg.snap is not None and "snap" in pg.view.markers
    w.accept_()
    xy = pg.store.click(g, ph)
    assert np.linalg.norm(np.array(xy) - truth.px(g, ph)) < 0.5, (xy, truth.px(g, ph))
    w.undo_()
    pg.open_photo(ph)
    s = pg.solution().states["gcp01"]
    assert s.clicks_used == 3 and s.residual_px < 1.5 and np.linalg.norm(s.error_m) < 0.5
    assert "residual" in pg.detail.text() and "error X" in pg.detail.text()
    w.undo_()
    assert len([c for g in _gcps_of_file(root) for c in g.clicks]) == 2
    w.redo_()
    assert len([c for g in _gcps_of_file(root) for c in g.clicks]) == 3
    pg.open_photo(done[0][1])
    w.delete_()
    assert (done[0][1].split("/")[-1]) not in {c.image for g in _gcps_of_file(root) for c in g.clicks}
    w.undo_()
    assert len([c for g in _gcps_of_file(root) for c in g.clicks]) == 3
    # coordinates imported from the page (as "Import coordinates..." does): gcp04 becomes a check point
    x, y, z = truth.frame.local_to_crs(truth.xyz["gcp04"])
    f = tmp_path / "more.txt"
    f.write_text(f"{truth.frame.crs_spec}\ngcp04 {x:.4f} {y:.4f} {z:.4f} 0.02 0.03 check\n")
    pg.import_dialog(str(f))
    kinds = {pg.table.topLevelItem(i).text(0): pg.table.topLevelItem(i).text(1) for i in range(pg.table.topLevelItemCount())}
    assert kinds == {"gcp01": "GCP", "gcp02": "GCP", "gcp03": "GCP", "gcp04": "check"} and pg.store.point("gcp04").check
    assert len(pg.store) == 3
    where = (pg.gcp, pg.photo)
    w.save_session()
    w.close()
    w2 = MainWindow(root)
    w2.show()
    QApplication.processEvents()
    assert w2.tabs.currentIndex() == GCP_TAB and (w2.gcps.gcp, w2.gcps.photo) == where
    assert len(w2.gcps.store) == 3
    w2.close()


# --- on a real X server ------------------------------------------------------------------------

DRIVER = r"""
import json, sys
from PySide6.QtCore import QTimer
from gui.app import make_app
from gui.main_window import GCP_TAB, MainWindow
app = make_app()
w = MainWindow(sys.argv[1])
w.resize(1500, 950)
w.move(0, 0)
w.show()
pg = w.gcps
pg.per_gcp.setValue(int(sys.argv[2]))
def report(gcp, photo):
    def later():
        vp, tf = pg.view.viewport(), pg.view.viewportTransform()
        o = vp.mapToGlobal(vp.rect().topLeft())
        t = pg.title.mapToGlobal(pg.title.rect().center())
        print("SHOWN " + json.dumps({"gcp": gcp, "photo": photo, "viewport": [o.x(), o.y(), vp.width(), vp.height()],
              "title": [t.x(), t.y()],
              "m": [tf.m11(), tf.m22(), tf.dx(), tf.dy()], "clicks": len(pg.store)}), flush=True)
    QTimer.singleShot(200, later)
pg.photo_shown.connect(report)
def start():
    if w.tabs.currentIndex() == GCP_TAB and pg.photo:   # reopened on the GCPs tab (its session)
        report(pg.gcp, pg.photo)
    w.tabs.setCurrentIndex(GCP_TAB)
QTimer.singleShot(300, start)
app.exec()
"""


def test_gcp_session_on_xvfb_clicks_true_positions_and_georegisters(gcp_site, xserver, tmp_path):
    """A scripted surveyor on X: the page opens each photo of each GCP zoomed at its prediction; a
    real click (xdotool, XTEST) at the true position + 0.5 px noise places it; 4 GCPs x 8 photos (as
    many clicks as the sample has). The annotator is then killed (SIGKILL, no chance to save): every
    click is in gcp_list.txt at the clicked pixel, and the block georegistered to these clicks alone
    is as good as with the sample's own clicks (camera centres vs truth)."""
    root = _copy(gcp_site, tmp_path)
    truth = Truth(root)
    per_gcp, n_gcp = 8, len(truth.xyz)
    rng = np.random.default_rng(7)
    app = subprocess.Popen([sys.executable, "-c", DRIVER, str(root), str(per_gcp)], env=xserver, cwd=str(ROOT),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(150, app.kill)
    watchdog.start()
    clicked = {}
    shot = None
    try:
        t0 = time.time()
        for line in app.stdout:
            if not line.startswith("SHOWN "):
                continue
            s = json.loads(line[6:])
            if len(clicked) == per_gcp * n_gcp:
                break
            assert s["clicks"] == len(clicked), (s, len(clicked))   # the page saw every click
            if len(clicked) == 12 and shot is None:
                subprocess.run(["xdotool", "mousemove", "1599", "999"], env=xserver, check=True, timeout=10)
                time.sleep(0.3)
                shot = tmp_path / "gcp_page.png"
                subprocess.run(["import", "-window", "root", str(shot)], env=xserver, check=True, timeout=30)
            m11, m22, dx, dy = s["m"]
            uv = truth.px(s["gcp"], s["photo"]) + rng.normal(0, CLICK_SIGMA, 2)
            vx, vy = s["viewport"][:2]
            sx, sy = int(round(vx + uv[0] * m11 + dx)), int(round(vy + uv[1] * m22 + dy))
            subprocess.run(["xdotool", "mousemove", str(sx), str(sy), "click", "1"], env=xserver, check=True, timeout=10)
            clicked[(s["gcp"], s["photo"])] = (uv, ((sx - vx - dx) / m11, (sy - vy - dy) / m22), m11)
        session_s = time.time() - t0
        assert len(clicked) == per_gcp * n_gcp, f"only {len(clicked)} clicks: {app.stderr.read()[-1500:]}"
    finally:
        watchdog.cancel()
        app.kill()     # mid-session, no close event: what is on disk is what the page wrote at each click
        app.wait(10)
    gcps = _gcps_of_file(root)
    on_disk = {(g.name, c.image): (c.x, c.y) for g in gcps for c in g.clicks}
    assert on_disk.keys() == clicked.keys()
    for k, (uv, pixel, zoom) in clicked.items():
        # the photo pixel under the screen pixel xdotool moved to (XTEST moves to whole screen pixels)
        assert np.allclose(on_disk[k], pixel, atol=0.02) and np.allclose(on_disk[k], uv, atol=0.6 / zoom), k
    mine = centre_errors(root, gcps)
    sample = centre_errors(root, truth.sample)
    assert mine < 1.25 * sample + 0.05, (mine, sample)
    out = os.environ.get("GTKIT_GCP_SCREENSHOT")
    if out and shot is not None:
        shutil.copy(shot, out)
    print(f"GCP page on Xvfb: {len(clicked)} clicks in {session_s:.1f} s; block georegistered to them: camera "
          f"centres {mine:.3f} m from truth (median), to the sample's clicks {sample:.3f} m")


@pytest.mark.skipif(not os.environ.get("GTKIT_SLOW"), reason="slow (about 1 min): set GTKIT_SLOW=1")
def test_gcp_session_on_xvfb_without_gps(tiny_sample, xserver, tmp_path):
    """No GPS in the photos: the page has nothing to predict until 3 GCPs are clicked in 2+ photos,
    so the scripted surveyor steps through the photos (a real N key) to those that show the GCP and
    clicks it (true position + 0.5 px); after a GCP's 2nd click its own triangulation predicts it in
    the rest (best photos first), and from the 4th GCP on the page opens the photos zoomed at the
    predictions of the Sim(3). 8 photos a GCP, as many as the sample clicked. The block georegistered to these clicks alone vs
    to the sample's own clicks (camera centres vs truth)."""
    from gtkit.errors import GtkitError
    from gtkit.sfm.blocks import run_reference

    root = tmp_path / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    apply_gcp_points_variant(root, "gcp-points-no-gps")
    with pytest.raises(GtkitError, match="georegistration failed"):
        run_reference(root, stage_settings("sfm_reference", root))
    truth = Truth(root)
    per_gcp, n_gcp = 8, len(truth.xyz)
    rng = np.random.default_rng(11)
    app = subprocess.Popen([sys.executable, "-c", DRIVER, str(root), str(per_gcp)], env=xserver, cwd=str(ROOT),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(150, app.kill)
    watchdog.start()
    clicked, keys, zoomed = {}, 0, []
    try:
        for line in app.stdout:
            if not line.startswith("SHOWN "):
                continue
            s = json.loads(line[6:])
            if not keys and not clicked:   # a first real click (on the photo's title) activates the window for keys
                subprocess.run(["xdotool", "mousemove", str(s["title"][0]), str(s["title"][1]), "click", "1"],
                               env=xserver, check=True, timeout=10)
            if len(clicked) == per_gcp * n_gcp:
                break
            m11, m22, dx, dy = s["m"]
            vx, vy, vw, vh = s["viewport"]
            uv = truth.px(s["gcp"], s["photo"])
            if uv is None or not truth.cams[s["photo"]].in_image(uv, 20) or (s["gcp"], s["photo"]) in clicked:
                subprocess.run(["xdotool", "mousemove", str(vx + vw // 2), str(vy + vh // 2), "key", "n"], env=xserver,
                               check=True, timeout=10)
                keys += 1
                continue
            uv = uv + rng.normal(0, CLICK_SIGMA, 2)
            sx, sy = int(round(vx + uv[0] * m11 + dx)), int(round(vy + uv[1] * m22 + dy))
            subprocess.run(["xdotool", "mousemove", str(sx), str(sy), "click", "1"], env=xserver, check=True, timeout=10)
            clicked[(s["gcp"], s["photo"])] = (uv, ((sx - vx - dx) / m11, (sy - vy - dy) / m22))
            zoomed.append((s["gcp"], m11))
        assert len(clicked) == per_gcp * n_gcp, f"only {len(clicked)} clicks: {app.stderr.read()[-1500:]}"
    finally:
        watchdog.cancel()
        app.kill()
        app.wait(10)
    gcps = _gcps_of_file(root)
    on_disk = {(g.name, c.image): (c.x, c.y) for g in gcps for c in g.clicks}
    assert on_disk.keys() == clicked.keys()
    assert all(np.allclose(on_disk[k], px, atol=0.02) for k, (uv, px) in clicked.items())
    # the first GCPs were found by hand (the photo fitted in the view), the last one at its prediction
    fit_zoom = min(z for g, z in zoomed if g == "gcp01")
    assert min(z for g, z in zoomed if g == "gcp04") > 3 * fit_zoom
    # one noise draw each: with 4 GCPs and no GPS the block's error varies 5x between draws (the
    # sample's photos over 8 draws: 0.15-0.73 m, mean 0.33 m; the page's photo choice 0.12-0.44 m,
    # mean 0.26 m), so "as well as" is judged with that spread (measured here: 0.40 vs 0.20 m)
    mine = centre_errors(root, gcps, "unplaced_model")
    sample = centre_errors(root, truth.sample, "unplaced_model")
    assert mine < 2.5 * sample + 0.1 and mine < 0.8, (mine, sample)
    print(f"GCP page on Xvfb, no GPS: {len(clicked)} clicks, {keys} N keys; block georegistered to them: camera "
          f"centres {mine:.3f} m from truth (median), to the sample's clicks {sample:.3f} m")
