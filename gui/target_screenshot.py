"""Screenshot of the annotator's Targets tab, grabbed offscreen (QWidget.grab):

    QT_QPA_PLATFORM=offscreen python -m gui.target_screenshot SITE --out docs/images [--image NAME]

Writes gui_targets.png: the zoom photo (default: the first one with targets in the project's
detections.csv), zoomed onto its targets, the first one selected, the loupe at it, and the
table with each target's tracked position when ``gtkit track`` has run. Places no click:
it writes only the annotator's session file (work/annotate/session.json)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def main(argv=None):
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    ap = argparse.ArgumentParser(prog="python -m gui.target_screenshot")
    ap.add_argument("project")
    ap.add_argument("--out", default="docs/images")
    ap.add_argument("--image", help="zoom photo to show (default: the first with targets)")
    ap.add_argument("--zoom", type=float, default=0.0, help="view zoom (screen px per photo px; 0 = fit)")
    ap.add_argument("--size", default="1500x900")
    a = ap.parse_args(argv)
    from PySide6.QtCore import QEvent, QPointF, Qt
    from PySide6.QtGui import QMouseEvent
    from PySide6.QtWidgets import QApplication

    from .app import make_app
    from .main_window import MainWindow

    app = make_app()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    w = MainWindow(a.project)
    w.resize(*map(int, a.size.split("x")))
    w.show()
    w.tabs.setCurrentIndex(2)
    app.processEvents()
    page = w.targets
    counts = page.store.counts() if page.store else {}
    page.open_image(a.image or (min(counts) if counts else None))
    targets = page.store.in_image(page.image) if page.store else []
    page.view.fit()
    if targets:
        page.select(targets[0].id)
        if a.zoom:
            page.view.center_on(sum(t.x for t in targets) / len(targets), sum(t.y for t in targets) / len(targets),
                                zoom=a.zoom)
        app.processEvents()
        pos = QPointF(page.view.scene_to_widget(targets[0].x, targets[0].y))
        ev = QMouseEvent(QEvent.Type.MouseMove, pos, page.view.viewport().mapToGlobal(pos), Qt.MouseButton.NoButton,
                         Qt.MouseButton.NoButton, Qt.KeyboardModifier.NoModifier)
        QApplication.sendEvent(page.view.viewport(), ev)
    app.processEvents()
    w.grab().save(str(out / "gui_targets.png"))
    print(out / "gui_targets.png", page.image, len(targets), "targets")
    w.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
