"""SfM blocks on real photos (the 18 DJI Brighton Beach images, downscaled for speed),
georegistered by their GPS and compared with the independent model.laz; ODM file readers.
The reference block is built ONCE per session and asserted on by several tests."""
from __future__ import annotations

import time

import numpy as np
import pytest
from PIL import Image

from conftest import BRIGHTON
from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame
from gtkit.io.odm import parse_odm_crs, read_gcp_list, read_geo_txt
from gtkit.io.poses import read_intrinsics, read_poses
from gtkit.project import Project
from gtkit.evaluate import gt_report as report  # the report with its checks (gtkit report)
from gtkit.sfm import blocks

pytestmark = pytest.mark.skipif(not (BRIGHTON / "images").is_dir(), reason="Brighton Beach photos not available")

FRAME = GeoFrame("EPSG:32615", (576700.0, 5188160.0, 0.0))


def _settings() -> blocks.SfmSettings:
    s = blocks.SfmSettings()
    s.features.max_image_size = 1000
    s.features.max_num_features = 2000
    s.georegister.gps_inlier_m = 5.0  # consumer GPS
    s.query_pattern = "*.JPG"
    return s


@pytest.fixture(scope="session")
def brighton(tmp_path_factory):
    root = tmp_path_factory.mktemp("brighton")
    proj = Project.create(root, FRAME, "brighton")
    (root / "images").mkdir()
    (root / "images" / "reference").symlink_to(BRIGHTON / "images")
    # a query "sequence": 5 consecutive photos plus a featureless one that cannot register
    seq = root / "images" / "queries" / "seqA"
    seq.mkdir(parents=True)
    for n in ("DJI_0018", "DJI_0019", "DJI_0020", "DJI_0021", "DJI_0022"):
        (seq / f"{n}.JPG").symlink_to(BRIGHTON / "images" / f"{n}.JPG")
    Image.new("RGB", (1000, 560), (128, 128, 128)).save(seq / "DJI_9999.JPG")
    t = time.time()
    ref = blocks.run_reference(proj, _settings())
    t_ref = time.time() - t
    q = blocks.run_queries(proj, _settings())
    rep = report.run(proj, report.ReportSettings(point_cloud=str(BRIGHTON / "model.laz")))
    return proj, ref, q, rep, t_ref


def test_reference_block_registers_all_photos(brighton):
    proj, ref, _, _, _ = brighton
    assert ref["n_registered"] == ref["n_images"] == 18
    # full-size pixels of 4000x2250 photos, features found at 1000 px: 1 px there = 4 px here
    assert ref["mean_reproj_px"] < 2.0
    poses = read_poses(proj.paths.stage("sfm_reference") / "poses.txt")
    cams = read_intrinsics(proj.paths.stage("sfm_reference") / "intrinsics.txt")
    assert len(poses) == len(cams) == 18
    # no cameras.txt: the EXIF focal (20 mm equivalent -> ~2120 px) is kept, distortion refined
    f = np.median([c.fx for c in cams.values()])
    assert 2000 < f < 2400, f


def test_georegistered_by_gps(brighton):
    proj, ref, _, _, _ = brighton
    geo = ref["georegistration"]
    assert geo["n_inliers"] >= 16 and geo["gps_residual_median_m"] < 2.0, geo
    gps = blocks.gps_positions(proj, [f"reference/{p.name}" for p in (BRIGHTON / "images").glob("*.JPG")])
    poses = read_poses(proj.paths.stage("sfm_reference") / "poses.txt")
    d = [np.linalg.norm(poses[n].center - gps[n]) for n in poses]
    assert np.median(d) < 2.0
    # nadir photos: optical axis points down
    assert all((p.R.T @ [0, 0, 1])[2] < -0.9 for p in poses.values())


def test_offsets_from_independent_point_cloud(brighton):
    _, _, _, rep, _ = brighton
    pc = rep["point_cloud_comparison"]
    # measured: +0.68 m vertical, 0.02 m horizontal (1600 px features); GPS heights are consumer-grade
    assert abs(pc["vertical_offset_m"]) < 3.0
    assert pc["horizontal_offset_m"] < 1.0
    assert pc["nn_distance_after_shift_median_m"] < 0.5
    assert pc["vertical_abs_median_m"] < 0.5
    md = (brighton[0].paths.reports / "gt_report.md").read_text()
    assert "vertical offset from model.laz" in md


def test_query_block_lists_unregistered_with_reason(brighton):
    proj, _, q, _, _ = brighton
    b = q["seqA"]
    # one flight line over sand at 1000 px / 2000 features: a weak block; what fails is listed
    assert b["n_registered"] >= 3 and b["n_images"] == 6
    assert set(b["unregistered"]) == {f"queries/seqA/{n}.JPG" for n in ("DJI_0018", "DJI_0019", "DJI_0020",
                                                                          "DJI_0021", "DJI_0022", "DJI_9999")} - set(
        read_poses(proj.paths.stage("sfm_queries") / "seqA" / "poses.txt"))
    assert "too few features" in b["unregistered"]["queries/seqA/DJI_9999.JPG"]
    assert all(why for why in b["unregistered"].values())


def test_resume_skips_finished_stage(brighton):
    proj, ref, _, _, t_ref = brighton
    t = time.time()
    again = blocks.run_reference(proj, _settings())
    assert time.time() - t < 2.0 < t_ref
    assert again["n_registered"] == ref["n_registered"]


# --- ODM readers ----------------------------------------------------------------------------

def test_odm_crs_header():
    assert parse_odm_crs("WGS84 UTM 50N") == "EPSG:32650"
    assert parse_odm_crs("WGS84 UTM 33S") == "EPSG:32733"
    assert parse_odm_crs("EPSG:32615") == "EPSG:32615"
    with pytest.raises(GtkitError, match="CRS"):
        parse_odm_crs("EPSG:99999999")


def test_gcp_list_and_geo_txt(tmp_path):
    f = tmp_path / "gcp_list.txt"
    f.write_text("WGS84 UTM 15N\n576710.5 5188170.25 160.0 100.5 200.5 DJI_0018.JPG g1\n"
                 "576710.5 5188170.25 160.0 300.5 220.5 DJI_0019.JPG g1\n"
                 "576720.0 5188180.0 161.0 50 60 DJI_0019.JPG g2\n")
    g = read_gcp_list(f, FRAME)
    assert [x.name for x in g] == ["g1", "g2"] and len(g[0].clicks) == 2
    np.testing.assert_allclose(g[0].xyz, [10.5, 10.25, 160.0], atol=1e-6)
    f.write_text("EPSG:32615\n1 2 3 4 5\n")
    with pytest.raises(GtkitError, match="line 2"):
        read_gcp_list(f, FRAME)
    geo = tmp_path / "geo.txt"
    geo.write_text("EPSG:4326\nDJI_0018.JPG -91.995 46.843 198.3\nDJI_0019.JPG -91.995 46.8431\n")
    e = read_geo_txt(geo, FRAME)
    assert np.isfinite(e["DJI_0018.JPG"].xyz).all() and np.isnan(e["DJI_0019.JPG"].xyz[2])
    assert abs(e["DJI_0018.JPG"].xyz[0] - (FRAME.wgs84_to_local(-91.995, 46.843, 0)[0])) < 1e-6
