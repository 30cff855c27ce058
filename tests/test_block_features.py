"""Which size a block finds its features at (gtkit/sfm/blocks.py ``block_feature_settings``, issue 55):
a small reference block of photos larger than the default feature size, and its query sequences with
it, find them at 3200 px / 8192 keypoints (on the real-truth sets' 3072-px photos, 1600 px left the
blocks 2-3x worse than plain COLMAP's); a large block, small photos, or a size the user set keep theirs."""
from __future__ import annotations

import dataclasses

import numpy as np
from PIL import Image

from gtkit.geo import GeoFrame
from gtkit.project import Project
from gtkit.sfm.blocks import FINE_FEATURES, SfmSettings, block_feature_settings


def _project(tmp_path, n_ref: int, side: int, extra: dict | None = None) -> tuple[Project, list[str], list[str]]:
    p = Project.create(tmp_path / "site", GeoFrame("EPSG:32632", (500000.0, 5000000.0, 0.0)), extra=extra)
    ref = [f"reference/{k:03d}.jpg" for k in range(n_ref)]
    seq = [f"queries/seq/{k:03d}.jpg" for k in range(3)]
    img = Image.fromarray(np.zeros((side * 2 // 3, side, 3), np.uint8))
    for n in ref + seq:
        (p.paths.images / n).parent.mkdir(parents=True, exist_ok=True)
        img.save(p.paths.images / n, quality=50)
    return Project.load(p.paths.root), ref, seq


def test_a_small_block_of_large_photos_and_its_queries_find_finer_features(tmp_path):
    p, ref, seq = _project(tmp_path, 7, 3072)
    s = SfmSettings()
    fine = block_feature_settings(p, ref, s)
    assert (fine.features.max_image_size, fine.features.max_num_features) == FINE_FEATURES
    q = block_feature_settings(p, seq, s, ref)
    assert q.features == fine.features and s.features.max_image_size == 1600      # the default untouched
    # a size the user set (project.toml, or a flag with another value) is kept
    mine = dataclasses.replace(s, features=dataclasses.replace(s.features, max_image_size=2400))
    assert block_feature_settings(p, ref, mine).features.max_image_size == 2400


def test_a_large_block_small_photos_or_a_set_size_keep_the_default(tmp_path):
    p, ref, seq = _project(tmp_path / "a", 41, 3072)
    assert block_feature_settings(p, ref, SfmSettings()).features.max_image_size == 1600
    assert block_feature_settings(p, seq, SfmSettings(), ref).features.max_image_size == 1600
    p, ref, _ = _project(tmp_path / "b", 7, 1600)
    assert block_feature_settings(p, ref, SfmSettings()).features.max_image_size == 1600
    p, ref, _ = _project(tmp_path / "c", 7, 3072, extra={"sfm": {"features": {"max_num_features": 3000}}})
    assert block_feature_settings(p, ref, SfmSettings()).features.max_image_size == 1600
