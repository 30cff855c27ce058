"""Start the annotator: ``gtkit annotate DIR`` or ``python -m gui DIR``.

``GTKIT_GUI_SCRIPT=actions.json`` drives the window with real mouse and key events (tests,
demos): a list of ``{"click": "query"|"reference", "x": .., "y": ..}``, ``{"key": "Ctrl+Z"}``,
``{"pair": [query, reference]}``, ``{"wait": ms}``, ``{"quit": true}`` or
``{"locate": "query"|"reference", "points": [[x, y], ..]}`` (the screen positions of photo pixels, for
drivers that click with real X events, e.g. ``xdotool``). After each action the app prints one line
``DONE <json>`` (with the tie point it committed), flushed, so a driver can kill it at any point.
"""
from __future__ import annotations

import json
import os
import sys


def make_app():
    from PySide6.QtWidgets import QApplication

    # gtkit's own renderer (the review) holds an EGL context in this process; after it, Qt's GLX
    # contexts on X fail to become current ("QOpenGLWidget: Failed to make context current",
    # measured with Mesa), which the interactive 3D tab needs: Qt's OpenGL on X goes through EGL too
    os.environ.setdefault("QT_XCB_GL_INTEGRATION", "xcb_egl")
    return QApplication.instance() or QApplication(sys.argv[:1])


# what PySide6's xcb platform plugin loads beyond the offscreen set (Debian 12 package -> library)
XCB_LIBS = {"libxkbcommon-x11-0": "libxkbcommon-x11.so.0", "libxcb-cursor0": "libxcb-cursor.so.0",
            "libxcb-icccm4": "libxcb-icccm.so.4", "libxcb-image0": "libxcb-image.so.0",
            "libxcb-keysyms1": "libxcb-keysyms.so.1", "libxcb-render-util0": "libxcb-render-util.so.0",
            "libxcb-shape0": "libxcb-shape.so.0", "libxcb-xkb1": "libxcb-xkb.so.1"}


def display_problem(env=None) -> str | None:
    """Why Qt could not open a window here (one line saying what to do), or None. Checked before Qt
    loads: a missing display or missing X libraries make Qt abort the process with a long message."""
    env = os.environ if env is None else env
    if sys.platform in ("win32", "darwin"):
        return None
    platform = env.get("QT_QPA_PLATFORM", "")
    if platform and not platform.startswith("xcb"):
        return None  # offscreen, wayland, ...: Qt's own choice
    if not platform and env.get("WAYLAND_DISPLAY"):
        return None
    disp = env.get("DISPLAY")
    if not disp:
        return ("no display for the annotator (neither DISPLAY nor WAYLAND_DISPLAY is set): run it on a desktop "
                "(or under Xvfb with DISPLAY set), or set QT_QPA_PLATFORM=offscreen for scripted use")
    if disp.startswith(":"):  # a local X server listens on /tmp/.X11-unix/X<n>
        num = disp[1:].split(".")[0]
        if num.isdigit() and not os.path.exists(f"/tmp/.X11-unix/X{num}"):
            return (f"no X server for DISPLAY={disp} (/tmp/.X11-unix/X{num} does not exist): start one "
                    f"(e.g. Xvfb {disp}) or set QT_QPA_PLATFORM=offscreen for scripted use")
    import ctypes

    missing = []
    for pkg, lib in XCB_LIBS.items():
        try:
            ctypes.CDLL(lib)
        except OSError:
            missing.append(pkg)
    if missing:
        return (f"Qt's X11 (xcb) platform needs the Debian packages {' '.join(missing)}: run `bash scripts/setup.sh` "
                f"(or apt-get install them), or set QT_QPA_PLATFORM=offscreen for scripted use")
    return None


def main(project_dir, poses=None, query=None) -> int:
    why = display_problem()
    if why:
        from gtkit.errors import GtkitError

        raise GtkitError(why)
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
