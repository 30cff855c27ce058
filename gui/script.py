"""Drive the annotator with real input events from a list of actions (see :mod:`gui.app`)."""
from __future__ import annotations

import json
import sys

from PySide6.QtCore import QObject, Qt, QTimer
from PySide6.QtGui import QKeySequence
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication, QPushButton


class ScriptRunner(QObject):
    def __init__(self, window, actions: list[dict], interval_ms: int = 50, out=sys.stdout):
        super().__init__(window)
        self.w, self.actions, self.interval, self.out = window, list(actions), interval_ms, out
        self.k = 0

    def start(self):
        self.out.write(f"READY {len(self.w.store)}\n")
        self.out.flush()
        QTimer.singleShot(0, self.step)

    def step(self):
        if self.k >= len(self.actions):
            self.out.write("FINISHED\n")
            self.out.flush()
            return
        a = self.actions[self.k]
        if "until_tab" in a and self.w.tabs.tabText(self.w.tabs.currentIndex()) != a["until_tab"]:
            QTimer.singleShot(50, self.step)  # a driver switches tabs (e.g. with a real click): wait for it
            return
        self.k += 1
        wait = self.interval
        info = run_action(self.w, a)
        if "wait" in a:
            wait = int(a["wait"])
        self.out.write("DONE " + json.dumps(info) + "\n")
        self.out.flush()
        QTimer.singleShot(wait, self.step)


def run_action(w, a: dict) -> dict:
    """Perform one action on the main window with real events; returns what was committed."""
    page = w.tiepoints
    if "click" in a:
        view = page.qview if a["click"] == "query" else page.rview
        image = page.query if a["click"] == "query" else page.reference
        pos = view.scene_to_widget(float(a["x"]), float(a["y"]))
        before = page.undo.index()
        QTest.mouseClick(view.viewport(), Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, pos)
        committed = page.undo.index() > before
        o = page.store.observation(page.active, image) if committed else None
        return {"action": a, "tp": page.active if committed else None, "image": image,
                "x": o.x if o else None, "y": o.y if o else None}
    if "key" in a:
        seq = QKeySequence(a["key"])[0]
        QTest.keyClick(w, seq.key(), seq.keyboardModifiers())
        return {"action": a, "undo_index": page.undo.index(), "n_tiepoints": len(page.store)}
    if a.get("quit"):
        w.close()
        QTimer.singleShot(0, QApplication.instance().quit)
        return {"action": a}
    if a.get("locate") == "scene":  # the 3D tab's view and buttons on the screen
        sc = w.scene3d
        QApplication.processEvents()
        v = sc.view_widget()
        g = v.mapToGlobal(v.rect().topLeft())
        buttons = {b.text(): [(c := b.mapToGlobal(b.rect().center())).x(), c.y()]
                   for b in sc.findChildren(QPushButton)}
        return {"action": a, "photo": sc.photo, "view": [g.x(), g.y(), v.width(), v.height()],
                "image_size": list(sc.image().shape[1::-1]) if sc.image() is not None else None, "buttons": buttons,
                "open_s": sc.open_s, "backend": sc.backend, "backend_why": sc.backend_why,
                "camera": sc.proc.camera() if sc.proc is not None else None}
    if a.get("locate") == "review":  # what the review tab shows (gtkit's own renderer)
        rv = w.review
        QApplication.processEvents()
        return {"action": a, "image": rv.image,
                "misalignment_px": float(rv._cache[5].misalignment_px) if rv._cache is not None else None}
    if "locate" in a:  # where photo pixels are on the screen, for drivers that click with real X events
        from PySide6.QtCore import QPointF

        view = page.qview if a["locate"] == "query" else page.rview
        vp, tf = view.viewport(), view.viewportTransform()
        pts = []
        for x, y in a.get("points", []):
            g = vp.mapToGlobal(tf.map(QPointF(float(x), float(y))))
            pts.append([g.x(), g.y()])
        return {"action": a, "image": page.query if a["locate"] == "query" else page.reference,
                "screen": pts, "zoom": view.zoom(), "window": [w.x(), w.y(), w.width(), w.height()],
                "viewport": [vp.mapToGlobal(vp.rect().topLeft()).x(), vp.mapToGlobal(vp.rect().topLeft()).y(),
                             vp.width(), vp.height()],
                "tabs": {w.tabs.tabText(i): [(c := w.tabs.tabBar().mapToGlobal(w.tabs.tabBar().tabRect(i).center())).x(),
                                             c.y()] for i in range(w.tabs.count())}}
    if "pair" in a:
        page.set_pair(*a["pair"])
        return {"action": a, "query": page.query, "reference": page.reference}
    return {"action": a}
