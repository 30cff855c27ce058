"""The 3D scene (gtkit.view.scene, pyvista offscreen): ``gtkit view`` and the annotator's 3D tab.

Measured on the small finished project (``finished_demo``): the snapshots are written and not
blank; every reference camera's frustum apex is drawn where the view projects the camera centre;
looking through a query photo at its localized pose reproduces the photo (correlation with the
photo); the decimated model keeps its colours; in the annotator the tab opens on the photo
selected in the tie-point tab and mouse drags orbit the view.
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("pytestqt")
pytest.importorskip("pyvista")
from PySide6.QtCore import QPointF, Qt  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

from gtkit.cli import main  # noqa: E402

YELLOW = np.array([0xFF, 0xD4, 0x00])


def _near_colour(img, xy, colour, r=3, tol=60):
    x, y = int(round(xy[0])), int(round(xy[1]))
    win = img[max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1].reshape(-1, 3).astype(int)
    return bool((np.linalg.norm(win - colour, axis=1) < tol).any())


def test_gtkit_view_writes_snapshots(finished_demo, tmp_path, capsys):
    capsys.readouterr()
    assert main(["view", str(finished_demo), "--out", str(tmp_path), "--size", "640x400"]) == 0
    info = json.loads(capsys.readouterr().out)
    import cv2

    for which in ("oblique", "top"):
        img = cv2.imread(str(tmp_path / f"scene_{which}.png"))
        assert img.shape == (400, 640, 3) and img.std() > 20, which
    assert info["n_reference_cameras"] == 10 and info["trajectories"] == {"prior": 3, "localized": 3}
    assert info["frame_ms_median"] > 0 and info["open_s"] > 0
    assert not (finished_demo / "reports" / "scene_top.png").exists()  # --out respected


def test_scene_draws_cameras_where_they_are_and_looks_through_photos(finished_demo, tmp_path):
    import cv2

    from gtkit.io.poses import read_poses
    from gtkit.view.process import SceneProcess
    from gtkit.view.scene import ViewSettings, load_scene

    sp = SceneProcess(finished_demo, 800, 600)  # VTK renders in a child process (gtkit.view.process)
    try:
        assert sp.info["reference_source"].startswith("photo priors") and sp.info["n_reference_cameras"] == 10
        sp.overview("top")
        img = sp.render()
        apex = sp.world_to_pixel(sp.info["reference_centres"])
        hits = [_near_colour(img, xy, YELLOW) for xy in apex]
        assert all(hits), hits
    finally:
        sp.close()
    # through a query photo at its localized pose (the demo's localization is within centimetres):
    # the rendered model matches the photo
    name = "queries/seq1/0001_W.jpg"
    photo = cv2.cvtColor(cv2.imread(str(finished_demo / "images" / name)), cv2.COLOR_BGR2RGB)
    sp = SceneProcess(finished_demo, photo.shape[1], photo.shape[0], ViewSettings(layers=("model",)))
    try:
        assert sp.photo(name)
        cam = sp.camera()
        view = sp.render()
    finally:
        sp.close()
    pose = read_poses(finished_demo / "work/localize/poses.txt")[name]
    assert np.allclose(cam["position"], pose.center, atol=1e-6)

    def g(a):
        return cv2.GaussianBlur(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(float), (0, 0), 2).ravel()

    corr = np.corrcoef(g(view), g(photo))[0, 1]
    shifted = np.corrcoef(g(np.roll(view, 8, axis=1)), g(photo))[0, 1]
    assert corr > 0.8 and corr - shifted > 0.1, (corr, shifted)
    # decimated: at most the asked triangles, colours kept (sampled from the texture)
    site = tmp_path / "site"
    shutil.copytree(finished_demo, site)
    small = load_scene(site, ViewSettings(max_triangles=300))
    assert small.n_triangles_model == 652 and small.n_triangles_shown <= 300
    rgb = small.model[0][0].point_data["rgb"]
    assert rgb.std(axis=0).mean() > 10
    # ... and cached in work/view/: the second load reads the same mesh from there
    assert len(list((site / "work/view").glob("model_*.npz"))) == 1
    again = load_scene(site, ViewSettings(max_triangles=300))
    assert np.array_equal(again.model[0][0].point_data["rgb"], rgb) and again.n_triangles_shown == small.n_triangles_shown


def test_annotator_scene_tab_jumps_to_the_selected_photo_and_orbits(finished_demo, tmp_path, qtbot):
    from gui.main_window import MainWindow

    site = tmp_path / "site"
    shutil.copytree(finished_demo, site)
    w = MainWindow(site)
    qtbot.addWidget(w)
    w.resize(1200, 800)
    w.show()
    QApplication.processEvents()
    assert w.tabs.currentIndex() == 1  # the session reopens the review tab
    qtbot.keyClick(w, Qt.Key.Key_1, Qt.KeyboardModifier.ControlModifier)
    page = w.tiepoints
    page.set_pair("queries/seq1/0002_W.jpg", page.reference)
    qtbot.keyClick(w, Qt.Key.Key_4, Qt.KeyboardModifier.ControlModifier)
    sc = w.scene3d
    assert sc.photo == "queries/seq1/0002_W.jpg", sc.photo
    assert w.tabs.currentIndex() == 3 and sc.proc is not None and sc.open_s is not None
    from gtkit.io.poses import read_poses

    pose = read_poses(site / "work/localize/poses.txt")["queries/seq1/0002_W.jpg"]
    assert np.allclose(sc.proc.camera()["position"], pose.center, atol=1e-6)  # looking through the photo
    first = sc.image().copy()
    assert first.std() > 10
    sc.overview("oblique")
    before = sc.image().copy()
    vp = sc.view
    c = QPointF(vp.width() / 2, vp.height() / 2)
    qtbot.mousePress(vp, Qt.MouseButton.LeftButton, pos=c.toPoint())
    from PySide6.QtCore import QEvent
    from PySide6.QtGui import QMouseEvent

    for dx in (20, 40, 60):
        ev = QMouseEvent(QEvent.Type.MouseMove, c + QPointF(dx, 0), vp.mapToGlobal(c + QPointF(dx, 0)),
                         Qt.MouseButton.NoButton, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier)
        QApplication.sendEvent(vp, ev)
    qtbot.mouseRelease(vp, Qt.MouseButton.LeftButton, pos=(c + QPointF(60, 0)).toPoint())
    after = sc.image()
    assert np.abs(after.astype(int) - before).mean() > 2  # the view turned
    assert len(sc.frame_ms) >= 5
    print(f"3D tab: open {sc.open_s:.2f} s, frame median {np.median(sc.frame_ms):.1f} ms")
    # gtkit's own renderer (moderngl) is unaffected by VTK (in its child process): the review renders
    # the model at the localized pose of the next photo, aligned
    qtbot.keyClick(w, Qt.Key.Key_2, Qt.KeyboardModifier.ControlModifier)
    qtbot.keyClick(w, Qt.Key.Key_K)
    rv = w.review
    assert rv.image is not None and rv._cache[5].misalignment_px < 1.0, rv.image
    w.close()
    assert sc.proc is None  # the scene process is closed with the window
