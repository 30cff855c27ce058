"""Tiled OBJ models (ContextCapture layout): written from a mesh, read lazily, rendered from tiles
exactly as the single mesh renders; SRS handling and its errors."""
import re
import shutil

import numpy as np
import pytest
from test_import_support import FRAME_CRS, FRAME_ORIGIN, oblique_poses, small_site

from gtkit.camera import Camera
from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame
from gtkit.io.mesh import load_model, write_obj, write_offset_sidecar
from gtkit.io.srs import SrsToWorld
from gtkit.io.tiled import read_tiled, write_metadata, write_tiled
from gtkit.render.renderer import Renderer
from gtkit.render.tiles import TileStreamer, near_far

FRAME = GeoFrame(FRAME_CRS, FRAME_ORIGIN)


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    """The site as one OBJ + offset sidecar (the way a sample site stores its reference model),
    loaded into the world frame."""
    d = tmp_path_factory.mktemp("single")
    mesh = small_site().translated(np.zeros(3))
    obj = write_obj(d / "reference.obj", mesh, texture_format="png")
    write_offset_sidecar(obj, FRAME_CRS, FRAME_ORIGIN)
    return load_model(obj, FRAME)


@pytest.fixture(scope="module", params=["crop", "share"])
def tiled(request, single, tmp_path_factory):
    d = tmp_path_factory.mktemp(f"tiled_{request.param}")
    write_tiled(single, d / "model", FRAME_CRS, FRAME_ORIGIN, tile_size=50.0, texture=request.param)
    return request.param, read_tiled(d / "model", FRAME)


def _compare(a, b):
    va, vb = np.isfinite(a.depth), np.isfinite(b.depth)
    assert va.mean() > 0.5
    assert np.array_equal(va, vb)
    assert np.array_equal(a.depth[va], b.depth[vb])           # depth bit-identical
    return np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max(-1)


def test_tiled_renders_identical_to_single_mesh(single, tiled):
    mode, model = tiled
    assert len(model) == 16 and model.to_world.is_translation
    np.testing.assert_array_equal(model.bounds(), single.bounds())
    cam = Camera.pinhole(320, 240, 260.0, cx=161.0, cy=119.5)
    streamer = TileStreamer(model)
    ref = Renderer()
    ref.add_mesh(single, origin=streamer.origin)
    for pose in oblique_poses(4):
        n, f = near_far(single.bounds(), pose)
        a = ref.render(cam, pose, near=n, far=f)
        b = streamer.render(cam, pose)
        assert 0 < streamer.stats.tiles_drawn <= 16
        diff = _compare(a, b)
        if mode == "share":
            assert diff.max() == 0                                 # RGB bit-identical
        else:  # cropped textures sample other mip/anisotropic footprints near some texels
            assert (diff == 0).mean() > 0.99 and (diff > 3).mean() < 0.005, ((diff > 0).mean(), diff.max())
    ref.release()
    # DSM-like top-down render: heights bit-identical, colours as above
    ref_ortho = Renderer()
    ref_ortho.add_mesh(single, origin=streamer.origin)
    a = ref_ortho.render_ortho(-100, -100, 100, 100, 0.5)
    b = streamer.render_ortho(-100, -100, 100, 100, 0.5)
    diff = _compare(a, b)
    assert diff.max() == 0 if mode == "share" else (diff == 0).mean() > 0.98
    part = streamer.render_ortho(-20, -20, 20, 20, 0.5)         # a window touches only its tiles
    assert streamer.stats.tiles_drawn == 4
    np.testing.assert_allclose(part.depth, a.depth[160:240, 160:240], atol=1e-4)  # other ortho matrix
    ref_ortho.release()
    streamer.release()


def test_lazy_index_and_frustum(single, tmp_path):
    out = write_tiled(single, tmp_path / "m", FRAME_CRS, FRAME_ORIGIN, tile_size=50.0)
    (out / "tiles_index.json").unlink()                          # force the header scan
    m = read_tiled(out / "metadata.xml", FRAME, write_index=True)
    assert (out / "tiles_index.json").is_file()
    m2 = read_tiled(out, FRAME)
    for n in m.names:
        np.testing.assert_array_equal(m.tiles[n].bounds, m2.tiles[n].bounds)
    assert set(m.names) == {f"Tile_{i:+04d}_{j:+04d}" for i in range(-2, 2) for j in range(-2, 2)}
    # a narrow nadir view over one tile's centre sees few tiles
    from gtkit.pose import Pose

    s = TileStreamer(m)
    cam = Camera.from_hfov(200, 150, 20.0)
    names = s.visible_tiles(cam, Pose.from_dji(0, -90, 0, [-75.0, -75.0, 60.0]))
    assert "Tile_-002_-002" in names and len(names) <= 2


def test_enu_srs_tiles_land_in_project_frame(single, tmp_path):
    """A model in ENU:lat,lon lands where the same points reprojected by hand land."""
    lon, lat = FRAME.local_to_wgs84(np.zeros(3))[:2]
    srs = f"ENU:{lat:.9f},{lon:.9f}"
    tr = SrsToWorld(srs, FRAME)
    assert not tr.is_translation
    np.testing.assert_allclose(tr.points(np.zeros(3)), [0, 0, 0], atol=1e-3)  # 1e-9 deg in the spec
    # at 100 m east of the tangent point the ENU axes and the UTM grid differ by meridian convergence
    p = tr.points(np.array([[100.0, 0, 0], [0, 100.0, 0], [0, 0, 50.0]]))
    assert np.all(np.abs(np.linalg.norm(p, axis=1) - [100, 100, 50]) < 0.1)
    R = tr.rotation_at(np.zeros(3))
    assert abs(np.linalg.det(R) - 1) < 1e-9 and np.degrees(np.arccos(R[0, 0])) < 3.0
    out = write_tiled(single, tmp_path / "enu", FRAME_CRS, FRAME_ORIGIN, tile_size=100.0)
    write_metadata(out / "metadata.xml", srs, (0, 0, 0))        # reinterpret stored coords as ENU
    m = read_tiled(out, FRAME)
    t = m.load_all()
    v = np.concatenate([q.vertices for q in t.parts])
    assert np.abs(v).max() < 150 and m.bounds()[0][0] <= v[:, 0].min()


@pytest.mark.parametrize("bad", ["EPSG:999999", "not a crs at all", ""])
def test_unknown_srs_is_a_clear_error(single, tmp_path, bad):
    out = write_tiled(single, tmp_path / "m", FRAME_CRS, FRAME_ORIGIN, tile_size=100.0)
    write_metadata(out / "metadata.xml", bad, (0, 0, 0))
    with pytest.raises(GtkitError, match="metadata.xml") as e:
        read_tiled(out, FRAME)
    assert "\n" not in str(e.value)


def test_inconsistent_tile_srs_is_an_error(single, tmp_path):
    out = write_tiled(single, tmp_path / "m", FRAME_CRS, FRAME_ORIGIN, tile_size=100.0)
    tile = sorted((out / "Data").iterdir())[1]
    write_metadata(tile / "metadata.xml", "EPSG:32651", FRAME_ORIGIN)
    with pytest.raises(GtkitError, match=re.escape(tile.name) + ".*inconsistent"):
        read_tiled(out, FRAME)
    write_metadata(tile / "metadata.xml", FRAME_CRS, (1.0, 2.0, 3.0))
    with pytest.raises(GtkitError, match="inconsistent"):
        read_tiled(out, FRAME)
    shutil.rmtree(out / "Data")
    with pytest.raises(GtkitError, match="no Tile_"):
        read_tiled(out, FRAME)


def test_windowed_dsm_from_tiles_is_identical_and_bounded(single, tiled):
    """A DSM-sized top-down render, window by window with a tiny memory budget: each window loads
    only the tiles under it, and the raster equals the single mesh's (same windows) bit for bit."""
    mode, model = tiled
    streamer = TileStreamer(model, budget_mb=1.0)
    ref = Renderer()
    ref.add_mesh(single, origin=streamer.origin)
    a = ref.render_ortho(-100, -100, 100, 100, 0.25, tile=200)
    peak = []
    orig_evict = streamer._evict

    def spy(keep):
        orig_evict(keep)
        peak.append(len(streamer.resident))

    streamer._evict = spy
    b = streamer.render_ortho(-100, -100, 100, 100, 0.25, tile=200)
    # 16 windows of 50 m on the 50 m tile grid; tile boxes overhang their cell, so up to 3 x 3 per window
    assert streamer.stats.tiles_drawn == 16 and max(peak) <= 9
    np.testing.assert_array_equal(a.depth, b.depth)
    if mode == "share":
        np.testing.assert_array_equal(a.rgb, b.rgb)
    ref.release()
    streamer.release()


def test_heights_only_dsm_from_tiles_one_tile_at_a_time_is_identical(single, tiled):
    """The DSM of a tiled model draws its tiles one at a time from their triangles (textures not
    read, gtkit.export.surface.render_heights_in_pieces): the heights equal the single textured
    mesh's top-down render bit for bit, and the tiles are read without their texture images."""
    from gtkit.export.grid import Grid
    from gtkit.export.surface import TiledSurface, rasterize_surface

    mode, model = tiled
    ref = Renderer()
    ref.add_mesh(single, origin=model.bounds().mean(0))
    a = ref.render_ortho(-100, -100, 100, 100, 0.25, with_rgb=False)
    ref.release()
    b = rasterize_surface(TiledSurface(model), Grid(-100.0, 100.0, 0.25, 800, 800)).height
    assert np.isfinite(a.depth).mean() > 0.5
    np.testing.assert_array_equal(a.depth, b)
    tile = model.load_tile(model.names[0], textures=False)
    assert tile.parts and all(p.texture is None and p.uv is None for p in tile.parts)
