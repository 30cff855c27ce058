"""The GT and localization reports show the 3D scene snapshots that ``gtkit view`` wrote."""
from pathlib import Path

from PIL import Image

from gtkit.sfm.report import scene_links


def test_reports_link_the_scene_snapshots(tmp_path: Path):
    assert scene_links(tmp_path) == []
    for n in ("scene_oblique.png", "scene_top.png"):
        Image.new("RGB", (4, 4)).save(tmp_path / n)
    lines = scene_links(tmp_path)
    assert "![scene_oblique.png](scene_oblique.png)" in lines and "![scene_top.png](scene_top.png)" in lines
