"""One writer per project (issue 49): the project lock, measured on real processes and real files.

A writer is held by a separate process (``python -c`` taking the lock, as ``gtkit run`` does) so
the fast tests need no whole run; the two real ``gtkit run`` started together are behind
``GTKIT_SLOW=1`` (the tiny sample's main job, about 2 min on 2 cores)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gtkit.geo import GeoFrame
from gtkit.project import Project
from gtkit.project_lock import (HOLDER_FILE, LOCK_FILE, ProjectLocked, acquire, held_here, holder, project_lock,
                                read_holder, release)

ROOT = Path(__file__).resolve().parents[1]
SLOW = os.environ.get("GTKIT_SLOW") == "1"
GTKIT = [sys.executable, "-m", "gtkit.cli"]
HOLD = """
import sys, time
from gtkit.project_lock import acquire
acquire(sys.argv[1], sys.argv[2])
print("held", flush=True)
time.sleep(float(sys.argv[3]))
"""


@pytest.fixture
def site(tmp_path) -> Path:
    """A project with nothing to compute: every stage of `gtkit run` is skipped or quick."""
    return Project.create(tmp_path / "site", GeoFrame("EPSG:32650", (241873.0, 3379486.0, 0.0)), "lock-test").paths.root


def _holder(root: Path, command: str, seconds: float = 60.0) -> subprocess.Popen:
    """A process holding the project's lock (as `command`) until killed; returns once it holds it."""
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(root), command, str(seconds)], cwd=str(ROOT),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "held", p.stderr.read()
    return p


def _run(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=str(ROOT), capture_output=True, text=True, timeout=timeout)


def _refused_one_line(r: subprocess.CompletedProcess, pid: int, command: str) -> str:
    """The second writer's answer: exit 2, one line on stderr naming the holder, no traceback."""
    err = r.stderr.strip()
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert len(err.splitlines()) == 1 and "Traceback" not in r.stderr + r.stdout, r.stderr
    assert f"pid {pid}" in err and f"`{command}`" in err and "since" in err and "UTC" in err, err
    return err


def test_second_writer_refused_in_one_line_naming_the_holder(site):
    cmd = f"gtkit run {site}"
    h = _holder(site, cmd)
    try:
        rec = json.loads((site / "work" / HOLDER_FILE).read_text())
        assert rec["pid"] == h.pid and rec["command"] == cmd and rec["host"] and rec["since"] > time.time() - 60
        t0 = time.time()
        r = _run(GTKIT + ["run", str(site)])
        err = _refused_one_line(r, h.pid, cmd)
        assert err.startswith(f"gtkit: error: {site}: another writer holds this project") and f"kill {h.pid}" in err
        assert time.time() - t0 < 30          # at once: no waiting for the holder
        for stage in (["register", str(site)], ["export", "coords", str(site)], ["sfm", str(site), "--block", "reference"],
                      ["gcp", "predict", str(site)]):
            _refused_one_line(_run(GTKIT + stage), h.pid, cmd)
        _refused_one_line(_run([sys.executable, "-m", "pipelines.full", str(site)]), h.pid, cmd)
        # the installed `gtkit` (gtkit.supervisor: the command in a child process) answers the same
        _refused_one_line(_run([sys.executable, "-m", "gtkit.supervisor", "run", str(site)]), h.pid, cmd)
        # read-only commands still answer beside a writer
        r = _run(GTKIT + ["info", str(site)])
        assert r.returncode == 0 and "lock-test" in r.stdout and f"writer    `{cmd}` (pid {h.pid}" in r.stdout, r.stderr
        assert not (site / "reports" / "run.json").exists()     # the refused run wrote nothing
    finally:
        h.kill()
        h.wait()


def test_lock_of_a_killed_process_is_taken_over_with_one_line(site):
    h = _holder(site, f"gtkit run {site}")
    os.kill(h.pid, signal.SIGKILL)
    h.wait()
    assert read_holder(site).pid == h.pid          # its record is left behind: nothing released it
    assert holder(site) is None                    # but nobody holds the project
    r = _run(GTKIT + ["run", str(site), "--from", "export_coords"])
    assert r.returncode == 0, r.stderr
    notes = [ln for ln in r.stderr.splitlines() if "took over the lock" in ln]
    assert len(notes) == 1 and f"pid {h.pid}" in notes[0] and "no longer running" in notes[0], r.stderr
    assert "Traceback" not in r.stderr
    assert not (site / "work" / HOLDER_FILE).exists() and (site / "work" / LOCK_FILE).is_file()   # released
    # and a clean release leaves nothing to take over
    r = _run(GTKIT + ["run", str(site), "--from", "export_coords"])
    assert r.returncode == 0 and "took over" not in r.stderr, r.stderr
    assert "writer    none" in _run(GTKIT + ["info", str(site)]).stdout


def test_a_killed_holders_pid_reused_by_another_process_is_not_a_holder(site, tmp_path):
    """The annotator's banner and ``gtkit info`` ask :func:`holder`: a killed writer's record names a
    pid that the system may hand to an unrelated process; the kernel's lock table decides then."""
    from gtkit.project_lock import flock_held, lock_paths

    lock = lock_paths(site)[0]
    h = _holder(site, f"gtkit run {site}")
    assert holder(site).pid == h.pid and flock_held(lock) is True
    os.kill(h.pid, signal.SIGKILL)
    h.wait()
    assert flock_held(lock) is False
    other = subprocess.Popen(["sleep", "60"])           # stands for the process that got the pid
    try:
        rec = site / "work" / HOLDER_FILE
        d = json.loads(rec.read_text())
        rec.write_text(json.dumps({**d, "pid": other.pid}))
        assert read_holder(site).alive() is True        # the recorded pid lives ...
        assert holder(site) is None                     # ... but holds nothing: not a writer
        from gui.write_guard import WriteGuard

        assert WriteGuard(site).blocked() is None       # the annotator edits and saves
        # a record of a file system without flock: the pid alone decides, as before
        rec.write_text(json.dumps({**d, "pid": other.pid, "flock": False}))
        assert holder(site).pid == other.pid
    finally:
        other.kill()
        other.wait()
    table = tmp_path / "locks"                          # the table's rows as Linux writes them
    st = os.stat(lock)
    dev = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    table.write_text(f"1: POSIX  ADVISORY  WRITE 7 {dev} 0 EOF\n2: -> FLOCK  ADVISORY  WRITE 8 {dev} 0 EOF\n")
    assert flock_held(lock, str(table)) is False        # a POSIX lock and a waiter are not our holder
    table.write_text(f"3: FLOCK  ADVISORY  WRITE 9 {dev} 0 EOF\n")
    assert flock_held(lock, str(table)) is True
    assert flock_held(lock, str(tmp_path / "none")) is None


def test_reentrant_in_one_process_and_released_after(site):
    """A stage run inside `gtkit run` (the main job inside its own lock, gtkit run's loop inside the
    CLI's) takes the lock again without waiting on itself; the last release frees the project."""
    from gtkit import run_site

    with project_lock(site, "outer"):
        assert held_here(site)
        s = run_site.run(site, run_site.RunOptions(start="export_coords"))   # takes it again, inside
        assert s["stages"]["export_coords"]["status"] == "skipped"
        assert held_here(site) and read_holder(site).command == "outer"
    assert not held_here(site) and read_holder(site) is None
    # a forked child (a worker) does not own its parent's lock, and does not keep it after the parent's release
    assert acquire(site, "parent") is True
    pid = os.fork()
    if pid == 0:   # the child: neither holds nor may release the parent's lock; it outlives the release
        ok = not held_here(site) and release(site) is None
        time.sleep(8)
        os._exit(0 if ok else 1)
    r = _run(GTKIT + ["register", str(site)])
    assert r.returncode == 2 and f"pid {os.getpid()}" in r.stderr     # the parent still holds it
    release(site)
    assert holder(site) is None
    r = _run(GTKIT + ["run", str(site), "--from", "export_coords"])    # while the child still lives
    assert r.returncode == 0 and "took over" not in r.stderr, r.stderr
    assert os.waitpid(pid, 0)[1] == 0


def test_library_run_refused_beside_a_writer(site):
    h = _holder(site, "python -m pipelines.full site")
    try:
        from gtkit import run_site

        with pytest.raises(ProjectLocked) as e:
            run_site.run(site)
        assert e.value.holder.pid == h.pid and "python -m pipelines.full site" in str(e.value)
    finally:
        h.kill()
        h.wait()


def test_annotator_beside_a_run_says_so_and_writes_nothing(qtbot, tmp_path):
    """The annotator opened while another process writes the project shows a read-only banner and
    saves nothing (tie points, targets, GCP clicks, verdicts); once the writer ends it saves again,
    each save holding the project's lock."""
    from PySide6.QtWidgets import QApplication

    from gui.demo import make_demo_project
    from gui.main_window import MainWindow

    root = make_demo_project(tmp_path / "site", n_query=2).paths.root
    tp_file = root / "tiepoints.json"
    before = tp_file.read_bytes() if tp_file.exists() else None
    h = _holder(root, f"gtkit run {root}")
    try:
        w = MainWindow(root)
        qtbot.addWidget(w)
        w.show()
        QApplication.processEvents()
        assert w.banner.isVisible() and f"pid {h.pid}" in w.banner.text() and "read-only" in w.banner.text()
        assert "read-only" in w.windowTitle()
        page = w.tiepoints
        assert page.place(page.query, 100.0, 100.0) is None           # refused, said in the status bar
        assert w.store.n_writes == 0 and (tp_file.read_bytes() if tp_file.exists() else None) == before
        assert "read-only" in w.statusBar().currentMessage()
        w.review.image = w.review.image or "queries/seq1/0000_W.jpg"
        w.review.set_verdict("accept")
        assert not (root / "review.json").exists()
    finally:
        h.kill()
        h.wait()
    w.guard._checked = -1e9
    assert w.check_writer() is None and not w.banner.isVisible()
    tp = page.place(page.query, 100.0, 100.0)
    assert tp is not None and w.store.n_writes == 1 and tp in tp_file.read_text()
    assert holder(root) is None and read_holder(root) is None     # the save held the lock and gave it back
    w.close()


@pytest.mark.skipif(not SLOW, reason="GTKIT_SLOW=1: two whole `gtkit run` on the tiny sample (~2 min)")
def test_two_runs_started_together_one_completes_other_refuses(tiny_sample, tmp_path):
    root = tmp_path / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    runs = [subprocess.Popen([sys.executable, "-m", "gtkit.supervisor", "run", str(root)], cwd=str(ROOT), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for _ in range(2)]
    # a stage command beside the run: refused at once
    deadline = time.time() + 60
    while read_holder(root) is None and time.time() < deadline:
        time.sleep(0.1)
    winner_pid = read_holder(root).pid
    side = _run(GTKIT + ["register", str(root)])
    _refused_one_line(side, winner_pid, f"gtkit run {root}")
    out = [(p, *p.communicate(timeout=900)) for p in runs]
    refused = [(p, o, e) for p, o, e in out if "another writer holds this project" in e]
    done = [(p, o, e) for p, o, e in out if "another writer holds this project" not in e]
    assert len(refused) == 1 and len(done) == 1, [(p.returncode, e[-2000:]) for p, o, e in out]
    p, o, e = refused[0]
    assert p.returncode == 2 and len(e.strip().splitlines()) == 1 and "Traceback" not in o + e and f"pid {winner_pid}" in e
    p, o, e = done[0]
    assert p.returncode in (0, 1) and "Traceback" not in o + e, e[-3000:]   # the holder was its child (supervisor)
    s = json.loads((root / "reports" / "run.json").read_text())
    assert s["pseudo_gt"]["n_registered"] == s["pseudo_gt"]["n_images"] > 0
    assert read_holder(root) is None


def test_a_save_racing_a_writer_keeps_the_edit_and_raises_nothing(site):
    """The lock taken by another process between the page's look and the save (the race the
    banner cannot close): the store writes nothing and raises nothing into the Qt slot; the edit
    stays in memory and the next save after the writer ends writes it."""
    from gtkit.io.tiepoints import Observation, TiePoint, read_tiepoints
    from gui.store import TiePointStore
    from gui.write_guard import WriteGuard

    guard = WriteGuard(site, ttl_s=1e9)
    guard._checked = time.monotonic()           # the page looked a moment ago: nobody writing
    store = TiePointStore(site / "tiepoints.json", guard=guard)
    h = _holder(site, f"gtkit run {site}")
    try:
        store.insert(TiePoint("t1", [Observation("reference/a.jpg", 10.0, 20.0)]))
        assert store.n_writes == 0 and not (site / "tiepoints.json").exists()
        assert f"pid {h.pid}" in guard.refused and len(store) == 1
    finally:
        h.kill()
        h.wait()
    store.insert(TiePoint("t2", [Observation("reference/b.jpg", 30.0, 40.0)]))
    assert store.n_writes == 1 and guard.refused is None
    assert [t.id for t in read_tiepoints(site / "tiepoints.json")] == ["t1", "t2"]
