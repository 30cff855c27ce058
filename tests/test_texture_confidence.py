"""The model build's texture test (issue 57): depth on ground without texture is given up, and the DSM's
gap fill then fills it (marked) closer to the truth than the false surface SGBM laid there.

On the ``plain-grass`` variant of the tiny sample (a 37.5 m square of grass without detail; the reference
photos rendered again): the real SGBM depth maps of the photos that see the square (at their true poses,
so that no SfM is needed), with and without the test; their points gridded into a DSM (highest point a
0.5 m cell), filled by :func:`gtkit.export.gapfill.fill_gaps`, and compared with the true surface
(``truth/world.ply`` drawn on the same grid). The full chain (SfM, model, ``gtkit export dsm``) on the
tiny and small presets is ``benchmarks/bench_dsm_coverage.py`` (figures in docs/benchmarks.md).
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from gtkit.model.settings import ModelSettings
from gtkit.project import Project

from conftest import true_reference_views


@pytest.fixture(scope="module")
def plain(tiny_sample, tmp_path_factory):
    """The plain-grass variant, its views at the true poses, the square, the true surface renderer."""
    from gtkit.render.renderer import Renderer
    from gtkit.synth.truth import read_world_ply
    from gtkit.synth.variants import apply_variant

    root = tmp_path_factory.mktemp("plain") / "site"
    shutil.copytree(tiny_sample[0], root, ignore=shutil.ignore_patterns("work", "exports", "reports", "queries"))
    apply_variant(root, "plain-grass")
    info = json.loads((root / "truth" / "plain_area.json").read_text())
    square = (*info["square_centre_xy"], info["half_side_m"])
    views = true_reference_views(root)
    world = read_world_ply(root / "truth" / "world.ply")
    return root, views, square, world, Renderer(world)


def _in_square(xy, square, inset=2.0):
    cx, cy, half = square
    return (np.abs(xy[:, 0] - cx) < half - inset) & (np.abs(xy[:, 1] - cy) < half - inset)


def test_plain_square_is_given_up_and_filled_closer_to_the_truth(plain, tmp_path):
    from gtkit.export.gapfill import Cameras, fill_gaps
    from gtkit.export.grid import Grid
    from gtkit.export.surface import MeshSurface
    from gtkit.model import depth as D
    from gtkit.model.build import _depth_map, _grey_pictures
    from gtkit.model.fusion import lift
    from gtkit.model.texture import _gtkit_camera
    from gtkit.model.views import choose_neighbours

    root, views, square, world, render = plain
    proj = Project.load(root)
    s = ModelSettings()
    off = ModelSettings(texture_min_contrast=0.0)
    nb, _ = choose_neighbours(views, s)
    # the photos whose view centre falls near the square (nadir and oblique)
    near = []
    for n, v in views.items():
        c, ax = v.center, v.axis
        hit = c[:2] + ax[:2] * (c[2] - 0.0) / max(-ax[2], 1e-3)        # the view axis meets the ground (z ~ 0)
        if n in nb and np.all(np.abs(hit - np.asarray(square[:2])) < square[2] + 25.0):
            near.append(n)
    assert len(near) >= 6, near
    img = _grey_pictures(proj, views)
    folder = tmp_path / "depth"
    folder.mkdir()
    sq_had = sq_gone = out_had = out_gone = 0
    pts_off, pts_on, errs_kept = [], [], []
    for n in near:
        assert _depth_map(n, nb[n], views, img, off, folder) is None
        d_off = D.read_depth(D.depth_file(folder, n))
        d_on, had, gone = D.texture_test(d_off, img(n), s)
        assert had == int(np.isfinite(d_off).sum()) and gone == had - int(np.isfinite(d_on).sum())
        v = views[n]
        gt = render.render(_gtkit_camera(v), v.pose, with_rgb=False).depth
        xt, rc = lift(v, np.where(np.isfinite(gt), gt, np.nan).astype(np.float32), 1)
        ins = np.zeros(gt.shape, bool)
        ins[rc[:, 0], rc[:, 1]] = _in_square(xt[:, :2], square) & (xt[:, 2] < np.median(xt[:, 2]) + 1.5)
        f_off, f_on = np.isfinite(d_off), np.isfinite(d_on)
        sq_had, sq_gone = sq_had + int((f_off & ins).sum()), sq_gone + int((f_off & ins & ~f_on).sum())
        out_had, out_gone = out_had + int((f_off & ~ins).sum()), out_gone + int((f_off & ~ins & ~f_on).sum())
        ok = f_on & np.isfinite(gt) & ~ins
        errs_kept.append(np.abs(d_on - gt)[ok] / gt[ok])
        pts_off.append(lift(v, d_off, 2)[0])
        pts_on.append(lift(v, d_on, 2)[0])
    # the one written by the build with the test on is the one computed here
    n = near[0]
    _depth_map(n, nb[n], views, img, s, tmp_path)
    assert np.array_equal(np.isfinite(D.read_depth(D.depth_file(tmp_path, n))),
                          np.isfinite(D.texture_test(D.read_depth(D.depth_file(folder, n)), img(n), s)[0]))
    assert D.read_depth_counts(D.depth_file(tmp_path, n))[1] > 0
    given_up_sq, given_up_out = sq_gone / sq_had, out_gone / out_had
    print(f"{len(near)} photos: given up in the plain square {100 * given_up_sq:.1f} % of its ground pixels with a depth, "
          f"elsewhere {100 * given_up_out:.1f} %; kept depth vs truth outside the square: median "
          f"{100 * np.median(np.concatenate(errs_kept)):.3f} %")
    # measured (seed 0, 6 photos): 99.7 % in the square, 8.6 % elsewhere (the margin around the square, the pond)
    assert given_up_sq > 0.95 and given_up_out < 0.15

    # the points gridded (highest point a cell), the gaps filled, the square's ground against the truth
    cx, cy, half = square
    grid = Grid.covering(cx - half - 15, cy - half - 15, cx + half + 15, cy + half + 15, 0.5)
    true = MeshSurface(world).rasterize(grid, False).height.astype(float)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    sq = _in_square(np.stack([X.ravel(), Y.ravel()], 1), square).reshape(grid.shape)
    ground = sq & (true < np.median(true[sq]) + 1.5)           # not the trees in the square
    cams = Cameras({n: views[n].pose for n in views}, {n: views[n].camera for n in views})
    res = {}
    for key, pts in (("off", pts_off), ("on", pts_on)):
        p = np.concatenate(pts)
        col = np.floor((p[:, 0] - grid.xmin) / grid.res).astype(int)
        row = np.floor((grid.ymax - p[:, 1]) / grid.res).astype(int)
        k = (col >= 0) & (col < grid.width) & (row >= 0) & (row < grid.height)
        h = np.full(grid.shape, -np.inf)
        np.maximum.at(h, (row[k], col[k]), p[k, 2])
        h = np.where(np.isfinite(h), h, np.nan).astype(np.float32)
        gf = fill_gaps(h, grid, cams)
        e = np.abs(gf.height - true)[ground]
        res[key] = (float(np.median(e)), float(np.percentile(e, 90)), float(gf.filled[ground].mean()),
                    float(np.isfinite(gf.height[ground]).mean()))
        print(f"texture test {key}: square ground cells vs truth median {res[key][0]:.2f} m / p90 {res[key][1]:.2f} m, "
              f"{100 * res[key][2]:.0f} % filled, {100 * res[key][3]:.0f} % valid")
    # measured (seed 0): with the test 0.57 / 1.03 m (100 % filled); without it 2.17 / 5.97 m (the false surface,
    # 33 % filled)
    assert res["on"][2] > 0.8 and res["on"][3] > 0.99          # given up, then filled (and marked)
    assert res["on"][0] < 0.8 and res["on"][1] < 1.5
    assert res["on"][1] < 0.5 * res["off"][1]


@pytest.mark.skipif(__import__("os").environ.get("GTKIT_SLOW") != "1", reason="GTKIT_SLOW=1: SfM, model and DSM of the variant")
def test_plain_grass_variant_end_to_end(plain, tmp_path):
    """The whole chain on the plain-grass variant (SfM of the reference block, the model with the texture
    test, ``export dsm``): the square given up and filled, marked in band 2, the record saying the share
    filled; the square's DSM against the truth."""
    import rasterio

    from gtkit.export import dsm
    from gtkit.export.dsm import Dsm
    from gtkit.export.surface import MeshSurface
    from gtkit.model.build import run as build
    from gtkit.project import read_stage_record
    from gtkit.sfm.blocks import SfmSettings, run_reference

    src, _views, square, world, _r = plain
    root = tmp_path / "site"
    shutil.copytree(src, root)
    s = SfmSettings()
    s.features.max_num_features = 1000
    run_reference(root, s)
    summary = build(root, ModelSettings(max_image_size=480, max_triangles=150_000), show=False)
    proj = Project.load(root)
    out = dsm.run(proj, dsm.DsmSettings(resolution=0.5))
    rec = read_stage_record(proj.paths.stage("export_dsm")).summary
    with rasterio.open(out) as f:                       # band 2 read back: the filled cells
        h, filled = f.read(1, masked=True), f.read(2)
    d = Dsm.for_project(root)
    grid = d.grid
    true = MeshSurface(world).rasterize(grid, False).height.astype(float)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    sq = _in_square(np.stack([X.ravel(), Y.ravel()], 1), square).reshape(grid.shape)
    e = np.abs(d.heights - true)[sq]
    ground = sq & (true < np.median(true[sq]) + 1.5)        # not the trees in the square
    eg = np.abs(d.heights - true)[ground]
    print(f"end to end: {100 * summary['textureless']['share']:.1f} % of the depth given up; square {np.median(e):.2f} / "
          f"{np.percentile(e, 90):.2f} m (its ground {np.median(eg):.2f} / {np.percentile(eg, 90):.2f} m), "
          f"{100 * d.filled[sq].mean():.0f} % filled; flown area valid "
          f"{100 * rec['valid_share_flown_before']:.1f} -> {100 * rec['valid_share_flown_after']:.1f} %")
    assert np.array_equal(d.filled, filled == 1) and rec["filled_cells"] == int((filled == 1).sum()) and h.count() > 0
    assert rec["valid_share_flown_after"] >= 0.99 and rec["filled_share"] > 0.02
    # measured (seed 0, 480 px): square 0.66 / 3.96 m (its trees), its ground 0.68 / 1.15 m, 87 % filled, flown
    # area 73.3 -> 100 % valid; the full-size build (bench_dsm_coverage): 0.60 / 1.16 m; without the
    # texture test 0.82 / 5.70 m, 0 % filled
    assert d.filled[sq].mean() > 0.6 and np.median(e) < 0.8 and np.percentile(e, 90) < 5.0
    assert np.median(eg) < 0.8 and np.percentile(eg, 90) < 2.0
