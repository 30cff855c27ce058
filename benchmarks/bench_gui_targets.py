"""Targets tab end to end on a sample site: clicks through the annotator (real mouse events,
offscreen) at the TRUE projections of the site's targets, then ``gtkit track`` with the true
wide poses, against truth; next to the tracker fed the exact true pixels without the GUI.
Prints the click precision, both error summaries and the click / track times.

    QT_QPA_PLATFORM=offscreen python benchmarks/bench_gui_targets.py SITE WORKDIR [--zoom 4]

SITE is read only (a sample project, e.g. ``gtkit sample create SITE --preset small``); it is
copied to WORKDIR (without work/, exports/, reports/), where the rig is calibrated, the DSM
exported, and ``detections.csv`` written by the GUI. Reads truth/ (evaluation only).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("site")
    ap.add_argument("workdir")
    ap.add_argument("--zoom", type=float, default=4.0, help="view zoom while clicking (screen px per photo px)")
    a = ap.parse_args(argv)
    import numpy as np
    from PySide6.QtCore import Qt
    from PySide6.QtTest import QTest

    from gtkit.cli import main as gtkit
    from gtkit.evaluate.tracking import evaluate_tracking, simulate_detections
    from gtkit.project import Project
    from gtkit.track import calibrate
    from gtkit.track.rig import RigCalibrationSettings
    from gtkit.track.targets import read_csv
    from gui.app import make_app
    from gui.main_window import MainWindow

    dst = Path(a.workdir)
    if not dst.exists():
        shutil.copytree(a.site, dst, ignore=shutil.ignore_patterns("work", "exports", "reports"))
    P = Project.load(dst).paths
    calibrate.run(Project.load(dst), RigCalibrationSettings(max_pairs=14))
    if not P.dsm.is_file():
        assert gtkit(["export", "dsm", str(dst)]) == 0
    n = simulate_detections(P, dst / "truth_pixels.csv", sigma_px=0.0, mode="point")
    true = read_csv(dst / "truth_pixels.csv")
    track = ["track", str(dst), "--poses", str(P.truth / "poses.txt"), "--force"]
    shutil.copy(dst / "truth_pixels.csv", P.detections)        # the tracker on the exact pixels
    assert gtkit(track) == 0
    ref = evaluate_tracking(P)
    P.detections.unlink()

    app = make_app()
    w = MainWindow(dst)
    w.resize(1500, 900)
    w.show()
    w.tabs.setCurrentIndex(2)
    app.processEvents()
    page = w.targets
    t0 = time.perf_counter()
    for d in true:
        page.open_image(d.image)
        page.label_box.setCurrentText(d.label)
        page.view.center_on(d.u, d.v, zoom=a.zoom)
        app.processEvents()
        QTest.mouseClick(page.view.viewport(), Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                         page.view.scene_to_widget(d.u, d.v))
    t_click = time.perf_counter() - t0
    w.close()
    clicked = read_csv(P.detections)
    assert [(c.image, c.label) for c in clicked] == [(d.image, d.label) for d in true]
    px = np.array([np.hypot(c.u - d.u, c.v - d.v) for c, d in zip(clicked, true)])
    t0 = time.perf_counter()
    assert gtkit(track) == 0                                  # reads the GUI's detections.csv
    t_track = time.perf_counter() - t0
    rep = evaluate_tracking(P)
    e_ref = np.array([r.get("err_3d_m", np.nan) for r in ref["per_detection"]])
    e_gui = np.array([r.get("err_3d_m", np.nan) for r in rep["per_detection"]])

    def f(v):
        return "-" if v is None else f"{v:.3f}"

    print(f"\n{n} visible targets; GUI clicks at zoom {a.zoom:g} vs true pixel: median {np.median(px):.3f} px, "
          f"max {px.max():.3f} px; {len(true)} photos opened + clicked in {t_click:.2f} s; gtkit track {t_track:.2f} s")
    print("| detections | located | median err h m | median err 3D m | p90 err 3D m |")
    print("|---|---|---|---|---|")
    for name, r in (("true pixels (no GUI)", ref), ("GUI clicks", rep)):
        print(f"| {name} | {r['n_targets'] - r['n_failed']}/{r['n_targets']} | {f(r['median_err_h_m'])} | "
              f"{f(r['median_err_3d_m'])} | {f(r.get('p90_err_3d_m'))} |")
    print(f"per target, |3D error GUI - 3D error true pixels|: max {np.nanmax(np.abs(e_gui - e_ref)):.3f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
