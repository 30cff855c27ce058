"""DSM gaps filled inside the photos' footprint, the filled cells marked, the orthophoto's seams
blended and measured, tracks on filled cells flagged (issue 57)."""
import shutil

import numpy as np
import pytest

from gtkit.camera import Camera
from gtkit.export.gapfill import Cameras, fill_gaps, flown_area, laplace_fill
from gtkit.export.grid import Grid
from gtkit.pose import Pose
from test_track_stage import ground, project  # noqa: F401,F811  (the tracking stage's synthetic project fixture)

NADIR = np.diag([1.0, -1.0, -1.0])     # camera x east, y south, z down


def _surface(X, Y):
    return 10 + 0.05 * X + 0.5 * np.sin(X / 25.0) * np.cos(Y / 30.0)


def _four_cameras(height=70.0):
    cam = Camera.pinhole(400, 400, 400.0)   # 53 deg: about 60 m of ground from 70 m above it
    centres = [(30, 35), (30, 65), (45, 35), (45, 65)]
    return Cameras({f"c{i}": Pose.from_center(NADIR, [x, y, height]) for i, (x, y) in enumerate(centres)},
                   {f"c{i}": cam for i in range(4)})


def test_fill_inside_the_footprint_only_and_from_valid_cells():
    grid = Grid(0.0, 100.0, 1.0, 100, 100)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    truth = _surface(X, Y)
    h = truth.copy()
    gap = (X > 40) & (X < 90) & (Y > 30) & (Y < 70)      # runs out of the photos' footprint (east)
    hole = (X - 20) ** 2 + (Y - 50) ** 2 < 8 ** 2           # enclosed by measured cells
    h[gap | hole] = np.nan
    gf = fill_gaps(h.astype(np.float32), grid, _four_cameras())
    fp = gf.footprint
    assert fp[50, 20] and not fp[50, 95] and 0.3 < fp.mean() < 0.7
    # filled: exactly the empty cells inside the footprint; outside it they stay empty
    assert np.array_equal(gf.filled, (gap | hole) & fp)
    assert np.isnan(gf.height[gap & ~fp]).all() and (gap & ~fp).sum() > 500
    assert np.array_equal(gf.height[~(gap | hole)], h[~(gap | hole)].astype(np.float32))
    # error against the true surface: the enclosed hole (Dirichlet all round) within 2 cm; the gap
    # whose eastern side is the footprint's edge (no flux there: the border's 5 % slope goes on) within 5 cm
    e_hole = np.abs(gf.height - truth)[hole]
    e_gap = np.abs(gf.height - truth)[gap & fp]
    print(f"fill error: enclosed hole median {np.median(e_hole):.3f} m, gap at the footprint edge median "
          f"{np.median(e_gap):.3f} m p90 {np.percentile(e_gap, 90):.3f} m")
    assert np.median(e_hole) < 0.02 and e_hole.max() < 0.06
    assert np.median(e_gap) < 0.05 and e_gap.max() < 0.3
    s = gf.summary
    assert s["valid_share_flown_before"] < 0.9 and s["valid_share_flown_after"] == 1.0
    assert s["filled_cells"] == int(gf.filled.sum())
    # settings: off fills nothing; a distance limit leaves the far cells empty
    off = fill_gaps(h.astype(np.float32), grid, _four_cameras(), enabled=False)
    assert not off.filled.any() and off.summary["valid_share_flown_after"] == off.summary["valid_share_flown_before"]
    near = fill_gaps(h.astype(np.float32), grid, _four_cameras(), max_distance_m=5.0)
    assert near.filled.sum() < gf.filled.sum() and np.isnan(near.height[50, 60])
    # no cameras: no footprint, nothing filled
    assert not fill_gaps(h.astype(np.float32), grid, None).filled.any()


def test_fill_of_a_plain_field_with_trees_stays_on_the_ground():
    """A plain field given up by the model build, lined and dotted with trees (crowns 5 m high, each with
    the skirt a Poisson surface drapes from the crown down to where the points end): the fill takes the
    field's ground from its outer border, not the crowns (on its border: a plane clipped harder above
    than below; inside it: islands standing above that plane are left out)."""
    grid = Grid(0.0, 100.0, 0.5, 200, 200)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    truth = _surface(X, Y)
    field = (np.abs(X - 37.5) < 18) & (np.abs(Y - 50) < 18)
    rng = np.random.default_rng(3)
    trees = np.r_[rng.uniform([24, 36], [51, 64], (8, 2)),                      # in the field
                  np.c_[np.linspace(21, 54, 9), np.full(9, 32.0)]]               # along its southern edge
    crown = np.zeros(X.shape, bool)
    top = truth.copy()
    for tx, ty in trees:
        r = np.hypot(X - tx, Y - ty)
        skirt = np.clip(5.0 - 3.0 * (r - 2.5), 0.0, 5.0)            # 5 m over the crown, down to 0.5 m at 4 m
        top = np.maximum(top, truth + np.where(r < 4.0, skirt, 0.0))
        crown |= r < 4.0
    h = np.where(field & ~crown, np.nan, top)
    gf = fill_gaps(h.astype(np.float32), grid, _four_cameras())
    ground = field & ~crown
    e = np.abs(gf.height - truth)[ground]
    print(f"field with {len(trees)} trees: fill error vs ground median {np.median(e):.3f} m, p90 {np.percentile(e, 90):.3f} m")
    # measured: median 0.009 m, p90 0.030 m; before (a plane fitted to the whole border, symmetric clipping,
    # crowns and skirts kept): 0.66 / 1.07 m; without the skirts left out: 0.08 / 0.94 m
    assert gf.filled[ground].all() and np.median(e) < 0.05 and np.percentile(e, 90) < 0.15


def test_flown_area_is_the_hull_of_the_camera_centres():
    grid = Grid(0.0, 100.0, 1.0, 100, 100)
    m = flown_area(grid, np.array([[30, 35], [30, 65], [45, 35], [45, 65]]))
    assert m.sum() == 15 * 30 and m[50, 35] and not m[50, 50]      # 15 m x 30 m of 1 m cells
    assert not flown_area(grid, np.array([[0, 0], [10, 10], [20, 20.0]])).any()   # collinear: no area


def test_large_gap_through_the_coarse_grid_matches_the_direct_solve(monkeypatch):
    import gtkit.export.gapfill as gapfill

    grid_n = 120
    yy, xx = np.mgrid[0:grid_n, 0:grid_n].astype(float)
    truth = 5 + 0.03 * xx - 0.02 * yy
    h = truth.copy()
    h[20:100, 30:110] = np.nan
    unknown = np.isnan(h)
    direct = laplace_fill(h, unknown)
    monkeypatch.setattr(gapfill, "DIRECT_MAX", 1000)       # force the coarse-to-fine path
    coarse = laplace_fill(h, unknown)
    assert np.isfinite(coarse[unknown]).all()
    assert np.abs(coarse - direct)[unknown].max() < 0.05
    assert np.abs(direct - truth)[unknown].max() < 1e-6   # a plane enclosed by its border: exact


def _cut_hole(obj, centre_xy, radius):
    """Drop the OBJ's faces with a vertex within ``radius`` of ``centre_xy`` (OBJ coordinates)."""
    lines = obj.read_text().splitlines()
    v = np.array([[float(t) for t in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    inside = np.hypot(v[:, 0] - centre_xy[0], v[:, 1] - centre_xy[1]) < radius
    out = []
    for ln in lines:
        if ln.startswith("f "):
            idx = [int(t.split("/")[0]) - 1 for t in ln.split()[1:]]
            if inside[idx].any():
                continue
        out.append(ln)
    obj.write_text("\n".join(out) + "\n")


@pytest.fixture(scope="module")
def holed_site(tiny_sample, tmp_path_factory):
    """The tiny sample with a 12 m hole cut into its model (rural west, few buildings) and its true
    reference poses as the reference block (as a perfect SfM would give)."""
    from gtkit.io.mesh import read_offset_sidecar
    from gtkit.project import Paths, Project

    root = tmp_path_factory.mktemp("gapfill") / "site"
    shutil.copytree(tiny_sample[0], root)
    P = Paths(root)
    frame = Project.load(root).frame
    for f in ("poses.txt", "intrinsics.txt"):
        lines = (P.truth / f).read_text().splitlines()
        keep = [ln for ln in lines if ln.startswith("#") or ln.startswith("reference/")]
        (P.stage("sfm_reference")).mkdir(parents=True, exist_ok=True)
        (P.stage("sfm_reference") / f).write_text("\n".join(keep) + "\n")
    obj = P.model / "reference.obj"
    side = read_offset_sidecar(obj)
    off = np.asarray(side[1], float) - np.asarray(frame.origin, float)     # OBJ + off = world
    centre = (-20.0, 15.0)
    _cut_hole(obj, (centre[0] - off[0], centre[1] - off[1]), 12.0)
    return Project.load(root), centre


def test_dsm_of_a_holed_model_fills_marks_and_states_the_share(holed_site, caplog):
    import logging

    import rasterio

    from gtkit.export import dsm
    from gtkit.export.surface import MeshSurface
    from gtkit.project import read_stage_record
    from gtkit.synth.truth import read_world_ply

    proj, centre = holed_site
    with caplog.at_level(logging.INFO, logger="gtkit.export.dsm"):
        out = dsm.run(proj, dsm.DsmSettings())
    with rasterio.open(out) as src:
        assert src.count == 2 and src.descriptions == ("height", "filled")
        height, filled = src.read(1), src.read(2)
        nodata = src.nodata
    d = dsm.Dsm.open(out, proj.frame)
    assert np.array_equal(d.filled, filled == 1) and d.filled.any()
    xc, yc = d.grid.centres()
    X, Y = np.meshgrid(xc, yc)
    in_hole = np.hypot(X - centre[0], Y - centre[1]) < 9.0      # well inside the 12 m cut
    assert d.filled[in_hole].all() and (height[in_hole] != nodata).all()
    rec = read_stage_record(proj.paths.stage("export_dsm")).summary
    assert rec["valid_share_flown_before"] < 0.97 and rec["valid_share_flown_after"] >= 0.99
    assert rec["filled_cells"] == int(d.filled.sum()) and 0 < rec["filled_share"] < 0.2
    assert f"{rec['filled_cells']} cells filled" in caplog.text and "after filling" in caplog.text
    # the fill against the true surface (truth read by the test only)
    true = MeshSurface(read_world_ply(proj.paths.truth / "world.ply")).rasterize(d.grid, False).height
    err = np.abs(d.heights - true)[in_hole & np.isfinite(true)]
    print(f"fill error in a 12 m hole vs truth: median {np.median(err):.3f} m, p90 {np.percentile(err, 90):.3f} m")
    assert np.median(err) < 0.5


def test_dsm_reader_says_which_cells_are_filled(tmp_path):
    from gtkit.export.geotiff import write_geotiff
    from gtkit.geo import GeoFrame
    from gtkit.project import Project
    from gtkit.track.raycast import cast_rays
    from gtkit.export.dsm import Dsm

    frame = GeoFrame("EPSG:32650", (500000.0, 4000000.0, 50.0))
    proj = Project.create(tmp_path / "site", frame)
    grid = Grid(-100.0, 100.0, 1.0, 200, 200)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    z = 0.02 * X + frame.origin[2]
    filled = (X > 0).astype(np.float32)                    # the eastern half interpolated
    write_geotiff(proj.paths.dsm, np.stack([z, filled], -1).astype(np.float32), grid, frame.crs, frame.origin,
                  nodata=-9999.0, band_names=["height", "filled"])
    d = Dsm.open(proj.paths.dsm, frame)
    assert d.filled_at(10.0, 0.0) and not d.filled_at(-10.0, 0.0) and not d.filled_at(500.0, 0.0)
    assert list(d.filled_at(np.array([-5.0, 5.0]), np.array([0.0, 0.0]))) == [False, True]
    hits = cast_rays(d, np.array([[-20.0, 0, 100], [20.0, 0, 100]]), np.array([[0, 0, -1.0], [0, 0, -1.0]]))
    assert list(d.filled_at(hits.points[:, 0], hits.points[:, 1])) == [False, True]


def test_track_stage_writes_the_flag_and_counts_it(project):  # noqa: F811
    """The tracking stage's own project (tests/test_track_stage.py) with the DSM's band 'filled'
    set over part of the site: the targets there carry on_filled_dsm = 1, the others 0."""
    import csv

    from gtkit.evaluate.tracking import evaluate_tracking
    from gtkit.export.geotiff import write_geotiff
    from gtkit.track.tracker import TrackSettings, run

    proj, truth = project
    P, frame = proj.paths, proj.frame
    grid = Grid(-200.0, 200.0, 1.0, 400, 400)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    filled = (X < 0).astype(np.float32)                    # the west interpolated: targets at x = -40, -10, -60
    write_geotiff(P.dsm, np.stack([ground(X, Y) + frame.origin[2], filled], -1).astype(np.float32), grid,
                  frame.crs, frame.origin, nodata=-9999.0, band_names=["height", "filled"])
    summary = run(proj, TrackSettings())
    rows = {r["image"]: r for r in csv.DictReader(ln for ln in open(P.tracks) if not ln.startswith("#"))}
    for name, Xt in truth.items():
        assert rows[name]["on_filled_dsm"] == ("1" if Xt[0] < 0 else "0"), name
    assert rows["queries/seq1/0005_Z.jpg"]["on_filled_dsm"] == ""     # not placed: no flag
    assert summary["n_on_filled_dsm"] == 3
    rep = evaluate_tracking(P, plot=False)
    assert rep["n_on_filled_dsm"] == 3 and rep["on_filled_dsm"]["median_err_h_m"] < 0.05


def test_orthophoto_from_photos_blends_seams_between_unevenly_exposed_photos(holed_site):
    """Every other nadir photo 30 % brighter (as an auto-exposure does over bright ground): the
    orthophoto over the filled DSM covers the whole DSM, and blending lowers the colour jump across
    seams (seam_difference) and the two photos' disagreement at their seams."""
    import rasterio

    from gtkit.export import dsm, ortho
    from gtkit.project import read_stage_record
    from gtkit.synth.plain_variant import _replace_pixels
    from PIL import Image

    proj, _ = holed_site
    P = proj.paths
    dsm.run(proj, dsm.DsmSettings())
    nadir = sorted(P.reference_images.glob("*_N.jpg"))
    for p in nadir[::2]:
        img = np.asarray(Image.open(p)).astype(np.float32)
        _replace_pixels(p, np.clip(img * 1.3, 0, 255).astype(np.uint8), 92)
    out = ortho.run(proj, ortho.OrthoSettings())
    rec = read_stage_record(P.stage("export_ortho")).summary
    with rasterio.open(out) as src:
        alpha = src.read(4)
    print(f"seam difference {rec['seam_difference_before']:.1f} -> {rec['seam_difference_after']:.1f} "
          f"(within one photo {rec['seam_difference_within']:.1f}); photos at seams "
          f"{rec['seam_photo_difference_before']:.1f} -> {rec['seam_photo_difference_after']:.1f}; gains {rec['gains_range']}")
    assert rec["method"] == "photos" and (alpha == 255).mean() > 0.99 and rec["covered_share"] > 0.99
    assert rec["seam_difference_after"] < 0.5 * rec["seam_difference_before"]
    assert rec["seam_photo_difference_after"] < 0.5 * rec["seam_photo_difference_before"]
    assert 0.6 < rec["gains_range"][0] and rec["gains_range"][1] < 1.6
    # blending off: the mosaic as sourced, both figures the same
    out2 = ortho.run(proj, ortho.OrthoSettings(blend=False), out=P.exports / "ortho_raw.tif")
    raw = read_stage_record(P.stage("export_ortho")).summary
    assert out2.is_file() and raw["seam_difference_after"] == raw["seam_difference_before"]


def test_plain_grass_variant_paints_the_square_and_keeps_the_metadata(tiny_sample, tmp_path):
    """The ``plain-grass`` variant: inside its square the reference photos show one colour (up to the
    sun's shading of the relief and the sensor noise), outside it they match the sample's; EXIF/XMP
    unchanged; the model removed so that one is built from the photos."""
    import json

    from gtkit.io.exif import read_photo_meta
    from gtkit.io.poses import read_intrinsics, read_poses
    from gtkit.synth.variants import VARIANTS, apply_variant
    from PIL import Image

    root = tmp_path / "plain"
    shutil.copytree(tiny_sample[0], root)
    apply_variant(root, "plain-grass")
    assert "plain-grass" in VARIANTS and not (root / "model").exists()
    info = json.loads((root / "truth" / "plain_area.json").read_text())
    (cx, cy), half = info["square_centre_xy"], info["half_side_m"]
    assert half > 15 and info["photos_rerendered"] == len(list((root / "images" / "reference").glob("*.jpg")))
    truth = read_poses(root / "truth" / "poses.txt")
    cams = read_intrinsics(root / "truth" / "intrinsics.txt")
    name = min((n for n in truth if n.endswith("_N.jpg")), key=lambda n: np.hypot(*(truth[n].center[:2] - [cx, cy])))
    pose, cam = truth[name], cams[name]
    # pixels of ground points in and out of the square (ground height: the camera's height minus ~90 m)
    z = pose.center[2] - 90.0
    def pix(x, y):
        uv, _ = cam.project(pose.transform(np.array([[x, y, z]])))
        return np.round(uv[0]).astype(int)
    new = np.asarray(Image.open(root / "images" / name)).astype(float)
    old = np.asarray(Image.open(tiny_sample[0] / "images" / name)).astype(float)
    u0, v0 = pix(cx - 0.5 * half, cy + 0.5 * half)
    u1, v1 = pix(cx + 0.5 * half, cy - 0.5 * half)
    inside_new = new[min(v0, v1):max(v0, v1), min(u0, u1):max(u0, u1)]
    inside_old = old[min(v0, v1):max(v0, v1), min(u0, u1):max(u0, u1)]
    def mad(a):   # median absolute deviation, mean of the channels (trees in the square are few)
        return float(np.mean(np.median(np.abs(a - np.median(a, axis=(0, 1))), axis=(0, 1))))
    print(f"{name}: texture inside the square: MAD {mad(inside_new):.1f} DN (the sample's: {mad(inside_old):.1f} DN)")
    assert inside_new.size > 3 * 2000 and mad(inside_new) < 0.4 * mad(inside_old)
    a, b = read_photo_meta(root / "images" / name), read_photo_meta(tiny_sample[0] / "images" / name)
    assert (a.lat, a.lon, a.altitude, a.focal_mm, a.abs_alt) == (b.lat, b.lon, b.altitude, b.focal_mm, b.abs_alt)
