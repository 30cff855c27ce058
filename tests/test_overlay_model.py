"""The overlay scene and the orthophoto read an OBJ with gtkit.io.obj_geometry: one material (one
decoded texture) uploaded at a time, so a large textured model loads in bounded memory. On the tiny
sample the overlays, their alignment figures and the orthophoto are those of the model loaded by
trimesh (gtkit.io.mesh.load_model), pixel for pixel."""
from __future__ import annotations

import numpy as np

from gtkit.io.mesh import load_model
from gtkit.project import Project
from gtkit.render import overlay as ov
from gtkit.render.renderer import Renderer


def test_overlays_from_the_streamed_obj_equal_the_trimesh_ones(tiny_sample):
    root = tiny_sample[0]
    proj = Project.load(root)
    scene = ov.OverlayScene(proj, root / "truth" / "poses.txt")        # the numpy reader
    assert scene.model_path.suffix == ".obj"
    by_trimesh = Renderer(load_model(scene.model_path, proj.frame))
    streamed = scene.renderer
    assert streamed.n_triangles == by_trimesh.n_triangles
    names = scene.images()
    picks = [n for n in names if n.endswith("_W.jpg")][:3] + [next(n for n in names if n.startswith("reference/"))]
    for name in picks:
        photo, rgb, valid, s = scene.render(name, 1024)
        scene.renderer = by_trimesh
        _, rgb0, valid0, _ = scene.render(name, 1024)
        scene.renderer = streamed
        # measured: identical on the tiny sample (4 views) and on small seed 3's built model (120 parts)
        np.testing.assert_array_equal(valid, valid0)
        np.testing.assert_array_equal(rgb, rgb0)
        np.testing.assert_array_equal(ov.compose("blend", photo, rgb, valid), ov.compose("blend", photo, rgb0, valid0))
        assert ov.alignment(photo, rgb, valid, scale=s) == ov.alignment(photo, rgb0, valid0, scale=s)


def test_orthophoto_from_the_streamed_obj_equals_the_trimesh_one(tiny_sample):
    from gtkit.export.dsm import plan_grid
    from gtkit.export.sources import load_surface
    from gtkit.export.surface import MeshSurface, ObjTexturedSurface, rasterize_surface

    root = tiny_sample[0]
    proj = Project.load(root)
    obj = root / "model" / "reference.obj"
    src, frame = load_surface(obj, proj.frame)                            # textures: the orthophoto's source
    assert isinstance(src, ObjTexturedSurface)
    ref = MeshSurface(load_model(obj, proj.frame))
    np.testing.assert_array_equal(src.bounds(), ref.bounds())
    assert src.detail() == ref.detail()
    grid = plan_grid(ref, frame, None, default_factor=1.0).grid
    a, b = rasterize_surface(src, grid, with_rgb=True), rasterize_surface(ref, grid, with_rgb=True)
    np.testing.assert_array_equal(a.height, b.height)
    np.testing.assert_array_equal(a.rgb, b.rgb)


def test_overlays_from_a_tiled_model_stream_its_tiles_and_match_the_obj(tiny_sample, tmp_path):
    """A tiled model (a folder) is overlaid by streaming: each photo uploads only the tiles in its
    frustum, under the memory budget. The tiny sample's model cut into 60 m tiles gives the OBJ's
    overlays: the same pixels covered, colours within a few grey levels (the tiles' textures are crops
    saved again; measured: 0.6-1.8 % of pixels more than 8 levels apart) and the same alignment figures."""
    from gtkit.io.tiled import tile_model_file
    from gtkit.render.tiles import TileStreamer

    root = tiny_sample[0]
    proj = Project.load(root)
    tiles = tile_model_file(root / "model" / "reference.obj", tmp_path / "tiles", proj.frame, tile_size=60.0)
    obj_scene = ov.OverlayScene(proj, root / "truth" / "poses.txt")
    tiled_scene = ov.OverlayScene(proj, root / "truth" / "poses.txt", model_path=tiles, tile_budget_mb=96)
    assert isinstance(tiled_scene.renderer, TileStreamer) and len(tiled_scene.renderer.model) > 4
    names = tiled_scene.images()
    picks = [n for n in names if n.endswith("_W.jpg")][:3] + [next(n for n in names if n.startswith("reference/"))]
    for name in picks:
        photo, rgb, valid, s = tiled_scene.render(name, 1024)
        st = tiled_scene.renderer.stats
        assert 0 < st.tiles_drawn < len(tiled_scene.renderer.model) and st.resident_mb <= 96
        _, rgb0, valid0, _ = obj_scene.render(name, 1024)
        same = valid == valid0
        diff = np.abs(rgb.astype(int) - rgb0.astype(int)).max(-1)[valid & valid0]
        print(f"{name}: {st.tiles_drawn} of {len(tiled_scene.renderer.model)} tiles, coverage differs on "
              f"{1 - same.mean():.5f} of pixels, rgb differs > 8 on {np.mean(diff > 8):.4f}")
        assert same.mean() > 0.999 and np.median(diff) <= 2 and np.mean(diff > 8) < 0.03
        a, a0 = ov.alignment(photo, rgb, valid, scale=s), ov.alignment(photo, rgb0, valid0, scale=s)
        assert abs(a.misalignment_px - a0.misalignment_px) < 0.05
