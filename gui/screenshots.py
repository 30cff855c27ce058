"""Screenshots of every mode of the annotator, grabbed offscreen (QWidget.grab):

    QT_QPA_PLATFORM=offscreen python -m gui.screenshots SITE --poses SITE/truth/poses.txt --out docs/images

Writes gui_tiepoints.png (workspace with the loupe), gui_suggestions.png, gui_review_<mode>.png
for blend / swipe / edges / checker at the given poses, and gui_review_edges_off1deg.png with the
pose turned by 1 degree (visibly misaligned)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def main(argv=None):
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    ap = argparse.ArgumentParser(prog="python -m gui.screenshots")
    ap.add_argument("project")
    ap.add_argument("--poses", required=True)
    ap.add_argument("--out", default="docs/images")
    ap.add_argument("--query", help="query photo to show (default: the first)")
    ap.add_argument("--review-image", help="image for the review shots (default: the query)")
    ap.add_argument("--size", default="1500x900")
    a = ap.parse_args(argv)
    import numpy as np
    from PySide6.QtCore import QEvent, QPointF, Qt
    from PySide6.QtGui import QMouseEvent
    from PySide6.QtWidgets import QApplication
    from scipy.spatial.transform import Rotation

    from gtkit.pose import Pose

    from .app import make_app
    from .main_window import MainWindow

    app = make_app()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    w = MainWindow(a.project, poses=a.poses, query=a.query)
    w.resize(*map(int, a.size.split("x")))
    w.show()
    w.tabs.setCurrentIndex(0)
    app.processEvents()
    page = w.tiepoints
    page.qview.fit()
    page.rview.fit()
    # the tie points of this pair, the first one active, the loupe over it
    tps = [t for t, _ in page.store.in_image(page.query) if any(o.image == page.reference for o in t.observations)]
    if not tps:
        ranked = page.store.pair_counts(page.query)
        if ranked:
            page.set_pair(page.query, max(ranked, key=ranked.get))
            tps = [t for t, _ in page.store.in_image(page.query)
                   if any(o.image == page.reference for o in t.observations)]
    if tps:
        page.active = tps[0].id
        page.refresh()
        o = page.store.observation(tps[0].id, page.query)
        pos = QPointF(page.qview.scene_to_widget(o.x, o.y))
    else:
        pos = QPointF(page.qview.viewport().width() / 2, page.qview.viewport().height() / 2)
    app.processEvents()
    ev = QMouseEvent(QEvent.Type.MouseMove, pos, page.qview.viewport().mapToGlobal(pos), Qt.MouseButton.NoButton,
                     Qt.MouseButton.NoButton, Qt.KeyboardModifier.NoModifier)
    QApplication.sendEvent(page.qview.viewport(), ev)
    app.processEvents()
    w.grab().save(str(out / "gui_tiepoints.png"))
    page.qview.loupe.hide()
    page.compute_suggestions(sync=True)
    page.qview.fit()
    page.rview.fit()
    app.processEvents()
    w.grab().save(str(out / "gui_suggestions.png"))
    page.suggestions = []
    page.refresh()

    w.tabs.setCurrentIndex(1)
    rv = w.review
    rv.open_image(a.review_image or page.query)
    app.processEvents()
    for mode in ("blend", "swipe", "edges", "checker"):
        rv.set_mode(mode)
        rv.slider.setValue(50 if mode == "blend" else 45)
        app.processEvents()
        rv.view.fit()
        app.processEvents()
        w.grab().save(str(out / f"gui_review_{mode}.png"))
    name = rv.image
    p = rv.scene.poses[name]
    R = Rotation.from_rotvec(np.radians(1.0) * np.array([0.0, 1.0, 0.0])).as_matrix() @ p.R
    rv.scene.poses[name] = Pose.from_center(R, p.center)
    rv._cache = None
    rv.open_image(name)
    rv.set_mode("edges")
    app.processEvents()
    rv.view.fit()
    app.processEvents()
    w.grab().save(str(out / "gui_review_edges_off1deg.png"))
    print(rv.measure.text())
    rv.scene.poses[name] = p
    w.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
