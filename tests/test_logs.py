"""Quiet by default: COLMAP's glog lines, C libraries' output, worker chatter and log records below
WARNING (issue 58) go to the running stage's work/<stage>/log.txt; warnings, progress bars and prints
stay on the terminal; -v leaves everything on the terminal. Run in a child process: pytest replaces
the test's stdio."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import logging, os, sys
import pycolmap
from gtkit.logs import quiet_terminal
from gtkit.project import start_stage_clock
from gtkit.sfm import quiet_colmap

logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
log = logging.getLogger("gtkit.demo")
verbose = sys.argv[2] == "-v"
with quiet_terminal(verbose) as cap:
    os.write(2, b"before any stage: on the terminal\n")
    log.info("demo: an INFO record before any stage")
    start_stage_clock(os.path.join(sys.argv[1], "work", "demo"))
    quiet_colmap()
    pycolmap.logging.info("COLMAP says hello")
    pycolmap.logging.warning("COLMAP warns")
    os.write(1, b"[Open3D INFO] a C library prints\n")
    log.info("demo: step finished")
    log.warning("demo: act on this")
    log.debug("demo: a detail")
    print("summary line")
print("after: log", cap.log_path)
"""


def _run(tmp_path: Path, flag: str) -> tuple[str, Path]:
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), flag], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout + r.stderr, tmp_path / "work" / "demo" / "log.txt"


def test_colmap_and_c_library_output_go_to_the_stage_log_not_the_terminal(tmp_path):
    terminal, log = _run(tmp_path, "-")
    assert "summary line" in terminal and "WARNING gtkit.demo: demo: act on this" in terminal
    assert "demo: step finished" not in terminal     # an INFO record: the stage's log only
    assert "before any stage: on the terminal" in terminal and "an INFO record before any stage" not in terminal
    assert "COLMAP says hello" not in terminal and "COLMAP warns" not in terminal and "Open3D" not in terminal
    assert f"after: log {log}" in terminal
    text = log.read_text()
    assert "COLMAP says hello" in text and "COLMAP warns" in text and "[Open3D INFO] a C library prints" in text
    assert "demo: step finished" in text and "demo: act on this" in text  # the stage log has gtkit's lines too
    assert text.index("an INFO record before any stage") < text.index("COLMAP says hello")  # held until it opened


def test_verbose_keeps_everything_on_the_terminal(tmp_path):
    terminal, log = _run(tmp_path, "-v")
    assert "COLMAP warns" in terminal and "[Open3D INFO] a C library prints" in terminal
    assert "INFO gtkit.demo: demo: step finished" in terminal and not log.exists()
