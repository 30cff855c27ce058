"""The annotator on a real X server (Xvfb), the way a Linux desktop presents itself to Qt.

The window is opened with Qt's xcb platform in a subprocess (one process holds one Qt platform; the
other GUI tests run offscreen), clicked and typed at with real X input events (``xdotool``, XTEST),
and the X screen is captured by another X client (ImageMagick ``import -window root``). Measured:
the tie point lands in tiepoints.json at the clicked photo pixel, the screen shows the query photo
where the window says it is, the only change the click makes inside the photo is the marker at the
clicked spot, and a real Ctrl+Z removes it from the file. Xvfb, xdotool and ImageMagick are installed
by scripts/setup.sh; the tests skip (saying which is missing) only where they are absent.
"""
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
import pytest

ROOT = Path(__file__).resolve().parents[1]
Q0 = "queries/seq1/0000_W.jpg"


def _screenshot(env, path: Path) -> np.ndarray:
    import cv2

    subprocess.run(["import", "-window", "root", str(path)], env=env, check=True, timeout=30)
    return cv2.imread(str(path), cv2.IMREAD_COLOR)


def _pointer(env, x, y, *then):
    subprocess.run(["xdotool", "mousemove", str(int(round(x))), str(int(round(y))), *then], env=env, check=True, timeout=10)


def _wait_for(pred, timeout=15.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    return pred()


def _photo_view_corr(shot, rect, photo) -> float:
    """Correlation of the photo with the screen's view ``rect`` (x, y, w, h) of the model through it:
    the same vertical field of view, so the photo spans the rect's height, centred."""
    import cv2

    x, y, w, h = rect
    shown = shot[y:y + h, x:x + w]
    ph, pw = photo.shape[:2]
    cw = int(round(h * pw / ph))
    crop = cv2.resize(shown[:, (w - cw) // 2:(w - cw) // 2 + cw], (pw, ph), interpolation=cv2.INTER_AREA)

    def g(a):
        return cv2.GaussianBlur(cv2.cvtColor(a, cv2.COLOR_BGR2GRAY).astype(float), (0, 0), 2).ravel()

    return float(np.corrcoef(g(crop), g(photo))[0, 1])


def _frustum_pixels(img, rect) -> int:
    """Pixels of the reference cameras' frustum yellow (#ffd400) inside ``rect``."""
    x, y, w, h = rect
    img = img[y:y + h, x:x + w]
    return int(((img[..., 2] > 230) & (np.abs(img[..., 1].astype(int) - 0xD4) < 20) & (img[..., 0] < 40)).sum())


def _tiepoints(root):
    from gtkit.io.tiepoints import read_tiepoints

    f = Path(root) / "tiepoints.json"
    return read_tiepoints(f) if f.is_file() else []


def test_annotator_on_xvfb_real_click_screenshot_and_key(xserver, tmp_path):
    import cv2

    from gui.demo import make_demo_project

    site = make_demo_project(tmp_path / "site", n_query=2).paths.root
    photo = cv2.imread(str(site / "images" / Q0), cv2.IMREAD_COLOR)
    H, W = photo.shape[:2]
    cx, cy = 200.0, 150.0  # the photo pixel to click
    script = tmp_path / "actions.json"
    script.write_text(json.dumps([{"locate": "query", "points": [[cx, cy], [0, 0], [W, H]]}, {"wait": 120000}]))
    env = dict(xserver, GTKIT_GUI_SCRIPT=str(script))
    t0 = time.time()
    app = subprocess.Popen([sys.executable, "-m", "gtkit.cli", "annotate", str(site)], env=env, cwd=str(ROOT),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(150, app.kill)  # a hung GUI must not hang the test run
    watchdog.start()
    try:
        loc = None
        for line in app.stdout:
            if line.startswith("DONE "):
                loc = json.loads(line[5:])
                break
        assert loc is not None, f"the annotator did not start on X: {app.stderr.read()[-1500:]}"
        open_s = time.time() - t0
        assert loc["image"] == Q0 and open_s < 60
        (gx, gy), (x0, y0), (x1, y1) = loc["screen"]
        zoom = loc["zoom"]
        wx, wy, ww, wh = loc["window"]
        _pointer(xserver, 1599, 999)  # away from the window: no loupe, no hover
        time.sleep(0.3)
        before = _screenshot(xserver, tmp_path / "before.png")
        # the window is on the X screen and not blank; the query photo is shown where the window says
        win = before[wy:wy + wh, wx:wx + ww]
        assert win.shape[0] == wh and win.shape[1] == ww and win.std() > 20
        # the photo drawn at the view's zoom and place, compared where the viewport shows it
        vx, vy, vw, vh = loc["viewport"]
        M = np.float32([[zoom, 0, x0], [0, zoom, y0]])
        expect = cv2.warpAffine(photo, M, (before.shape[1], before.shape[0]), flags=cv2.INTER_AREA)
        u0, v0 = int(max(vx, x0)) + 2, int(max(vy, y0)) + 2
        u1, v1 = int(min(vx + vw, x1)) - 2, int(min(vy + vh, y1)) - 2
        assert u1 - u0 > 200 and v1 - v0 > 200

        def gray(a):
            return cv2.GaussianBlur(cv2.cvtColor(a[v0:v1, u0:u1], cv2.COLOR_BGR2GRAY).astype(float), (0, 0), 1.0).ravel()

        corr = np.corrcoef(gray(before), gray(expect))[0, 1]
        off = np.corrcoef(gray(before), gray(np.roll(expect, 3, axis=1)))[0, 1]  # 3 screen px to the side
        assert corr > 0.95 and corr - off > 0.05, (corr, off)
        # a real click (XTEST) makes a tie point, saved at once at the clicked photo pixel
        _pointer(xserver, gx, gy, "click", "1")
        tps = _wait_for(lambda: _tiepoints(site))
        assert len(tps) == 1, "the click made no tie point"
        o = tps[0].observations[0]
        assert o.image == Q0
        # xdotool moves to whole screen pixels: the photo pixel under that screen pixel's centre
        assert abs(o.x - cx) <= 1.0 / zoom and abs(o.y - cy) <= 1.0 / zoom, (o.x, o.y, zoom)
        _pointer(xserver, 1599, 999)
        time.sleep(0.4)
        after = _screenshot(xserver, tmp_path / "after.png")
        # inside the photo the only change is the marker at the clicked spot
        diff = np.abs(after.astype(int) - before.astype(int)).max(axis=2) > 40
        yy, xx = np.mgrid[0:diff.shape[0], 0:diff.shape[1]]
        in_photo = (xx >= x0) & (xx < x1) & (yy >= y0) & (yy < y1)
        near = (np.hypot(xx - gx, yy - gy) < 14) & in_photo
        far = in_photo & (np.hypot(xx - gx, yy - gy) > 80)  # the marker's label sits to its right
        assert diff[near].sum() >= 20, "no marker drawn at the click"
        assert diff[far].mean() < 0.002, diff[far].mean()
        # a real Ctrl+Z (X keyboard events to the window under the pointer) removes it from the file
        _pointer(xserver, wx + ww // 2, wy + wh // 2)
        subprocess.run(["xdotool", "key", "ctrl+z"], env=xserver, check=True, timeout=10)
        assert _wait_for(lambda: not any(t.observations for t in _tiepoints(site))), "Ctrl+Z did not undo"
        out = os.environ.get("GTKIT_X11_SCREENSHOT")  # docs: keep the screenshot with the marker
        if out:
            shutil.copy(tmp_path / "after.png", out)
        print(f"annotator on Xvfb: open {open_s:.2f} s, photo correlation {corr:.4f} (3 px off: {off:.4f}), click at "
              f"({o.x:.2f}, {o.y:.2f}) for ({cx}, {cy}), zoom {zoom:.3f}")
    finally:
        watchdog.cancel()
        app.kill()
        app.wait(10)


def test_annotate_without_a_display_says_what_to_do(tmp_path):
    from gui.demo import make_demo_project

    site = make_demo_project(tmp_path / "site", n_query=1).paths.root
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    env["PYTHONPATH"] = str(ROOT)
    for extra, expect in (({}, "no display"), ({"DISPLAY": ":97", "QT_QPA_PLATFORM": "xcb"}, "no X server for DISPLAY=:97")):
        if extra and os.path.exists("/tmp/.X11-unix/X97"):
            continue
        r = subprocess.run([sys.executable, "-m", "gtkit.cli", "annotate", str(site)], env={**env, **extra},
                           cwd=str(ROOT), capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, (r.returncode, r.stderr[-1500:])
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and expect in lines[0] and "QT_QPA_PLATFORM=offscreen" in lines[0], r.stderr
        assert "Could not load the Qt platform plugin" not in r.stderr


def test_scene_tab_on_xvfb(xserver, finished_demo, tmp_path):
    """The 3D tab in the annotator on X (VTK renders through EGL beside Qt's xcb window): a real
    click on the tab opens it looking through the photo selected in the review tab (the X screen
    shows that photo's view of the model), a real click on "Top" shows the reference cameras' frusta."""
    import cv2

    site = tmp_path / "site"
    shutil.copytree(finished_demo, site)  # its session reopens the review tab on queries/seq1/0000_W.jpg
    script = tmp_path / "actions.json"
    script.write_text(json.dumps([{"locate": "query", "points": [[0, 0]]}, {"until_tab": "3D scene", "locate": "scene"},
                                  {"wait": 120000}]))
    env = dict(xserver, GTKIT_GUI_SCRIPT=str(script))
    app = subprocess.Popen([sys.executable, "-m", "gtkit.cli", "annotate", str(site)], env=env, cwd=str(ROOT),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(150, app.kill)  # a hung GUI must not hang the test run
    watchdog.start()
    try:
        done = (json.loads(line[5:]) for line in app.stdout if line.startswith("DONE "))
        loc = next(done, None)
        assert loc is not None, f"the annotator did not start on X: {app.stderr.read()[-1500:]}"
        _pointer(xserver, *loc["tabs"]["3D scene"], "click", "1")  # a real click on the tab
        sc = next(done, None)
        assert sc is not None and sc["photo"] == "queries/seq1/0000_W.jpg", sc
        _pointer(xserver, 1599, 999)
        time.sleep(0.3)
        shot = _screenshot(xserver, tmp_path / "through_photo.png")
        vx, vy, vw, vh = sc["view"]
        iw, ih = sc["image_size"]
        x0, y0 = vx + (vw - iw) // 2, vy + (vh - ih) // 2  # the rendered image, centred in the view
        corr = _photo_view_corr(shot, (x0, y0, iw, ih), cv2.imread(str(site / "images" / sc["photo"])))
        assert corr > 0.7, corr

        def frustum_pixels(img):
            return _frustum_pixels(img, (vx, vy, vw, vh))

        before = frustum_pixels(shot)
        _pointer(xserver, *sc["buttons"]["Top"], "click", "1")
        _pointer(xserver, 1599, 999)
        after = _wait_for(lambda: (n := frustum_pixels(_screenshot(xserver, tmp_path / "scene.png"))) > before + 500
                          and n, timeout=30)
        assert after, f"no camera frusta on the X screen after 'Top' ({before} frustum-coloured pixels before)"
        out = os.environ.get("GTKIT_X11_SCENE_SCREENSHOT")
        if out:
            shutil.copy(tmp_path / "scene.png", out)
        assert app.poll() is None, app.stderr.read()[-1500:]  # still running: no GL clash
        print(f"3D tab on Xvfb: opened in {sc['open_s']:.2f} s, view through the photo vs the photo: correlation "
              f"{corr:.3f}; frustum pixels {before} -> {after}")
    finally:
        watchdog.cancel()
        app.kill()
        app.wait(10)


def test_scene_tab_interactive_pyvistaqt_on_xvfb(xserver, finished_demo, tmp_path):
    """The 3D tab as a pyvistaqt QtInteractor (GTKIT_SCENE_VIEW=interactive; VTK renders into the
    annotator's OpenGL widget on X, Qt's EGL on Mesa): a real click on the tab opens it through the selected
    photo (the X screen shows that photo's view of the model), "Top" shows the frusta, a real mouse drag
    turns the view (VTK's own mouse handling), and gtkit's own renderer (moderngl, EGL) in the same
    process still renders the review aligned, after which the tab draws again."""
    pytest.importorskip("pyvistaqt")
    import cv2

    site = tmp_path / "site"
    shutil.copytree(finished_demo, site)
    script = tmp_path / "actions.json"
    script.write_text(json.dumps([{"locate": "query", "points": [[0, 0]]}, {"until_tab": "3D scene", "locate": "scene"},
                                  {"until_tab": "Alignment review", "key": "K"}, {"locate": "review"},
                                  {"until_tab": "3D scene", "locate": "scene"}, {"wait": 120000}]))
    env = dict(xserver, GTKIT_GUI_SCRIPT=str(script), GTKIT_SCENE_VIEW="interactive")
    app = subprocess.Popen([sys.executable, "-m", "gtkit.cli", "annotate", str(site)], env=env, cwd=str(ROOT),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(150, app.kill)
    watchdog.start()
    try:
        done = (json.loads(line[5:]) for line in app.stdout if line.startswith("DONE "))
        loc = next(done, None)
        assert loc is not None, f"the annotator did not start on X: {app.stderr.read()[-1500:]}"
        _pointer(xserver, *loc["tabs"]["3D scene"], "click", "1")
        sc = next(done, None)
        assert sc is not None and sc["backend"] == "interactive", sc
        assert sc["photo"] == "queries/seq1/0000_W.jpg"
        from gtkit.io.poses import read_poses

        pose = read_poses(site / "work/localize/poses.txt")[sc["photo"]]
        assert np.allclose(sc["camera"]["position"], pose.center, atol=1e-6)
        _pointer(xserver, 1599, 999)
        time.sleep(0.5)
        shot = _screenshot(xserver, tmp_path / "through_photo.png")
        view = sc["view"]
        vx, vy, vw, vh = view
        corr = _photo_view_corr(shot, view, cv2.imread(str(site / "images" / sc["photo"])))
        assert corr > 0.7, corr
        _pointer(xserver, *sc["buttons"]["Top"], "click", "1")
        _pointer(xserver, 1599, 999)
        top = _wait_for(lambda: (n := _frustum_pixels(_screenshot(xserver, tmp_path / "top.png"), view)) > 500 and n,
                        timeout=30)
        assert top, "no camera frusta on the X screen after 'Top'"
        before = _screenshot(xserver, tmp_path / "top.png")[vy:vy + vh, vx:vx + vw]
        # a real drag with the left button: VTK's trackball turns the camera
        cx, cy = vx + vw // 2, vy + vh // 2
        _pointer(xserver, cx, cy, "mousedown", "1")
        for dx in range(20, 201, 20):
            _pointer(xserver, cx + dx, cy + dx // 4)
            time.sleep(0.05)
        subprocess.run(["xdotool", "mouseup", "1"], env=xserver, check=True, timeout=10)
        _pointer(xserver, 1599, 999)
        time.sleep(0.5)
        after = _screenshot(xserver, tmp_path / "dragged.png")[vy:vy + vh, vx:vx + vw]
        changed = float((np.abs(after.astype(int) - before.astype(int)).max(axis=2) > 40).mean())
        assert changed > 0.2, changed
        out = os.environ.get("GTKIT_X11_INTERACTIVE_SCREENSHOT")
        if out:
            shutil.copy(tmp_path / "dragged.png", out)
        # gtkit's renderer beside VTK in this process: the review renders the next photo's model view aligned
        _pointer(xserver, *loc["tabs"]["Alignment review"], "click", "1")
        next(done, None)  # the key K: next photo
        rv = next(done, None)
        assert rv is not None and rv["image"] == "queries/seq1/0001_W.jpg", rv
        assert rv["misalignment_px"] is not None and rv["misalignment_px"] < 1.0, rv
        # ... and back in the 3D tab, VTK draws again: the view through the review's photo
        _pointer(xserver, *loc["tabs"]["3D scene"], "click", "1")
        sc2 = next(done, None)
        assert sc2 is not None and sc2["photo"] == "queries/seq1/0001_W.jpg", sc2
        _pointer(xserver, 1599, 999)
        time.sleep(0.5)
        corr2 = _photo_view_corr(_screenshot(xserver, tmp_path / "through_photo2.png"), view,
                                 cv2.imread(str(site / "images" / sc2["photo"])))
        assert corr2 > 0.7, corr2
        assert app.poll() is None, app.stderr.read()[-1500:]
        print(f"interactive 3D tab on Xvfb: opened in {sc['open_s']:.2f} s, through-photo correlation {corr:.3f}, "
              f"{changed:.0%} of the view changed by the drag, review misalignment {rv['misalignment_px']:.2f} px, "
              f"then through the next photo {corr2:.3f}")
    finally:
        watchdog.cancel()
        app.kill()
        app.wait(10)
