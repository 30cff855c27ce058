"""gtkit.queries: which photos are queries, read from [sfm] query_pattern without the SfM package
(the layer below it), and checked as the SfM's settings check it."""
from __future__ import annotations

import numpy as np
import pytest

from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.project import Project
from gtkit.queries import QUERY_PATTERN, query_pattern, query_photos
from gtkit.settings import resolve
from gtkit.sfm.blocks import SfmSettings


def test_query_pattern_is_the_sfm_setting(tmp_path):
    proj = Project.create(tmp_path / "p", GeoFrame("EPSG:32615", (576700.0, 5188160.0, 0.0)))
    for n in ("DJI_1_W.JPG", "DJI_1_Z.JPG", "notes.txt"):
        f = proj.paths.query_images / "seq1" / n
        f.parent.mkdir(parents=True, exist_ok=True)
        write_jpeg_with_meta(f, np.zeros((8, 8, 3), np.uint8)) if n.endswith("JPG") else f.write_text("x")
    assert query_pattern(proj) == QUERY_PATTERN == SfmSettings().query_pattern
    assert query_photos(proj) == ["queries/seq1/DJI_1_W.JPG"]
    proj.config["sfm"] = {"query_pattern": "*", "mapper": "incremental"}   # the rest of [sfm] is the SfM's
    assert query_pattern(proj) == resolve(SfmSettings(), "sfm", proj).query_pattern == "*"
    assert query_photos(proj) == ["queries/seq1/DJI_1_W.JPG", "queries/seq1/DJI_1_Z.JPG"]
    proj.config["sfm"] = {"query_pattern": 5}
    with pytest.raises(GtkitError, match="sfm.query_pattern") as e:
        query_pattern(proj)
    assert "project.toml" in str(e.value)
