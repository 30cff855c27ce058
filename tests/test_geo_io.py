"""CRS handling, pose/intrinsics files, tie points, project folders, EXIF/XMP, bad input."""

import numpy as np
import pytest

from conftest import BRIGHTON
from gtkit.camera import Camera
from gtkit.conventions import dji_to_rotation
from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame, parse_crs, utm_epsg
from gtkit.io.exif import read_photo_meta, write_jpeg_with_meta
from gtkit.io.mesh import read_mesh_file
from gtkit.io.poses import read_intrinsics, read_poses, write_intrinsics, write_poses
from gtkit.io.tiepoints import Observation, TiePoint, read_tiepoints, write_tiepoints
from gtkit.pose import Pose
from gtkit.project import Project, mark_stage_done, stage_done

PHOTOS = sorted((BRIGHTON / "images").glob("*.JPG"))


def test_utm_zone_from_longitude():
    assert utm_epsg(-91.995, 46.843) == 32615   # Brighton Beach, Duluth
    assert utm_epsg(114.3, 30.5) == 32650
    assert utm_epsg(151.2, -33.9) == 32756      # southern hemisphere


def test_wgs84_round_trip_and_origin():
    f = GeoFrame.for_lonlat(114.3, 30.5, 20.0)
    assert f.crs_spec == "EPSG:32650"
    local = f.wgs84_to_local(114.301, 30.501, 55.0)
    back = f.local_to_wgs84(local)
    np.testing.assert_allclose(back, [114.301, 30.501, 55.0], atol=1e-9)
    # the local origin is small: the site sits near (0, 0)
    assert np.all(np.abs(local[:2]) < 200) and local[2] == pytest.approx(35.0)
    # a named EPSG code is honoured
    assert GeoFrame.for_lonlat(114.3, 30.5, epsg=4547).crs.to_epsg() == 4547


def test_unknown_epsg_is_a_clear_error():
    with pytest.raises(GtkitError, match="EPSG:999999"):
        parse_crs("EPSG:999999")
    with pytest.raises(GtkitError, match="not projected"):
        GeoFrame("EPSG:4326")


def test_pose_and_intrinsics_files_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    poses = {f"queries/s1/{i:04d}_W.jpg": Pose.from_dji(*rng.uniform(-60, 60, 3), rng.normal(0, 100, 3))
             for i in range(5)}
    write_poses(tmp_path / "poses.txt", poses)
    got = read_poses(tmp_path / "poses.txt")
    for k, p in poses.items():
        dp, dr = got[k].error_to(p)
        assert dp < 1e-9 and dr < 1e-6
    cams = {"a.jpg": Camera("OPENCV", 1024, 768, (800, 801, 512, 384, -0.05, 0.01, 0.0, 0.0)),
            "b.jpg": Camera.pinhole(640, 480, 2000)}
    write_intrinsics(tmp_path / "cams.txt", cams)
    assert read_intrinsics(tmp_path / "cams.txt") == cams


def test_hloc_style_pose_file_loads(tmp_path):
    """A file as hloc / the UAVD4L tools write it (no header, 8 fields a line) loads unchanged."""
    (tmp_path / "p.txt").write_text("img1.JPG 0.7071067811865476 0 0 0.7071067811865476 1 2 3\n")
    p = read_poses(tmp_path / "p.txt")["img1.JPG"]
    np.testing.assert_allclose(p.t, [1, 2, 3])
    np.testing.assert_allclose(p.R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


@pytest.mark.parametrize("line,msg", [
    ("a.jpg 1 0 0 0 1 2", "expected"),
    ("a.jpg nan 0 0 0 1 2 3", "NaN|not unit"),
    ("a.jpg 2 0 0 0 1 2 3", "not unit"),
])
def test_bad_pose_file_names_file_and_line(tmp_path, line, msg):
    f = tmp_path / "bad.txt"
    f.write_text(line + "\n")
    with pytest.raises(GtkitError, match=msg) as e:
        read_poses(f)
    assert str(f) in str(e.value) and "line 1" in str(e.value) and "\n" not in str(e.value)


def test_pose_rejects_non_orthonormal():
    with pytest.raises(GtkitError, match="orthonormal"):
        Pose(np.diag([1.0, 1.0, 2.0]), np.zeros(3))


def test_camera_projection_and_distortion():
    cam = Camera("OPENCV", 1000, 800, (900, 900, 500, 400, -0.08, 0.02, 0.001, -0.0005))
    rng = np.random.default_rng(2)
    uv = rng.uniform([50, 50], [950, 750], (100, 2))
    d = cam.rays(uv)
    back, front = cam.project(d * 37.0)
    assert front.all()
    np.testing.assert_allclose(back, uv, atol=1e-6)
    # against pycolmap's own implementation of the model
    pc = cam.to_pycolmap()
    np.testing.assert_allclose(pc.img_from_cam(d), uv, atol=1e-6)


def test_tiepoints_round_trip(tmp_path):
    tps = [TiePoint("tp1", [Observation("queries/s1/0001_W.jpg", 10.5, 20.25),
                            Observation("reference/R0_0001_N.jpg", 400.0, 300.0)], "gui")]
    write_tiepoints(tmp_path / "t.json", tps)
    assert read_tiepoints(tmp_path / "t.json") == tps


def test_project_create_load_and_stage_records(tmp_path):
    frame = GeoFrame.for_lonlat(114.3, 30.5, 20.0)
    Project.create(tmp_path / "site", frame, name="demo")
    proj = Project.load(tmp_path / "site")
    assert proj.frame == frame and proj.name == "demo"
    d = proj.paths.stage("sfm")
    assert not stage_done(d, {"a": 1})
    mark_stage_done(d, {"a": 1}, inputs={"x": "1"})
    assert stage_done(d, {"a": 1}, inputs={"x": "1"})
    assert not stage_done(d, {"a": 2}, inputs={"x": "1"})     # changed setting recomputes
    assert not stage_done(d, {"a": 1}, inputs={"x": "2"})     # changed input recomputes
    with pytest.raises(GtkitError, match="not a gtkit project"):
        Project.load(tmp_path)


def test_reads_real_dji_photos():
    """The 18 real DJI photos: EXIF GPS and every DJI XMP tag gtkit uses."""
    assert len(PHOTOS) == 18
    frame = GeoFrame("EPSG:32615")
    for f in PHOTOS:
        m = read_photo_meta(f, require=("gps", "gimbal"))
        assert (m.width, m.height) == (4000, 2250)
        assert 46.84 < m.lat < 46.845 and -91.997 < m.lon < -91.993
        assert m.gimbal_pitch == pytest.approx(-89.9, abs=0.5)
        assert None not in (m.flight_yaw, m.flight_pitch, m.flight_roll, m.abs_alt, m.rel_alt)
        assert 35 < m.rel_alt < 45
        e, n, _ = frame.wgs84_to_local(m.lon, m.lat, m.abs_alt)
        # inside (or within GPS error of) the independent point cloud's bounds
        assert 576600 < e < 576830 and 5188050 < n < 5188280


def test_exif_xmp_write_read_round_trip(tmp_path):
    rgb = np.random.default_rng(3).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    f = write_jpeg_with_meta(tmp_path / "x.jpg", rgb, lat=-33.91234567, lon=151.2345678, alt=123.4,
                             dji={"GimbalYawDegree": -35.5, "GimbalPitchDegree": -45.2, "GimbalRollDegree": 0.3,
                                  "FlightYawDegree": -30.0, "AbsoluteAltitude": 123.4, "RelativeAltitude": 98.7},
                             timestamp="2024:05:01 10:00:02")
    m = read_photo_meta(f, require=("gps", "gimbal"))
    assert m.lat == pytest.approx(-33.91234567, abs=1e-7) and m.lon == pytest.approx(151.2345678, abs=1e-7)
    assert m.gps_alt == pytest.approx(123.4) and m.rel_alt == pytest.approx(98.7)
    assert (m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll) == (-35.5, -45.2, 0.3)
    assert m.timestamp == "2024:05:01 10:00:02"


def test_bad_input_errors_are_one_line_and_name_the_file(tmp_path):
    cases = []
    missing = tmp_path / "missing.jpg"
    with pytest.raises(GtkitError) as e:
        read_photo_meta(missing)
    cases.append((e.value, missing, "not found"))

    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(PHOTOS[0].read_bytes()[:200_000])
    with pytest.raises(GtkitError) as e:
        read_photo_meta(corrupt)
    cases.append((e.value, corrupt, "corrupt|truncated"))

    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(GtkitError) as e:
        read_photo_meta(garbage)
    cases.append((e.value, garbage, "not a readable image"))

    plain = tmp_path / "plain.jpg"
    write_jpeg_with_meta(plain, np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(GtkitError) as e:
        read_photo_meta(plain, require=("gps",))
    cases.append((e.value, plain, "no EXIF GPS"))

    notmesh = tmp_path / "model.obj"
    notmesh.write_text("hello, I am a text file\nnot a mesh\n")
    with pytest.raises(GtkitError) as e:
        read_mesh_file(notmesh)
    cases.append((e.value, notmesh, "no triangles|not a readable mesh"))

    binmesh = tmp_path / "model.ply"
    binmesh.write_bytes(b"\x00\x01garbage" * 50)
    with pytest.raises(GtkitError) as e:
        read_mesh_file(binmesh)
    cases.append((e.value, binmesh, "not a readable mesh|no triangles"))

    toml = tmp_path / "p" / "project.toml"
    toml.parent.mkdir()
    toml.write_text('[crs]\ncrs = "EPSG:999999"\n')
    with pytest.raises(GtkitError) as e:
        Project.load(toml.parent)
    cases.append((e.value, toml, "unknown or invalid CRS"))

    import re
    for err, path, pattern in cases:
        s = str(err)
        assert "\n" not in s and str(path) in s and re.search(pattern, s), s


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    from gtkit.cli import main

    rc = main(["meta", str(tmp_path / "nope.jpg")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "nope.jpg" in err and "not found" in err


def test_dji_angles_of_real_photos_give_nadir_rotation():
    m = read_photo_meta(PHOTOS[0])
    R = dji_to_rotation(m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll)
    assert R[2] @ np.array([0, 0, -1.0]) > 0.999  # optical axis points down


def _triangles(V, F):
    """Triangles as sorted rows of their 9 coordinates, corners sorted too (order-free comparison)."""
    t = np.asarray(V)[np.asarray(F)]                       # (M, 3, 3)
    t = np.take_along_axis(t, np.lexsort(t.transpose(2, 0, 1)[::-1], axis=-1)[:, :, None], axis=1).reshape(-1, 9)
    return t[np.lexsort(t.T[::-1])]


def test_obj_geometry_reader_agrees_with_trimesh_on_awkward_files(tmp_path):
    """The heights-only OBJ reader (gtkit.io.obj_geometry) gives trimesh's triangles for the forms
    OBJ writers use: v/vt, v//vn, bare v, quads and polygons (fans), vertex colours, CRLF, several
    materials; relative (negative) indices count back from the line, as the OBJ format says
    (trimesh 5.2 counts them from the end of the file, so they are checked against the same file
    with absolute indices); bad indices are a one-line error naming the file."""
    from PIL import Image

    from gtkit.io.obj_geometry import read_obj_geometry

    Image.fromarray(np.zeros((40, 80, 3), np.uint8)).save(tmp_path / "t.png")
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 1 1\nmap_Kd t.png\n\nnewmtl b\nKd 0.5 0.5 0.5\n")
    lines = ["# a comment", "mtllib m.mtl", "o first"]
    lines += [f"v {x} {y} {z} 0.5 0.5 0.5" for x, y, z in [(0, 0, 1), (4, 0, 1), (4, 2, 1), (0, 2, 1)]]
    lines += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "vn 0 0 1", "usemtl a", "f 1/1 2/2 3/3", "f 1/1/1 3/3/1 4/4/1"]
    lines += ["o second", "v 10 0 2", "v 12 0 2", "v 13 1 2", "v 12 2 2", "v 10 2 2", "usemtl b",
              "f 5//1 6//1 7//1 8//1 9//1", "f 6 8 9"]
    lines += ["o third", "v 20 0 3", "v 21 0 3", "v 21 1 3", "v 20 1 3", "f 10 11 12 13"]
    obj = tmp_path / "awkward.obj"
    obj.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    g = read_obj_geometry(obj)
    ref = read_mesh_file(obj)
    Vr = np.concatenate([p.vertices for p in ref.parts])
    Fr, n = [], 0
    for p in ref.parts:
        Fr.append(p.faces + n)
        n += len(p.vertices)
    assert g.n_triangles == 2 + 3 + 1 + 2 == ref.n_triangles
    np.testing.assert_array_equal(_triangles(g.vertices, g.faces), _triangles(Vr, np.concatenate(Fr)))
    np.testing.assert_array_equal(g.bounds(), ref.bounds())
    # texel size from material a only (80 x 40 texels over 4 x 2 m: 0.05 m), material b has no image
    assert g.texel_size == pytest.approx(0.05)
    relative = tmp_path / "relative.obj"
    relative.write_bytes(obj.read_bytes().replace(b"f 5//1 6//1 7//1 8//1 9//1", b"f -5//1 -4//1 -3//1 -2//1 -1//1"))
    r = read_obj_geometry(relative)
    np.testing.assert_array_equal(r.faces, g.faces)
    shifted = read_obj_geometry(obj, shift=(100.0, 200.0, 0.0))
    np.testing.assert_array_equal(shifted.vertices, g.vertices + np.array([100.0, 200.0, 0.0]))
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(GtkitError, match="bad.obj") as e:
        read_obj_geometry(bad)
    assert "does not exist" in str(e.value)
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\n")
    with pytest.raises(GtkitError, match="no triangles"):
        read_obj_geometry(empty)
