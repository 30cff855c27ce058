"""Stage records carry what the stage cost: wall, CPU (self + children), peak memory, disk."""
import json
import subprocess
import sys
import time

import numpy as np

from gtkit.project import mark_stage_done, stage_done


def _burn(seconds: float) -> None:
    t = time.process_time()
    x = 0
    while time.process_time() - t < seconds:
        x += 1


def test_a_stage_record_carries_its_wall_cpu_peak_memory_and_disk(tmp_path):
    (tmp_path / "project.toml").write_text("[crs]\ncrs = 'EPSG:32650'\n")
    stage = tmp_path / "work" / "demo"
    assert not stage_done(stage, {"a": 1})          # no record: the stage's clock starts here
    big = np.ones(400 * 2**20 // 8)                  # 400 MB resident
    _burn(0.5)
    subprocess.run([sys.executable, "-c", "import time\nt=time.process_time()\nwhile time.process_time()-t<0.4: pass"],
                   check=True)                       # a child's CPU counts too
    time.sleep(0.3)
    stage.mkdir(parents=True)
    (stage / "out.bin").write_bytes(b"\0" * 3 * 2**20)
    del big
    mark_stage_done(stage, {"a": 1}, outputs=[tmp_path / "extra.bin"])
    cost = json.loads((stage / "stage.json").read_text())["summary"]["cost"]
    assert cost["wall_s"] >= 1.2
    assert cost["cpu_s"] >= 0.85 and cost["cpu_children_s"] >= 0.35
    assert cost["peak_rss_gb"] >= 0.39
    assert cost["disk_mb"] >= 3.0 and cost["disk_mb"] < 3.01   # out.bin + stage.json not yet written
    assert stage_done(stage, {"a": 1})


def test_the_peak_of_a_nested_stage_is_its_own_and_the_outer_keeps_the_larger(tmp_path):
    (tmp_path / "project.toml").write_text("[crs]\ncrs = 'EPSG:32650'\n")
    outer, inner = tmp_path / "work" / "outer", tmp_path / "work" / "inner"
    assert not stage_done(outer, {})
    big = np.ones(500 * 2**20 // 8)
    del big
    assert not stage_done(inner, {})                 # resets the process's peak: the outer keeps its 500 MB
    small = np.ones(100 * 2**20 // 8)
    del small
    for d in (inner, outer):
        d.mkdir(parents=True)
        mark_stage_done(d, {})
    c_in = json.loads((inner / "stage.json").read_text())["summary"]["cost"]
    c_out = json.loads((outer / "stage.json").read_text())["summary"]["cost"]
    if c_in["peak_rss_scope"] == "stage":            # Linux: VmHWM can be reset
        assert c_out["peak_rss_gb"] >= 0.49
        assert c_in["peak_rss_gb"] < c_out["peak_rss_gb"] - 0.3


def test_a_step_window_inside_a_stage_does_not_lose_the_stage_peak(tmp_path):
    from gtkit.project import reset_peak_rss

    (tmp_path / "project.toml").write_text("[crs]\ncrs = 'EPSG:32650'\n")
    stage = tmp_path / "work" / "steps"
    assert not stage_done(stage, {})
    big = np.ones(400 * 2**20 // 8)
    del big
    reset_peak_rss()                                  # a step ends (the model build does this per step)
    stage.mkdir(parents=True)
    mark_stage_done(stage, {})
    cost = json.loads((stage / "stage.json").read_text())["summary"]["cost"]
    assert cost["peak_rss_gb"] >= 0.39
