"""Annotator responsiveness on big photos: a synthetic project with 20-megapixel JPEGs and 1,000
tie points. Prints a table of: time to open the project (window shown, first pair displayed),
time to switch the query photo / the reference photo (a preview decoded by QImageReader with
JPEG DCT scaling to 1/2^k size, prefetched in the background for the photos N / P / PgDn
would open next; markers redrawn), time until the full resolution is shown after zooming in
(background decode), and time for one click to be saved (tiepoints.json rewritten atomically).

    QT_QPA_PLATFORM=offscreen python benchmarks/bench_gui.py [--keep DIR]

With ``--alignment SITE`` it instead prints the alignment measures (gtkit.render.overlay) of
photos of a sample site at the true pose and at poses 1 m east / turned 1 degree:

    python benchmarks/bench_gui.py --alignment sample_site [--every 4]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def alignment_table(site: Path, every: int):
    import numpy as np
    from scipy.spatial.transform import Rotation

    from gtkit.pose import Pose
    from gtkit.project import Project
    from gtkit.render.overlay import OverlayScene, alignment

    scene = OverlayScene(Project.load(site), site / "truth" / "poses.txt")
    names = scene.images()
    picks = [n for n in names if n.startswith("queries/")][::every] + [n for n in names if n.startswith("reference/")][::4 * every]
    rows = []
    print(f"{'image':34s} {'misalignment px: true / 1 m / 1 deg':>38s} {'edge distance px: true / 1 m / 1 deg':>38s}")
    for name in picks:
        photo, _, _, s = scene.render(name)
        p = scene.poses[name]
        R1 = Rotation.from_rotvec(np.radians(1.0) * np.array([0.0, 1.0, 0.0])).as_matrix() @ p.R
        res = []
        for q in (p, Pose.from_center(p.R, p.center + [1.0, 0, 0]), Pose.from_center(R1, p.center)):
            _, rgb, valid, _ = scene.render(name, pose=q)
            res.append(alignment(photo, rgb, valid, scale=s))
        rows.append([[a.misalignment_px for a in res], [a.edge_distance_px for a in res]])
        m, e = rows[-1]
        print(f"{name:34s} {m[0]:12.2f} {m[1]:8.2f} {m[2]:8.2f}       {e[0]:12.2f} {e[1]:8.2f} {e[2]:8.2f}", flush=True)
    a = np.array(rows, dtype=float)
    med = np.nanmedian(a, axis=0)
    print(f"{'median of ' + str(len(rows)) + ' images':34s} {med[0][0]:12.2f} {med[0][1]:8.2f} {med[0][2]:8.2f}"
          f"       {med[1][0]:12.2f} {med[1][1]:8.2f} {med[1][2]:8.2f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--keep", help="build the project here and keep it")
    ap.add_argument("--n-query", type=int, default=4)
    ap.add_argument("--tiepoints", type=int, default=1000)
    ap.add_argument("--alignment", help="print the alignment table for this sample site instead")
    ap.add_argument("--every", type=int, default=4, help="with --alignment: every n-th query photo")
    a = ap.parse_args()
    if a.alignment:
        return alignment_table(Path(a.alignment), a.every)
    from gui.demo import make_demo_project

    root = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="gtkit_bench_gui_")) / "site"
    t = time.perf_counter()
    if not (root / "project.toml").is_file():
        make_demo_project(root, size=(1368, 912), photo_scale=4, n_query=a.n_query, n_tiepoints=a.tiepoints)
    t_make = time.perf_counter() - t
    from PIL import Image

    q0 = sorted((root / "images/queries/seq1").glob("*.jpg"))[0]
    with Image.open(q0) as im:
        w, h = im.size
    mb = q0.stat().st_size / 1e6

    from PySide6.QtWidgets import QApplication

    app = QApplication.instance() or QApplication([])
    from gui.main_window import MainWindow

    import shutil

    shutil.rmtree(root / "work" / "annotate", ignore_errors=True)  # cold: no session, no prior cache
    rows = []
    t = time.perf_counter()
    win = MainWindow(root)
    win.show()
    app.processEvents()
    rows.append(("open project (first pair shown, cold)", time.perf_counter() - t))
    n_tp = len(win.store)
    win.close()
    t = time.perf_counter()
    win = MainWindow(root)
    win.show()
    app.processEvents()
    rows.append(("open project again (prior cache warm)", time.perf_counter() - t))
    page = win.tiepoints

    def timed(fn, n, think=0.5):
        """Time each switch; between switches the user looks at the photos for ``think`` s
        (the event loop runs, so background prefetching can work)."""
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn()
            app.processEvents()
            out.append(time.perf_counter() - t0)
            t1 = time.perf_counter()
            while time.perf_counter() - t1 < think:
                app.processEvents()
                time.sleep(0.01)
        return out

    sq = timed(lambda: page.step_query(1), 2 * a.n_query)
    rows.append((f"switch query photo (median of {len(sq)})", statistics.median(sq)))
    rows.append(("switch query photo (max)", max(sq)))
    sr = timed(lambda: page.step_reference(1), 12)
    rows.append((f"switch reference photo (median of {len(sr)})", statistics.median(sr)))
    rows.append(("switch reference photo (max)", max(sr)))
    # zoom in past the preview: the full resolution is decoded in the background
    v = page.rview
    win.cache._full.clear()
    t0 = time.perf_counter()
    v.center_on(w / 2, h / 2, zoom=1.5)
    t_zoom_ui = time.perf_counter() - t0
    while not v._is_full and time.perf_counter() - t0 < 30:
        app.processEvents()
        time.sleep(0.005)
    rows.append(("zoom in: UI blocked (full resolution decodes in the background)", t_zoom_ui))
    rows.append(("zoom in: full resolution shown", time.perf_counter() - t0))
    clicks = []
    for k in range(10):
        t0 = time.perf_counter()
        page.place(page.query, w / 2 + k, h / 2 + k)
        app.processEvents()
        clicks.append(time.perf_counter() - t0)
    rows.append((f"one click placed and saved ({len(win.store)} tie points, median)", statistics.median(clicks)))
    win.close()

    print(f"\nproject: {root}  ({n_tp} tie points, photos {w}x{h} = {w * h / 1e6:.1f} MP, {mb:.1f} MB JPEG; "
          f"built in {t_make:.0f} s)")
    print(f"{'step':58s} {'seconds':>8s}")
    for name, s in rows:
        print(f"{name:58s} {s:8.3f}")


if __name__ == "__main__":
    main()
