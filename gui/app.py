"""Start the annotator: ``gtkit annotate DIR`` or ``python -m gui DIR``.

``GTKIT_GUI_SCRIPT=actions.json`` drives the window with real mouse and key events (tests,
demos): a list of ``{"click": "query"|"reference", "x": .., "y": ..}``, ``{"key": "Ctrl+Z"}``,
``{"pair": [query, reference]}``, ``{"wait": ms}`` or ``{"quit": true}``. After each action the app prints one line
``DONE <json>`` (with the tie point it committed), flushed, so a driver can kill it at any point.
"""
from __future__ import annotations

import json
import os
import sys


def make_app():
    from PySide6.QtWidgets import QApplication

    return QApplication.instance() or QApplication(sys.argv[:1])


def main(project_dir, poses=None, query=None) -> int:
    if not (os.environ.get("QT_QPA_PLATFORM") or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
            or sys.platform in ("win32", "darwin")):
        from gtkit.errors import GtkitError

        raise GtkitError("no display for the annotator (DISPLAY is not set): run it on a desktop, "
                         "or set QT_QPA_PLATFORM=offscreen for scripted use; `gtkit overlay` works headless")
    from gtkit.project import Project

    Project.load(project_dir)  # a clear one-line error before any window opens
    app = make_app()
    from .main_window import MainWindow

    w = MainWindow(project_dir, poses=poses, query=query)
    w.show()
    from PySide6.QtCore import QTimer

    QTimer.singleShot(0, w.restore_views)
    script = os.environ.get("GTKIT_GUI_SCRIPT")
    if script:
        from .script import ScriptRunner

        runner = ScriptRunner(w, json.loads(open(script, encoding="utf-8").read()),
                              int(os.environ.get("GTKIT_GUI_SCRIPT_INTERVAL_MS", "50")))
        QTimer.singleShot(300, runner.start)
    return app.exec()
