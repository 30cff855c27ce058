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


def test_scene_draws_tiepoints_gcps_and_targets_where_they_are(finished_demo, tmp_path):
    """Tie points placed on the model from their reference clicks (flagged ones in white), GCPs with
    their residual vectors, tracked targets with their track and lines of sight: each drawn in its
    colour where the view projects its 3D position (top view, offscreen PNG pixels)."""
    import cv2

    from gtkit.io.poses import read_intrinsics, read_poses, write_poses
    from gtkit.io.tiepoints import Observation, TiePoint, write_tiepoints
    from gtkit.project import Project
    from gtkit.view.process import SceneProcess
    from gtkit.view.scene import COLORS, ViewSettings, load_scene

    site = tmp_path / "site"
    shutil.copytree(finished_demo, site)
    proj = Project.load(site)
    origin = np.asarray(proj.frame.origin)
    truth, cams = read_poses(site / "truth/poses.txt"), read_intrinsics(site / "truth/intrinsics.txt")
    refs = {n: p for n, p in truth.items() if n.startswith("reference/")}
    write_poses(site / "work/sfm_reference/poses.txt", refs)  # the reference block's poses
    # three ground points (z = 0) that the true cameras see (no box of the demo model on the line of
    # sight: slab test on the boxes' bounds), clicked where they see them
    from gui.demo import demo_mesh

    boxes = [np.stack([p.vertices.min(0), p.vertices.max(0)]) for p in demo_mesh(0).parts[1:]]
    n0, n1, q = "reference/R01_000_N.jpg", "reference/R01_001_N.jpg", "queries/seq1/0001_W.jpg"

    def blocked(c, X, b):
        d = X - c
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (b[0] - 0.5 - c) / d, (b[1] + 0.5 - c) / d
        lo, hi = np.nanmax(np.minimum(t0, t1)), np.nanmin(np.maximum(t0, t1))
        return lo <= min(hi, 0.999)

    def seen(name, X):
        c = truth[name].center
        return (bool(cams[name].in_image(cams[name].project(truth[name].transform(X[None]))[0][0], margin=20))
                and not any(blocked(c, X, b) for b in boxes))

    clear = [X for X in (np.array([x, y, 0.0]) for x in range(-60, 61, 6) for y in range(-60, 61, 6))
             if seen(n0, X) and seen(n1, X) and seen(q, X)]
    assert len(clear) >= 5
    A, B, C = clear[0], clear[len(clear) // 2], clear[-1]

    def click(name, X):
        uv = cams[name].project(truth[name].transform(X[None]))[0][0]
        assert cams[name].in_image(uv), (name, X)
        return Observation(name, float(uv[0]), float(uv[1]))

    write_tiepoints(site / "tiepoints.json", [
        TiePoint("tA", [click(q, A), click(n0, A), click(n1, A)]), TiePoint("tB", [click(q, B), click(n1, B)]),
        TiePoint("tC", [click(q, C), click(n0, C)])])
    (site / "work/register").mkdir(parents=True, exist_ok=True)
    (site / "work/register/registration.json").write_text(json.dumps({
        "tiepoints": {t: {"in_final_ba": t != "tC"} for t in ("tA", "tB", "tC")},
        "bad_tiepoints": {"tC": {"reason": "clicks dropped as mistakes"}}}))
    # two GCPs; one with a 0.3 m residual (drawn 50x: 15 m)
    open_ground = [np.array([x, y, 0.0]) for x in range(-80, 81, 10) for y in range(-80, 81, 10)
                   if not any((b[0, :2] - 4 < (x, y)).all() and ((x, y) < b[1, :2] + 4).all() for b in boxes)]
    G1, G2 = open_ground[0], open_ground[-1]
    (site / "gcp_list.txt").write_text(f"{proj.frame.crs_spec}\n" + "".join(
        f"{x + origin[0]:.3f} {y + origin[1]:.3f} {z:.3f} 10 10 {n0} {name}\n" for name, (x, y, z) in (("g1", G1), ("g2", G2))))
    (site / "work/sfm_reference/block.json").write_text(json.dumps({"georegistration": {"gcp_residuals": {
        "g1": {"status": "ok", "dx_m": 0.3, "dy_m": 0.0, "dz_m": 0.0}}}}))
    # a tracked car: three placed detections in zoom photos of seq1 (the wide twins are localized)
    T = [np.array([-20.0 + 12 * k, -75.0 + 3 * k, 0.0]) for k in range(3)]
    rows = ["# gtkit track: test rows", "label,time,image,u,v,status,x,y,z,message"]
    rows += [f"car,{k}.0,queries/seq1/{k:04d}_Z.jpg,100,100,ok,{p[0] + origin[0]:.3f},{p[1] + origin[1]:.3f},{p[2]:.3f},"
             for k, p in enumerate(T)]
    (site / "exports").mkdir(exist_ok=True)
    (site / "exports/tracks.csv").write_text("\n".join(rows) + "\n")

    # a zoom photo looks from its wide twin's pose through the rig (3 degrees apart, 1500 px focal)
    from scipy.spatial.transform import Rotation

    R_zw = Rotation.from_euler("y", 3, degrees=True).as_matrix()
    (site / "work/rig").mkdir(parents=True)
    (site / "work/rig/rig.json").write_text(json.dumps({"R_zoom_from_wide": R_zw.tolist(), "offset_m": [0, 0, 0],
                                                         "zoom": [{"focal_mm": None, "camera": "PINHOLE 640 480 1500 1500 320 240"}]}))
    shutil.copy(site / "images/queries/seq1/0001_W.jpg", site / "images/queries/seq1/0001_Z.jpg")
    sc = load_scene(site)  # placement (no rendering)
    for tid, X in (("tA", A), ("tB", B), ("tC", C)):
        assert np.linalg.norm(sc.tiepoints[tid] - X) < 0.05, (tid, sc.tiepoints[tid], X)
    assert sc.tiepoints_flagged == {"tC"} and set(sc.tracks) == {("car", "queries/seq1")}
    assert np.allclose(sc.tracks[("car", "queries/seq1")], T, atol=1e-3)
    sp = SceneProcess(site, 900, 900)
    try:
        assert sp.info["n_tiepoints"] == 3 and sp.info["n_targets"] == 3 and sp.info["n_gcps"] == 2
        sp.overview("top")
        img = sp.render()
        px = {k: sp.world_to_pixel([X])[0] for k, X in
              (("A", A), ("B", B), ("C", C), ("G1", G1), ("G2", G2), ("res", G1 + [15.0, 0, 0]),
               *((f"T{k}", p) for k, p in enumerate(T)), ("line", (T[0] + T[1]) / 2))}
        wide = read_poses(site / "work/localize/poses.txt")["queries/seq1/0001_W.jpg"]
        eye = wide.center
        px["sight"] = sp.world_to_pixel([0.5 * (eye + T[1])])[0]
        assert sp.photo("queries/seq1/0001_Z.jpg")
        cam = sp.camera()
        axis = np.subtract(cam["focal_point"], cam["position"])
        assert np.allclose(cam["position"], eye, atol=1e-6)
        assert np.allclose(axis / np.linalg.norm(axis), (R_zw @ wide.R)[2], atol=1e-6)
        assert abs(cam["view_angle"] - np.degrees(2 * np.arctan(240 / 1500))) < 1e-6
    finally:
        sp.close()
    sp = SceneProcess(site, 900, 900, ViewSettings(layers=("model",)))  # the same view, model only
    try:
        sp.overview("top")
        bare = sp.render()
    finally:
        sp.close()
    cv2.imwrite(str(tmp_path / "top.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))

    def rgb(name):
        return np.array([int(COLORS[name][i:i + 2], 16) for i in (1, 3, 5)])

    expect = {"A": "tiepoint", "B": "tiepoint", "C": "tiepoint_flagged", "G1": "gcp", "G2": "gcp", "res": "residual",
              "T0": "track", "T1": "track", "T2": "track", "line": "track", "sight": "sight"}
    missing = {k: (c, px[k].round(1).tolist()) for k, c in expect.items() if not _near_colour(img, px[k], rgb(c), r=4, tol=50)}
    assert not missing, missing
    # ... and not there in the model alone (the demo's texture is colourful)
    in_model = {k: c for k, c in expect.items() if _near_colour(bare, px[k], rgb(c), r=4, tol=50)}
    assert not in_model, in_model
