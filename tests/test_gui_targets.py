"""The annotator's Targets page (issue 8, target input by clicks), driven offscreen with real
mouse events (pytest-qt) on a copy of the tiny sample.

Measured outcomes: a click at a known widget position stores the photo pixel under it (COLMAP
convention, at zoom 2 and 8); a drag stores a box the tracker reads back; every edit, undo and
redo is in ``detections.csv`` at once; reopening restores the targets and the photo; a file the
tracker cannot read is named in one line and left untouched. End to end: clicks placed through
the GUI at the true projections of the sample's targets, then ``gtkit track`` (no --detections:
it reads the GUI's file) with the true wide poses, give the targets to a few centimetres.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pytestqt")
from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

from gtkit.conventions import pixel_to_index  # noqa: E402
from gtkit.track.targets import read_csv, read_detections  # noqa: E402
from conftest import stage_settings

IMG = "queries/seq1/0001_Z.jpg"


@pytest.fixture
def site(tiny_sample, tmp_path):
    root, _settings, _summary = tiny_sample
    dst = tmp_path / "site"
    shutil.copytree(root, dst, ignore=shutil.ignore_patterns("work", "exports", "reports"))
    return dst


def _window(qtbot, root):
    from gui.main_window import MainWindow

    w = MainWindow(root)
    qtbot.addWidget(w)
    w.resize(1200, 800)
    w.show()
    w.tabs.setCurrentIndex(2)
    QApplication.processEvents()
    return w, w.targets


def _click(qtbot, view, x, y):
    qtbot.mouseClick(view.viewport(), Qt.MouseButton.LeftButton, pos=view.scene_to_widget(x, y))


def _drag(qtbot, view, a, b, button=Qt.MouseButton.LeftButton):
    pa, pb = view.scene_to_widget(*a), view.scene_to_widget(*b)
    qtbot.mousePress(view.viewport(), button, pos=pa)
    for k in range(1, 6):
        qtbot.mouseMove(view.viewport(), pos=pa + (pb - pa) * (k / 5))
    qtbot.mouseRelease(view.viewport(), button, pos=pb)
    QApplication.processEvents()


def _file(root):
    p = Path(root) / "detections.csv"     # read with the tracker's own reader
    return read_csv(p) if p.is_file() else []


def test_click_stores_the_photo_pixel_under_the_cursor(qtbot, site):
    w, page = _window(qtbot, site)
    page.open_image(IMG)
    v = page.view
    assert v.full_size == (320, 240)
    # zoom 4, photo point (150, 100) at the viewport centre: a click 40 screen px right and
    # 20 px down of the centre is 10 / 5 photo px away from it
    v.center_on(150.0, 100.0, zoom=4.0)
    QApplication.processEvents()
    c = v.viewport().rect().center()
    cx, cy = v.view_state()["center"]
    assert abs(cx - 150) <= 0.25 and abs(cy - 100) <= 0.25    # centerOn is exact to a screen pixel
    qtbot.mouseClick(v.viewport(), Qt.MouseButton.LeftButton, pos=c + QPoint(40, 20))
    d = _file(site)
    assert len(d) == 1 and d[0].image == IMG and d[0].label == page.current_label() and d[0].box is None
    assert abs(d[0].u - 160) <= 0.5 / 4 + 0.25 and abs(d[0].v - 105) <= 0.5 / 4 + 0.25
    assert abs(d[0].u - (cx + 10)) <= 0.5 / 4 + 0.01 and abs(d[0].v - (cy + 5)) <= 0.5 / 4 + 0.01
    # zoom 8 on the top-left pixel: its centre is (0.5, 0.5) (COLMAP), pixel index (0, 0)
    v.center_on(4.0, 4.0, zoom=8.0)
    QApplication.processEvents()
    _click(qtbot, v, 0.5, 0.5)
    d = _file(site)
    assert len(d) == 2
    assert abs(d[1].u - 0.5) <= 1 / 16 + 1e-3 and abs(d[1].v - 0.5) <= 1 / 16 + 1e-3
    assert tuple(pixel_to_index(np.array([d[1].u, d[1].v]))) == (0, 0)
    assert page.table.topLevelItemCount() == 2


def test_drag_draws_a_box_the_tracker_reads_and_one_kind_per_file(qtbot, site):
    w, page = _window(qtbot, site)
    page.open_image(IMG)
    v = page.view
    v.center_on(160.0, 120.0, zoom=3.0)
    page.label_box.setCurrentText("person")
    _drag(qtbot, v, (100.0, 80.0), (140.0, 130.0))
    d = _file(site)
    tol = 1.0 / v.zoom()
    assert len(d) == 1 and d[0].label == "person" and d[0].box is not None
    assert np.allclose(d[0].box, (100, 80, 140, 130), atol=tol)
    assert np.allclose((d[0].u, d[0].v), (120, 105), atol=tol)   # the tracker's foot point: the centre
    assert page.view.boxes and len(page.view.markers) == 1
    # the tracker reads one kind per file: a click is refused, the file is unchanged
    before = (site / "detections.csv").read_bytes()
    msgs = []
    page.status.connect(msgs.append)
    _click(qtbot, v, 60.0, 60.0)
    assert (site / "detections.csv").read_bytes() == before
    assert msgs and "one kind per file" in msgs[-1] and "detections.csv" in msgs[-1]
    # right drag pans, it draws nothing
    _drag(qtbot, v, (60.0, 60.0), (90.0, 90.0), button=Qt.MouseButton.RightButton)
    assert len(_file(site)) == 1


def test_move_delete_relabel_undo_redo_all_in_the_file_at_once(qtbot, site):
    w, page = _window(qtbot, site)
    page.open_image(IMG)
    v = page.view
    v.center_on(160.0, 120.0, zoom=3.0)
    tol = 1.0 / v.zoom()
    page.label_box.setCurrentText("car")
    _click(qtbot, v, 100.0, 100.0)
    _click(qtbot, v, 200.0, 150.0)
    assert [(round(d.u), round(d.v)) for d in _file(site)] == [(100, 100), (200, 150)]
    # drag the first marker to (110, 90)
    _drag(qtbot, v, (100.0, 100.0), (110.0, 90.0))
    d = _file(site)
    assert len(d) == 2 and np.allclose((d[0].u, d[0].v), (110, 90), atol=tol)
    w.undo_()
    assert np.allclose([(x.u, x.v) for x in _file(site)], [(100, 100), (200, 150)], atol=tol)
    w.redo_()
    assert np.allclose((_file(site)[0].u, _file(site)[0].v), (110, 90), atol=tol)
    # select the second, relabel it, delete it, undo both
    second = [t.id for t in page.store.targets][1]
    page.select(second)
    page.label_box.setCurrentText("truck")
    page.relabel_button.click()
    assert [x.label for x in _file(site)] == ["car", "truck"]
    qtbot.keyClick(w, Qt.Key.Key_Delete)
    assert [x.label for x in _file(site)] == ["car"]
    qtbot.keyClick(w, Qt.Key.Key_Z, Qt.KeyboardModifier.ControlModifier)
    assert [x.label for x in _file(site)] == ["car", "truck"]
    w.undo_()
    assert [x.label for x in _file(site)] == ["car", "car"]
    # undo on the Targets tab never touches the tie points
    tp_before = (site / "tiepoints.json").read_bytes()
    for _ in range(10):
        w.undo_()
    assert _file(site) == [] and (site / "tiepoints.json").read_bytes() == tp_before
    assert (site / "detections.csv").is_file()       # header only: nothing left, nothing lost


def test_reopen_restores_targets_and_photo(qtbot, site):
    w, page = _window(qtbot, site)
    page.open_image("queries/seq2/0002_Z.jpg")
    page.view.center_on(160.0, 120.0, zoom=2.0)
    _click(qtbot, page.view, 150.0, 90.0)
    _click(qtbot, page.view, 170.0, 95.0)
    saved = [(d.image, d.u, d.v, d.label) for d in _file(site)]
    w.close()
    w2, page2 = _window(qtbot, site)
    assert page2.image == "queries/seq2/0002_Z.jpg"                  # the session's photo
    assert [(t.image, t.x, t.y, t.label) for t in page2.store.targets] == saved
    assert len(page2.view.markers) == 2
    assert abs(page2.view.zoom() - 2.0) < 1e-6
    # an existing detector file (boxes, times) is kept as it is read: nothing is lost on an edit
    w2.close()
    (site / "detections.csv").write_text("image,xmin,ymin,xmax,ymax,label,time\n"
                                         "seq1/0001_Z.jpg,10,20,30,40,car,12.5\n")   # short name: resolved
    w3, page3 = _window(qtbot, site)
    page3.open_image(IMG)
    page3.view.center_on(160.0, 120.0, zoom=2.0)
    _drag(qtbot, page3.view, (100.0, 100.0), (120.0, 130.0))
    d = _file(site)
    assert d[0].image == IMG and d[0].box == (10, 20, 30, 40) and d[0].time == 12.5 and len(d) == 2


def test_a_file_the_tracker_cannot_read_is_named_and_never_overwritten(qtbot, site):
    bad = "image,x,y,label\nqueries/seq1/0001_Z.jpg,12.5,not-a-number,car\n"
    (site / "detections.csv").write_text(bad)
    w, page = _window(qtbot, site)
    assert page.store is None and "detections.csv" in page.error and "line 2" in page.error
    assert "\n" not in page.error
    msgs = []
    page.status.connect(msgs.append)
    page.open_image(IMG)
    _click(qtbot, page.view, 100.0, 100.0)
    _drag(qtbot, page.view, (50.0, 50.0), (90.0, 90.0))
    assert (site / "detections.csv").read_text() == bad
    assert msgs and "detections.csv" in msgs[-1]
    assert "cannot read" in page.file_label.text()


def test_gui_clicks_at_true_target_pixels_track_to_centimetres(qtbot, site):
    """Clicks through the GUI at the true projections of the sample's targets (the true zoom
    pose and camera), then the tracker with the true wide poses and the calibrated rig."""
    from gtkit.cli import main
    from gtkit.evaluate.tracking import evaluate_tracking, simulate_detections
    from gtkit.project import Project
    from gtkit.track import calibrate

    P = Project.load(site).paths
    calibrate.run(Project.load(site), stage_settings("track", site)["rig"])
    assert main(["export", "dsm", str(site)]) == 0
    truth_csv = site / "truth_pixels.csv"
    n = simulate_detections(P, truth_csv, sigma_px=0.0, mode="point")  # visible targets, exact pixels
    assert n >= 4
    true = read_detections(truth_csv)
    w, page = _window(qtbot, site)
    zoom = 8.0
    for d in true:
        page.open_image(d.image)
        page.label_box.setCurrentText(d.label)
        page.view.center_on(d.u, d.v, zoom=zoom)
        QApplication.processEvents()
        _click(qtbot, page.view, d.u, d.v)
    clicked = _file(site)
    assert [(c.image, c.label) for c in clicked] == [(d.image, d.label) for d in true]
    px_err = np.array([np.hypot(c.u - d.u, c.v - d.v) for c, d in zip(clicked, true)])
    print(f"GUI click vs true pixel at zoom {zoom:g}: max {px_err.max():.3f} px")
    assert px_err.max() <= np.sqrt(2) * 0.5 / zoom + 0.01   # half a screen pixel (+ the file's 0.01 px)
    # `gtkit track` reads the GUI's detections.csv by default
    assert main(["track", str(site), "--poses", str(P.truth / "poses.txt")]) == 0
    rep = evaluate_tracking(P)
    errs = [r.get("err_3d_m") for r in rep["per_detection"]]
    print("tracking from GUI clicks (true poses):", {k: rep[k] for k in ("n_targets", "n_failed", "median_err_h_m",
                                                                          "median_err_3d_m")}, errs)
    assert rep["n_targets"] == n and rep["n_failed"] == 0
    assert rep["median_err_3d_m"] < 0.15 and rep["median_err_h_m"] < 0.15
    # the page shows each click's tracked position
    page.refresh()
    texts = [page.table.topLevelItem(i).text(4) for i in range(page.table.topLevelItemCount())]
    assert texts and all(t.count(",") == 2 and "m" in t for t in texts), texts


def test_a_file_changed_by_another_program_is_not_overwritten(qtbot, site):
    w, page = _window(qtbot, site)
    page.open_image(IMG)
    page.view.center_on(160.0, 120.0, zoom=2.0)
    _click(qtbot, page.view, 100.0, 100.0)
    other = "image,x,y,label\nqueries/seq1/0002_Z.jpg,10.000,20.000,car\n"   # e.g. a detector run meanwhile
    (site / "detections.csv").write_text(other)
    msgs = []
    page.status.connect(msgs.append)
    _click(qtbot, page.view, 150.0, 100.0)
    w.undo_()
    page.select(page.store.targets[0].id)
    page.delete_active()
    assert (site / "detections.csv").read_text() == other
    assert msgs and all("changed on disk" in m and "detections.csv" in m for m in msgs)


_KILL_DRIVER = r'''
import json, sys
from PySide6.QtCore import Qt, QTimer
from PySide6.QtTest import QTest
from gui.app import make_app
from gui.main_window import MainWindow
app = make_app()
w = MainWindow(sys.argv[1]); w.resize(1200, 800); w.show(); w.tabs.setCurrentIndex(2)
page, k = w.targets, [0]
page.open_image("queries/seq1/0001_Z.jpg")
page.view.center_on(160.0, 120.0, zoom=3.0)
def step():
    x, y = 20.0 + (k[0] * 37) % 280, 20.0 + (k[0] * 23) % 200
    QTest.mouseClick(page.view.viewport(), Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     page.view.scene_to_widget(x, y))
    t = page.store.targets[-1]
    print("DONE " + json.dumps([t.image, t.x, t.y]), flush=True)
    k[0] += 1
    QTimer.singleShot(5, step)
QTimer.singleShot(100, step)
app.exec()
'''


def test_kill_mid_edit_loses_no_committed_click(site):
    """The annotator in a subprocess clicking as fast as it can, SIGKILLed after 25 clicks:
    every click it reported is in the file, which the tracker's reader reads."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import threading

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", PYTHONPATH=str(root))
    proc = subprocess.Popen([sys.executable, "-c", _KILL_DRIVER, str(site)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, env=env, cwd=str(root), text=True)
    watchdog = threading.Timer(120, proc.kill)
    watchdog.start()
    done = []
    try:
        for line in proc.stdout:
            if line.startswith("DONE "):
                done.append(json.loads(line[5:]))
                if len(done) == 25:
                    proc.send_signal(signal.SIGKILL)   # the next click is already on its way
                    break
    finally:
        watchdog.cancel()
        proc.kill()
        proc.wait()
    assert len(done) == 25
    on_disk = [[d.image, d.u, d.v] for d in read_detections(site / "detections.csv")]
    assert len(on_disk) >= 25 and on_disk[:25] == [[i, round(x, 3), round(y, 3)] for i, x, y in done]


def test_a_dragged_marker_stays_inside_the_photo(qtbot, site):
    w, page = _window(qtbot, site)
    page.open_image(IMG)
    page.view.fit()
    QApplication.processEvents()
    _click(qtbot, page.view, 300.0, 200.0)
    _drag(qtbot, page.view, (300.0, 200.0), (340.0, 230.0))    # the cursor leaves the photo
    d = _file(site)
    assert len(d) == 1 and abs(d[0].u - 320.0) < 1e-6 and 229.0 <= d[0].v <= 240.0
