"""``gtkit model build``: the reference model from the photos, measured against the sample's truth.

The end-to-end test runs the real chain on the ``tiny`` sample (45 photos of 640 x 480, the
session's fixture): pycolmap SfM of the reference block (georegistered), SGBM depth maps, fusion,
Poisson, texture, the OBJ in the project, then ``gtkit export dsm`` on it and the DSM against the
true world (``truth/world.ply``). The small-sample figures are in benchmarks/bench_model.py.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gtkit.errors import GtkitError
from gtkit.model.settings import ModelSettings
from gtkit.project import Project

from conftest import true_reference_views

# a lighter build than the default, to fit the test suite's time (measured on the tiny sample)
FAST = ModelSettings(max_image_size=480, neighbours=3, max_triangles=150_000)


@pytest.fixture(scope="module")
def built(tiny_sample, tmp_path_factory):
    from gtkit.model.build import run as build
    from gtkit.sfm.blocks import SfmSettings, run_reference

    src = tiny_sample[0]
    root = tmp_path_factory.mktemp("model") / "site"
    shutil.copytree(src, root, ignore=shutil.ignore_patterns("work", "exports", "reports", "model", "queries"))
    s = SfmSettings()
    s.features.max_num_features = 1000
    run_reference(root, s)
    return root, build(root, FAST, show=False)


def test_built_model_dsm_against_the_true_world(built):
    import rasterio

    from gtkit.evaluate.model import dsm_vs_truth
    from gtkit.export import dsm

    root, summary = built
    proj = Project.load(root)
    assert proj.config["model"]["source"] == "built" and (root / "model" / "reference.obj").is_file()
    out = dsm.run(proj, dsm.DsmSettings(resolution=0.5))          # the project's model, no --input
    with rasterio.open(out) as src:
        assert src.crs == rasterio.crs.CRS.from_user_input(proj.frame.crs_spec)
    m = dsm_vs_truth(root, out)
    print("tiny built model DSM vs true world:", json.dumps(m))
    assert summary["depth_maps"] >= 40 and summary["unseen_faces"] < 0.01 * summary["triangles"]
    # measured (seed 0, 480 px working size, the default settings otherwise): completeness 0.96 of the
    # grid (the tiny block has 3 x 3 stations), off-edge median 0.063 m / p95 0.39 m, bias +0.02 m
    assert m["completeness"] > 0.85
    assert m["off_edges"]["median"] < 0.10 and m["off_edges"]["p95"] < 0.8
    assert abs(m["bias"]) < 0.05


def test_texture_test_is_in_the_record(built):
    """The model's record says how much depth the texture test gave up (the log line too): on the tiny sample
    its pond and plain roofs, with the margin around them (measured 8.3 % at the default working size)."""
    from gtkit.project import read_stage_record

    root, summary = built
    t = summary["textureless"]
    assert t == read_stage_record(root / "work" / "model").summary["textureless"]
    assert t["pixels_with_depth"] > 100_000 and 0.01 < t["share"] < 0.2
    assert abs(t["given_up"] / t["pixels_with_depth"] - t["share"]) < 1e-4


def test_built_model_texture_matches_a_photo(built):
    """The textured model rendered at a reference photo's SfM pose looks like the photo."""
    from gtkit.io.mesh import load_model
    from gtkit.io.poses import read_intrinsics, read_poses
    from gtkit.io.photo import read_photo
    from gtkit.render.renderer import Renderer

    root, _ = built
    proj = Project.load(root)
    mesh = load_model(root / "model" / "reference.obj", proj.frame)
    assert len(mesh.parts) > 10 and all(p.texture is not None for p in mesh.parts if p.name != "unseen")
    block = root / "work" / "sfm_reference"
    name = "reference/R02_002_N.jpg"
    cam = read_intrinsics(block / "intrinsics.txt")[name]
    pose = read_poses(block / "poses.txt")[name]
    r = Renderer(mesh).render(cam, pose)
    photo = read_photo(root / "images" / name).astype(np.float64)
    ok = r.valid
    assert ok.mean() > 0.9          # measured 0.94
    a, b = r.rgb.astype(np.float64)[ok].mean(1), photo[ok].mean(1)
    corr = np.corrcoef(a, b)[0, 1]
    assert corr > 0.8, corr


def test_built_and_delivered_models_compared(built, tiny_sample, tmp_path):
    """The height difference of the built and the delivered model (a GeoTIFF read back)."""
    import rasterio

    from gtkit.model.compare import run as compare

    root, _ = built
    delivered = tiny_sample[0] / "model" / "reference.obj"
    r = compare(root, root / "model" / "reference.obj", delivered, 1.0, tmp_path / "diff.tif")
    with rasterio.open(tmp_path / "diff.tif") as src:
        d = src.read(1)
        d = d[d != src.nodata]
    assert len(d) == r["cells"] > 1000
    assert abs(np.median(d)) < 0.1 and np.median(np.abs(d)) < 0.2


def test_depth_maps_resume_per_photo(built, tmp_path):
    """A killed run keeps its finished depth maps: only the missing ones are computed again."""
    from gtkit.model import depth as D
    from gtkit.model.build import depth_maps
    from gtkit.model.views import choose_neighbours, load_views

    root, _ = built
    proj = Project.load(root)
    views, _ = load_views(proj, FAST)
    nb, _ = choose_neighbours(views, FAST)
    folder = next((root / "work" / "model" / "depth").iterdir())
    work = tmp_path / "depth"
    shutil.copytree(folder, work)
    names = [n for n in nb if D.depth_file(work, n).is_file()]
    gone = names[3]
    D.depth_file(work, gone).unlink()
    before = {n: D.depth_file(work, n).stat().st_mtime_ns for n in names if n != gone}
    depth_maps(proj, views, {n: nb[n] for n in names}, FAST, work, show=False)
    assert D.depth_file(work, gone).is_file()
    assert all(D.depth_file(work, n).stat().st_mtime_ns == t for n, t in before.items())
    redone, kept = D.read_depth(D.depth_file(work, gone)), D.read_depth(D.depth_file(folder, gone))
    assert np.array_equal(np.isfinite(redone), np.isfinite(kept))


def test_pair_depth_against_rendered_truth(tiny_sample):
    """One rectified SGBM pair at true poses: median depth error within 0.3 % of the true surface's
    (measured 0.07 %; a pair of 60 % overlap fills about a third of the photo)."""
    from gtkit.model import depth as D
    from gtkit.model.texture import _gtkit_camera
    from gtkit.model.views import choose_neighbours, load_image
    from gtkit.render.renderer import Renderer
    from gtkit.synth.truth import read_world_ply

    root = tiny_sample[0]
    views = true_reference_views(root)
    s = ModelSettings()
    nb, _ = choose_neighbours(views, s)
    proj = Project.load(root)
    world = Renderer(read_world_ply(root / "truth" / "world.ply"))
    for a in ("reference/R02_002_N.jpg", "reference/R02_002_L.jpg"):
        v, w = views[a], views[nb[a][0]]
        d = D.pair_depth(v, w, load_image(proj, v), load_image(proj, w), s)
        gt = world.render(_gtkit_camera(v), v.pose, with_rgb=False).depth
        ok = np.isfinite(d) & np.isfinite(gt)
        rel = np.abs(d - gt)[ok] / gt[ok]
        assert ok.mean() > 0.25 and np.median(rel) < 0.003, (a, ok.mean(), np.median(rel))


def test_photo_with_too_few_neighbours_is_skipped_with_its_reason():
    from gtkit.camera import Camera
    from gtkit.model.views import View, choose_neighbours
    from gtkit.pose import Pose

    cam = Camera.pinhole(640, 480, 430.0)
    K = np.array([[430.0, 0, 319.5], [0, 430.0, 239.5], [0, 0, 1]])
    R = np.diag([1.0, -1.0, -1.0])                       # nadir
    views = {}
    for i, (x, y) in enumerate([(0, 0), (30, 0), (60, 0), (0, 30), (30, 30), (60, 30), (900, 900)]):
        views[f"p{i}"] = View(f"p{i}", cam, Pose.from_center(R, [x, y, 100.0]), 1.0, 640, 480, K, 80, 120, 100)
    nb, skipped = choose_neighbours(views, ModelSettings())
    assert "p6" in skipped and "only 0 usable neighbour" in skipped["p6"]
    assert set(nb) == {f"p{i}" for i in range(6)} and all(len(v) >= 2 for v in nb.values())


def test_block_without_georegistration_is_refused(tmp_path):
    from gtkit.geo import GeoFrame
    from gtkit.model.build import run as build

    proj = Project.create(tmp_path / "site", GeoFrame("EPSG:32650", (500000.0, 3300000.0, 0.0)))
    with pytest.raises(GtkitError, match="run `gtkit sfm DIR --block reference` first"):
        build(proj, ModelSettings())
    block = proj.paths.stage("sfm_reference")
    block.mkdir(parents=True)
    (block / "block.json").write_text(json.dumps({"frame": "arbitrary SfM frame (georegistration failed)",
                                                  "georegistration": {"error": "fewer than 3 GPS positions"}}))
    with pytest.raises(GtkitError) as e:
        build(proj, ModelSettings())
    msg = str(e.value)
    assert "not georegistered (fewer than 3 GPS positions)" in msg and "block.json" in msg and "\n" not in msg


def test_built_model_never_replaces_a_delivered_one_unasked(tmp_path):
    """With a delivered model/reference.obj the built model goes to model/built/; --use swaps them."""
    from gtkit.export.sources import reference_model
    from gtkit.geo import GeoFrame
    from gtkit.io.mesh import Mesh, MeshPart, load_model, write_obj, write_offset_sidecar
    from gtkit.model.build import _write_model

    frame = GeoFrame("EPSG:32650", (500000.0, 3300000.0, 10.0))
    proj = Project.create(tmp_path / "site", frame)
    tri = np.array([[0, 1, 2]])
    delivered = Mesh([MeshPart(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), tri, colors=np.zeros((3, 3), np.uint8))])
    built = Mesh([MeshPart(np.array([[0, 0, 5], [1, 0, 5], [0, 1, 5.0]]), tri, colors=np.zeros((3, 3), np.uint8))])
    write_obj(proj.paths.model / "reference.obj", delivered)
    write_offset_sidecar(proj.paths.model / "reference.obj", frame.crs_spec, frame.origin)

    out = _write_model(proj, built, None)
    assert out == proj.paths.model / "built" / "reference.obj"
    assert Project.load(proj.paths.root).config["model"]["source"] == "delivered"
    assert reference_model(proj.paths) == proj.paths.model / "reference.obj"
    assert load_model(reference_model(proj.paths), frame).bounds()[0, 2] == 0.0      # still the delivered one

    out = _write_model(proj, built, True)
    assert out == proj.paths.model / "reference.obj"
    assert Project.load(proj.paths.root).config["model"]["source"] == "built"
    assert load_model(reference_model(proj.paths), frame).bounds()[0, 2] == 5.0      # the built one now
    assert load_model(proj.paths.model / "delivered" / "reference.obj", frame).bounds()[0, 2] == 0.0


def test_tiled_surface_and_tiled_model(built, tmp_path):
    """A site wider than ``tile_m`` is reconstructed tile by tile (memory bounded by a tile) and also
    written as a tiled model (ContextCapture layout, gtkit.io.tiled): the tiled surface meets the same
    accuracy against the true world as the single one, and the tiled model's DSM (read back by
    rasterio) is the single OBJ's DSM."""
    import rasterio
    from dataclasses import replace

    from gtkit.evaluate.model import dsm_vs_truth
    from gtkit.export import dsm
    from gtkit.model.build import run as build

    root0, _ = built
    root = tmp_path / "site"
    shutil.copytree(root0, root, ignore=shutil.ignore_patterns("exports", "reports"))
    summary = build(root, replace(FAST, tile_m=120.0, max_triangles=50_000), force=True, show=False)  # depth maps reused
    assert summary["seconds"]["depth"] < 10 and summary["surface_tiles"] >= 4
    proj = Project.load(root)
    tiles = root / proj.config["model"]["tiled"]
    assert (tiles / "metadata.xml").is_file() and len(list((tiles / "Data").iterdir())) >= 4
    s = dsm.DsmSettings(resolution=0.5)
    single = dsm.run(proj, s, input=root / "model" / "reference.obj", out=tmp_path / "single.tif")
    tiled = dsm.run(proj, s, input=tiles, out=tmp_path / "tiled.tif")
    with rasterio.open(single) as a, rasterio.open(tiled) as b:
        ha, hb = a.read(1), b.read(1)
        assert a.transform == b.transform and a.nodata == b.nodata
    from scipy.ndimage import maximum_filter, minimum_filter

    both = (ha != a.nodata) & (hb != b.nodata)
    d = np.abs(ha - hb)
    # float32 rendering from another origin: heights within 1 cm (measured max 2 mm), except where a cell's
    # centre grazes a roof edge (its 3 x 3 neighbourhood spans > 2 m), which one rendering may read on the
    # roof and the other beside it (measured: 1 cell of 136k, 27.3 vs 22.0 m with neighbours 28.3 / 22.0 m)
    h = np.where(both, ha, np.nan)
    edge = (maximum_filter(np.nan_to_num(h, nan=-1e9), 3) - minimum_filter(np.nan_to_num(h, nan=1e9), 3)) > 2.0
    off = both & (d >= 0.01)
    # coverage: the same cells, except where a cell's centre grazes the model's outer edge (a neighbour
    # with no data in either), which one rendering may cover and the other not (measured: 1 cell of
    # 137,792 in one CI run of stop 40, none in others)
    differ = (ha == a.nodata) != (hb == b.nodata)
    on_edge = maximum_filter((ha == a.nodata) & (hb == b.nodata), 3)
    assert np.all(on_edge[differ]) and differ.sum() <= 1e-4 * both.sum(), (differ.sum(), both.sum())
    assert np.median(d[both]) < 1e-4
    assert np.all(edge[off]) and off.sum() <= 1e-4 * both.sum(), (off.sum(), both.sum())
    # the tiles' textures are packed per tile (write_tiled texture="pack"): database views of the tiled
    # model look like those of the OBJ. Small seed 13 cut into 60 m tiles from its OBJ: mean 0.04 grey
    # levels, 99.7 % of pixels within 2. Here the build writes the OBJ's textures as JPEG and the
    # tiles' losslessly from the same pixels, so the JPEG error is most of it (measured: mean 1.38,
    # 84.6 % within 2, p99 6 grey levels over 34 views)
    from gtkit.localize.database import RenderDbSettings, db_camera
    from gtkit.localize.grid import ground_level, make_views
    from gtkit.render.tiles import open_renderer

    ra = open_renderer(root / "model" / "reference.obj", proj.frame, anisotropy=1.0)
    rb = open_renderer(tiles, proj.frame, 4096, anisotropy=1.0)
    bb = rb.model.bounds()
    ext = (bb[0, 0], bb[0, 1], bb[1, 0], bb[1, 1])
    cam = db_camera(RenderDbSettings())
    diffs = []
    for v in make_views(ext, ground_level(ra, *ext), (100.0,), (60.0,), (0.0, 45.0), 90.0)[::3]:
        a, b = ra.render(cam, v.pose()), rb.render(cam, v.pose())
        m = np.isfinite(a.depth) & np.isfinite(b.depth)
        if m.mean() >= 0.2:
            diffs.append(np.abs(a.rgb.astype(int) - b.rgb.astype(int))[m])
    ra.release(); rb.release()
    d = np.concatenate(diffs)
    print(f"tiled vs OBJ over {len(diffs)} views: mean |d| {d.mean():.2f}, within 2: {(d <= 2).mean():.3f}, "
          f"p99 {np.quantile(d, 0.99):.0f}")
    assert len(diffs) >= 3 and d.mean() < 2.0 and (d <= 2).mean() > 0.75 and np.quantile(d, 0.99) <= 12
    # both DSMs read triangles only (no texture decoded) and draw a piece (a tile) at a time; the OBJ's
    # heights are those of the textured model loaded whole, to float32 rounding (the path before this, which
    # the medium sample's 5.4 M-triangle, 650-texture model outgrew 8 GB with)
    from gtkit.export.sources import load_surface
    from gtkit.export.surface import MeshSurface, rasterize_surface
    from gtkit.io.mesh import load_model

    obj = root / "model" / "reference.obj"
    light, _ = load_surface(obj, proj.frame, textures=False)
    light.piece_triangles = 20_000
    grid = dsm.plan_grid(light, proj.frame, 0.5).grid
    assert light.geometry.n_triangles > 2 * light.piece_triangles
    # the same heights to float32 rounding (one CI run: 1 of 141,752 cells 5.7e-6 m apart, the two paths
    # summing a triangle's plane in another order)
    np.testing.assert_allclose(rasterize_surface(light, grid).height,
                               rasterize_surface(MeshSurface(load_model(obj, proj.frame)), grid).height, rtol=0, atol=1e-4)
    m = dsm_vs_truth(root, single)
    print("tiny built model, surface in", summary["surface_tiles"], "tiles, vs true world:", json.dumps(m))
    assert m["completeness"] > 0.85
    assert m["off_edges"]["median"] < 0.10 and m["off_edges"]["p95"] < 0.8
    assert abs(m["bias"]) < 0.05

    # a build killed while it makes the surface resumes at the next tile: the fused cloud and the
    # finished tiles (one file each) are read back, only the missing tile is made again
    work = root / "work" / "model"
    fused = next((work / "fused").iterdir())
    tiles_done = sorted(next((work / "surface").iterdir()).glob("tile_*.npz"))
    assert len(tiles_done) == summary["surface_tiles"] and len(json.loads((fused / "index.json").read_text())["cells"]) >= 2
    gone = tiles_done[1]
    gone.unlink()
    (work / "stage.json").unlink()                 # the build did not finish
    kept = {p: p.stat().st_mtime_ns for p in tiles_done if p != gone}
    kept[fused / "index.json"] = (fused / "index.json").stat().st_mtime_ns
    again = build(root, replace(FAST, tile_m=120.0, max_triangles=50_000), show=False)
    assert gone.is_file() and all(p.stat().st_mtime_ns == t for p, t in kept.items())
    assert abs(again["triangles"] - summary["triangles"]) <= 0.01 * summary["triangles"]
    m2 = dsm_vs_truth(root, dsm.run(proj, s, input=root / "model" / "reference.obj", out=tmp_path / "again.tif"))
    assert abs(m2["completeness"] - m["completeness"]) < 0.005
    assert abs(m2["off_edges"]["median"] - m["off_edges"]["median"]) < 0.005


def _welded_model(root):
    """The built model as one mesh (vertices welded across its parts)."""
    from gtkit.io.mesh import load_model

    mesh = load_model(root / "model" / "reference.obj", Project.load(root).frame)
    Vs, Fs, nv = [], [], 0
    for p in mesh.parts:
        Vs.append(p.vertices)
        Fs.append(p.faces + nv)
        nv += len(p.vertices)
    V, inv = np.unique(np.round(np.concatenate(Vs), 4), axis=0, return_inverse=True)
    return V, inv.reshape(-1)[np.concatenate(Fs)]


def test_colour_balancing_at_seams(built):
    """Photos with different exposures (a gain of 0.8-1.2 per photo and channel put on the tiny sample's
    photos) leave colour jumps at the texture seams; the solved gains undo the exposures (up to one
    common factor) and the seams' median colour jump falls back to what it is without them."""
    from gtkit.model import texture
    from gtkit.model.views import load_image, load_views

    root, _ = built
    proj = Project.load(root)
    views, _ = load_views(proj, FAST)
    V, F = _welded_model(root)
    names, best = texture.choose_views(V, F, views)
    index = {n: k for k, n in enumerate(names)}
    exposure = np.random.default_rng(7).uniform(0.8, 1.2, (len(names), 3))

    def exposed(v):
        return np.clip(load_image(proj, v, gray=False) * exposure[index[v.name]] + 0.5, 0, 255).astype(np.uint8)

    plain = texture.seam_colours(V, F, views, names, best, lambda v: load_image(proj, v, gray=False))
    sc = texture.seam_colours(V, F, views, names, best, exposed)
    gains = texture.colour_gains(sc, len(names))
    seen = np.unique(sc["a"])
    residual = np.log(gains[seen] * exposure[seen])
    residual -= np.median(residual, axis=0)
    before, after = texture.seam_difference(sc), texture.seam_difference(sc, gains)
    base, base_balanced = texture.seam_difference(plain), texture.seam_difference(plain, texture.colour_gains(plain, len(names)))
    print(f"seam |dRGB| median: one exposure {base:.2f} (balanced {base_balanced:.2f}); exposures 0.8-1.2 "
          f"{before:.2f} -> balanced {after:.2f}; gain error (log) median {np.median(np.abs(residual)):.4f}, "
          f"max {np.abs(residual).max():.4f} over {len(seen)} photos, {len(sc['a'])} seam edges")
    assert len(sc["a"]) > 1000 and len(seen) > 30
    # a photo's gain is solved where it meets another photo at >= 20 usable seam edges (colour_gains'
    # min_edges, counted as it counts them: texture.usable_seam_edges, not dark or clipped);
    # elsewhere it stays 1 by design (a fixture whose SfM left one photo with 17 seam edge ends: 0.22 there;
    # one CI run counted a photo's edges before that filter and called it solved at 0.20)
    n = len(names)
    ok = texture.usable_seam_edges(sc)
    lo, hi = np.minimum(sc["a"][ok], sc["b"][ok]), np.maximum(sc["a"][ok], sc["b"][ok])
    up, cnt = np.unique(lo.astype(np.int64) * n + hi, return_counts=True)
    solved = np.zeros(n, bool)
    solved[up[cnt >= 20] // n] = solved[up[cnt >= 20] % n] = True
    solved = solved[seen]
    assert solved.mean() > 0.9
    # the exposures' log spread is 0.115; measured median 0.006-0.010, max over solved photos 0.05-0.09
    assert np.median(np.abs(residual)) < 0.02 and np.abs(residual[solved]).max() < 0.15
    assert after < 0.7 * before and after < base + 1.0
    assert base_balanced < base + 0.5                                              # one exposure: no harm


def test_depth_maps_on_a_dask_cluster_equal_this_process(built, tmp_path):
    """``gtkit model build --executor dask``: the depth maps of 12 photos (two tasks) computed on a Dask
    LocalCluster of two workers are the fixture's, made in this process, bit for bit."""
    pytest.importorskip("dask.distributed")
    from gtkit.localize.executors import ExecutorSettings
    from gtkit.model import depth as D
    from gtkit.model.build import DEPTH_CHUNK, depth_maps
    from gtkit.model.views import choose_neighbours, load_views

    root, _ = built
    proj = Project.load(root)
    views, _ = load_views(proj, FAST)
    nb, _ = choose_neighbours(views, FAST)
    folder = next((root / "work" / "model" / "depth").iterdir())
    names = [n for n in nb if D.depth_file(folder, n).is_file()][5:5 + DEPTH_CHUNK + 4]
    work = tmp_path / "depth"
    work.mkdir()
    failed = depth_maps(proj, views, {n: nb[n] for n in names}, FAST, work, show=False,
                        executor=ExecutorSettings("dask", 2))
    assert failed == {}
    for n in names:
        a, b = D.read_depth(D.depth_file(work, n)), D.read_depth(D.depth_file(folder, n))
        assert np.array_equal(a, b, equal_nan=True), n


def test_build_killed_during_depth_maps_resumes(built, tmp_path):
    """``gtkit model build`` SIGKILLed while it computes depth maps, then run again: the maps finished
    before the kill are kept (same files, same mtimes), only the others are computed, and the model
    meets the same accuracy against the true world."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from gtkit.evaluate.model import dsm_vs_truth
    from gtkit.export import dsm
    from gtkit.model import depth as D

    root0, summary0 = built
    root = tmp_path / "site"
    skip = {root0 / "model", root0 / "work" / "model", root0 / "exports", root0 / "reports"}
    shutil.copytree(root0, root, ignore=lambda d, names: [n for n in names if Path(d) / n in skip])
    cmd = [sys.executable, "-c", "import sys; from gtkit.cli import main; sys.exit(main())", "model", "build", str(root),
           "--max-image-size", str(FAST.max_image_size), "--max-triangles", str(FAST.max_triangles)]
    def maps():
        return sorted(p for p in (root / "work" / "model" / "depth").glob("*/*.npz") if not p.name.startswith("."))

    # to keep the test short, the first 30 maps are the fixture's (same settings, so the same folder)
    src = next((root0 / "work" / "model" / "depth").iterdir())
    for p in sorted(src.glob("*.npz"))[:30]:
        (root / "work" / "model" / "depth" / src.name).mkdir(parents=True, exist_ok=True)
        shutil.copy2(p, root / "work" / "model" / "depth" / src.name / p.name)
    env = dict(os.environ, GTKIT_PROGRESS="0")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.time()
    while len(maps()) < 34 and proc.poll() is None and time.time() - t0 < 300:
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    kept = {p: p.stat().st_mtime_ns for p in maps()}
    assert 34 <= len(kept) < summary0["depth_maps"], len(kept)       # killed in the middle of the depth step
    assert not (root / "model" / "reference.obj").exists()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "% of the depth given up as textureless" in done.stdout, done.stdout   # the texture test's share, said
    after = maps()
    assert len(after) == summary0["depth_maps"]
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())       # not recomputed
    assert not list((root / "work" / "model" / "depth").glob("*/.*.tmp*"))   # no half-written map left
    assert all(np.isfinite(D.read_depth(p)).mean() > 0.2 for p in after)
    m = dsm_vs_truth(root, dsm.run(Project.load(root), dsm.DsmSettings(resolution=0.5)))
    print(f"killed after {len(kept)} of {len(after)} depth maps; resumed model vs true world:", json.dumps(m))
    assert m["completeness"] > 0.85
    assert m["off_edges"]["median"] < 0.10 and m["off_edges"]["p95"] < 0.8
    assert abs(m["bias"]) < 0.05


def test_fusion_in_cells_equals_one_accumulator(tmp_path):
    """Fusion kept on disk cell by cell (memory: one cell) gives the voxels one accumulator over the
    whole site gives: the same voxels, means within float32 rounding, the same colours; a box read
    back holds exactly the voxels inside it; the LAZ written cell by cell holds them all."""
    import laspy

    from gtkit.model.fusion import CellSpill, VoxelAccumulator, write_laz_cells

    rng = np.random.default_rng(3)
    acc = VoxelAccumulator(0.25, flush_at=50_000)
    spill = CellSpill(tmp_path / "spill", 0.25, 30.0)
    for _ in range(6):                             # six "photos" over a 100 m x 80 m site, some voxels shared
        xyz = rng.uniform([-40, -30, 0], [60, 50, 3], (40_000, 3))
        xyz[:20_000] = np.round(xyz[:20_000] / 0.25) * 0.25 + 0.1     # points falling into the same voxels
        rgb = rng.integers(0, 256, (len(xyz), 3)).astype(np.float64)
        d = rng.normal(size=(len(xyz), 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        acc.add(xyz, rgb, d)
        spill.add(xyz, rgb, d)
    ref_xyz, ref_rgb, ref_dir, ref_n = acc.result()
    cells = spill.reduce(tmp_path / "fused")
    # cells of 30 m (120 voxels) from the origin: x -40..60.1 falls in 5 of them, y -30..50.1 in 3
    assert len(cells.cells) == 15 and not (tmp_path / "spill").exists()
    assert all(np.floor(np.asarray(c["lo"]) / 30).tolist() == np.floor(np.asarray(c["hi"]) / 30).tolist() for c in cells.cells)
    r = cells.read()
    assert len(r) == len(cells) == len(ref_xyz)
    assert np.abs(r["xyz"] - ref_xyz).max() < 1e-4 and np.array_equal(r["n"], ref_n)
    assert np.abs(r["rgb"].astype(int) - ref_rgb).max() <= 1 and np.abs(r["dir"] - ref_dir).max() < 1e-5
    box = np.array([[-5.0, 0.0], [25.0, 20.0]])
    inside = np.all((ref_xyz[:, :2] >= box[0] - 2) & (ref_xyz[:, :2] <= box[1] + 2), axis=1)
    assert len(cells.read(box, 2.0)) == inside.sum()
    origin = np.array([500000.0, 3300000.0, 10.0])
    write_laz_cells(tmp_path / "p.laz", cells, origin, "EPSG:32650", chunk=7_000)
    las = laspy.read(tmp_path / "p.laz")
    assert len(las.x) == len(ref_xyz)
    back = np.sort(np.asarray(las.x) - origin[0])
    assert np.abs(back - np.sort(ref_xyz[:, 0])).max() < 0.001


def test_seam_colours_read_many_points_in_one_photo():
    """Colours are read at any number of points in one photo (a photo textured over a large site meets
    more than OpenCV's 32767 map entries a side): a linear ramp read back bilinearly is exact."""
    from gtkit.camera import Camera
    from gtkit.model.texture import _sample
    from gtkit.model.views import View
    from gtkit.pose import Pose

    cam = Camera.pinhole(640, 480, 430.0)
    K = np.array([[430.0, 0, 319.5], [0, 430.0, 239.5], [0, 0, 1]])
    v = View("p", cam, Pose.from_center(np.diag([1.0, -1.0, -1.0]), [0, 0, 100.0]), 1.0, 640, 480, K, 80, 120, 100)
    jj, ii = np.meshgrid(np.arange(640), np.arange(480))
    ramp = np.stack([jj * 0.25, ii * 0.5, np.full_like(jj, 7)], -1).astype(np.uint8)   # exact in uint8
    px = np.random.default_rng(1).uniform([0, 0], [639, 479], (50_000, 2))
    X = np.stack([(px[:, 0] - 319.5) / 430 * 100, -(px[:, 1] - 239.5) / 430 * 100, np.zeros(len(px))], 1)
    c = _sample({"p": v}, ["p"], lambda _: ramp, np.zeros(len(X), np.int64), X)
    want = np.stack([np.floor(px[:, 0]) * 0.25, np.floor(px[:, 1]) * 0.5], 1)
    assert np.isfinite(c).all() and np.abs(c[:, 2] - 7).max() < 1e-3
    assert np.abs(c[:, :2] - want).max() < 1.01          # uint8 ramps step by 1 every 4 / 2 px


def test_sgbm_disparities_are_unbiased_over_sub_pixel_shifts():
    """OpenCV's SGBM rounds its sub-pixel disparities up on one side (integer division): a texture
    shifted by every 1/32 px fraction came out +0.025 px too far on average, which put surfaces
    centimetres high; and its estimates stick to whole pixels. gtkit's disparities are corrected for
    the first and match the upside-down pass half a pixel apart against the second."""
    import cv2

    from gtkit.model.depth import sgbm_disparities

    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur((rng.random((300, 480)) * 255).astype(np.float32), (0, 0), 1.5)
    u8 = lambda a: np.clip(a, 0, 255).astype(np.uint8)  # noqa: E731

    def shifted(s):
        return u8(cv2.warpAffine(base, np.float32([[1, 0, -s], [0, 1, 0]]), (480, 300), flags=cv2.INTER_CUBIC))

    raw, corrected = [], []
    for s in np.arange(10.0, 11.0, 1 / 32):
        plain, _, _ = sgbm_disparities(u8(base), shifted(s), shifted(s), 32, ModelSettings(sgbm_disparity_bias_px=0.0))
        disp, d1, d2 = sgbm_disparities(u8(base), shifted(s), shifted(s - 0.5), 32, ModelSettings())
        ok = (d1 > 0.5) & (d2 > 0.5) & (np.abs(d1 - d2) <= 1)
        ok[:, :60] = False
        raw.append(float(np.mean((plain - 0.25)[ok])) - s)     # same shift both passes (d2 + 0.5 inside)
        corrected.append(float(np.mean(disp[ok])) - s)
    raw, corrected = np.array(raw), np.array(corrected)
    print(f"mean disparity error over 32 sub-pixel shifts: raw {raw.mean():+.4f} px (swing {np.ptp(raw):.3f}), "
          f"now {corrected.mean():+.4f} px (swing {np.ptp(corrected):.3f})")
    assert raw.mean() > 0.015 and abs(corrected.mean()) < 0.006
    assert np.ptp(corrected) < 0.5 * np.ptp(raw)


def test_patchmatch_workspace_is_the_views_as_a_colmap_model(built, tmp_path):
    """The GPU path's COLMAP workspace, written on the CPU: pycolmap reads back each view's pinhole K,
    pose and working image exactly, the sparse tracks give each photo a depth range around its scene
    (COLMAP's: 1st-99th percentile of its points' depths, x0.75 / x1.25), the stereo config lists each
    photo's neighbours. (PatchMatch itself needs CUDA: the next test.)"""
    import cv2
    import pycolmap

    from gtkit.model.patchmatch import workspace_name, write_workspace
    from gtkit.model.views import block_dir, choose_neighbours, load_image, load_views

    root, _ = built
    proj = Project.load(root)
    views, _ = load_views(proj, FAST)
    nb, _ = choose_neighbours(views, FAST)
    ws = tmp_path / "ws"
    write_workspace(proj, views, nb, block_dir(proj), ws)
    rec = pycolmap.Reconstruction(str(ws / "sparse"))
    assert len(rec.images) == len(views)
    by_name = {im.name: im for im in rec.images.values()}
    for n, v in views.items():
        im = by_name[workspace_name(n)]
        cam = rec.cameras[im.camera_id]
        assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (v.width, v.height)
        assert np.allclose(cam.params, [v.K[0, 0], v.K[1, 1], v.K[0, 2], v.K[1, 2]], rtol=0, atol=1e-9)
        assert np.allclose(im.cam_from_world().matrix(), v.pose.matrix[:3], atol=1e-9)
        z = np.sort([v.pose.transform(rec.points3D[p.point3D_id].xyz[None])[0, 2]
                     for p in im.points2D if p.has_point3D()])
        lo, hi = 0.75 * z[int(0.01 * len(z))], 1.25 * z[int(0.99 * len(z))]
        assert len(z) >= 20 and lo < v.median_depth < hi and lo < v.far and hi > v.near, (n, lo, hi, v.near, v.far)
    for n in list(views)[:3]:
        png = cv2.imread(str(ws / "images" / workspace_name(n)), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(png, load_image(proj, views[n], gray=True))
    lines = (ws / "stereo" / "patch-match.cfg").read_text().split("\n")
    cfg = {lines[i]: [s.strip() for s in lines[i + 1].split(",")] for i in range(0, len(lines) - 1, 2)}
    assert cfg == {workspace_name(n): [workspace_name(m) for m in v] for n, v in nb.items()}


def test_colmap_depth_map_files_round_trip(tmp_path):
    """COLMAP's dense array files (``W&H&C&`` then float32 planes, rows of W) as gtkit reads and writes them."""
    from gtkit.io.colmap_dense import read_colmap_array, write_colmap_array

    d = np.arange(15, dtype=np.float32).reshape(3, 5)          # 3 rows of 5
    write_colmap_array(tmp_path / "d.bin", d)
    raw = (tmp_path / "d.bin").read_bytes()
    assert raw.startswith(b"5&3&1&") and np.frombuffer(raw[6:], "<f4")[:6].tolist() == [0, 1, 2, 3, 4, 5]
    assert np.array_equal(read_colmap_array(tmp_path / "d.bin"), d)
    nrm = np.random.default_rng(0).random((4, 6, 3)).astype(np.float32)
    write_colmap_array(tmp_path / "n.bin", nrm)
    assert np.array_equal(read_colmap_array(tmp_path / "n.bin"), nrm)


def test_depth_method_is_chosen_by_cuda():
    from gtkit.model.patchmatch import cuda_available, resolve_method

    assert resolve_method("sgbm") == "sgbm"
    assert resolve_method("auto") == ("patchmatch" if cuda_available() else "sgbm")
    if not cuda_available():
        with pytest.raises(GtkitError, match="pycolmap-cuda12"):
            resolve_method("patchmatch")
    with pytest.raises(GtkitError, match="not one of"):
        resolve_method("opencl")


@pytest.mark.skipif("not __import__('gtkit.model.patchmatch', fromlist=['x']).cuda_available()",
                    reason="COLMAP's PatchMatch needs pycolmap's CUDA build and an NVIDIA GPU")
def test_patchmatch_depth_maps_agree_with_the_cpu_path(built, tmp_path):
    """With a GPU: the PatchMatch depth maps of the tiny sample against the CPU path's SGBM maps on the
    same views (same pixels): median relative difference under 1 %, and at least as many pixels."""
    from gtkit.model import depth as D
    from gtkit.model.patchmatch import depth_maps
    from gtkit.model.views import block_dir, choose_neighbours, load_views

    root, _ = built
    proj = Project.load(root)
    views, _ = load_views(proj, FAST)
    nb, _ = choose_neighbours(views, FAST)
    sgbm = next(f for f in (root / "work" / "model" / "depth").iterdir() if f.is_dir())
    folder = tmp_path / "depth"
    folder.mkdir()
    failed = depth_maps(proj, views, nb, FAST, folder, block_dir(proj), show=False)
    assert len(failed) <= 0.1 * len(nb)
    rel, share = [], []
    for n in nb:
        if n in failed or not D.depth_file(sgbm, n).is_file():
            continue
        a, b = D.read_depth(D.depth_file(folder, n)), D.read_depth(D.depth_file(sgbm, n))
        ok = np.isfinite(a) & np.isfinite(b)
        rel.append(np.median(np.abs(a[ok] - b[ok]) / b[ok]))
        share.append(np.isfinite(a).mean() / max(np.isfinite(b).mean(), 1e-9))
    print(f"PatchMatch vs SGBM over {len(rel)} photos: median |rel| {np.median(rel):.4f}, valid share ratio {np.median(share):.2f}")
    assert np.median(rel) < 0.01 and np.median(share) > 0.9


def test_model_build_settings_come_from_the_command_line_then_project_toml(tmp_path, capsys):
    """`gtkit model build` resolves its settings like every stage: flag > project.toml [model_build] >
    default. A depth method the machine cannot run is refused before any work, naming the fix."""
    from gtkit.cli import main
    from gtkit.geo import GeoFrame
    from gtkit.model.patchmatch import cuda_available

    proj = Project.create(tmp_path / "site", GeoFrame("EPSG:32650", (500000.0, 3300000.0, 0.0)))
    proj.config["model_build"] = {"depth_method": "patchmatch", "neighbours": 4}
    proj.save()
    root = str(proj.paths.root)
    if not cuda_available():
        assert main(["model", "build", root]) == 2
        err = capsys.readouterr().err
        assert "'patchmatch' needs pycolmap's CUDA build" in err and err.count("\n") == 1
    assert main(["model", "build", root, "--depth-method", "sgbm"]) == 2      # the flag wins: on to the block
    assert "run `gtkit sfm DIR --block reference` first" in capsys.readouterr().err
    proj.config["model_build"] = {"neighbors": 4}
    proj.save()
    assert main(["model", "build", root]) == 2
    assert "unknown setting model_build.neighbors" in capsys.readouterr().err
