"""`gtkit import model|poses`: every delivery kind lands in the project frame, is recorded in
project.toml, and bad input is a one-line error naming the file (exit status 2)."""
import tomllib

import numpy as np
import pytest
from test_import_support import FRAME_CRS, FRAME_ORIGIN, oblique_poses, small_site

from gtkit.camera import Camera
from gtkit.cli import main
from gtkit.geo import GeoFrame
from gtkit.io.blocks_exchange import write_blocks_exchange
from gtkit.io.mesh import load_model, write_obj
from gtkit.io.poses import read_poses, write_intrinsics, write_poses
from gtkit.io.tiled import write_tiled
from gtkit.project import Project

FRAME = GeoFrame(FRAME_CRS, FRAME_ORIGIN)


@pytest.fixture()
def project(tmp_path):
    return Project.create(tmp_path / "site", FRAME, name="site")


@pytest.fixture(scope="module")
def site_mesh():
    return small_site()


def _imports(project):
    return tomllib.loads(project.paths.project_toml.read_text())["imports"]


def test_import_tiled_model_and_blocks_exchange(project, site_mesh, tmp_path, capsys):
    write_tiled(site_mesh, tmp_path / "delivery", FRAME_CRS, FRAME_ORIGIN, tile_size=100.0)
    (tmp_path / "delivery" / "tiles_index.json").unlink()  # delivered without gtkit's index
    assert main(["import", "model", str(project.paths.root), str(tmp_path / "delivery")]) == 0
    rec = _imports(project)["model"]
    assert rec["format"] == "tiled" and rec["n_tiles"] == 4 and rec["source"] == str(tmp_path / "delivery")
    np.testing.assert_allclose(rec["bounds_world"], site_mesh.bounds(), atol=1e-9)
    assert (project.paths.stage("import") / "tiles_index.json").is_file()
    # poses from a BlocksExchange XML
    cam = Camera("OPENCV", 800, 600, (700.0, 700.0, 400.5, 299.5, -0.02, 0.01, 0.0, 0.0))
    poses = {f"reference/R0_{i:03d}_N.jpg": p for i, p in enumerate(oblique_poses(5, seed=8))}
    xml = write_blocks_exchange(tmp_path / "at.xml", poses, {k: cam for k in poses}, FRAME,
                                image_root=project.paths.images)
    assert main(["import", "poses", str(project.paths.root), str(xml)]) == 0
    rec = _imports(project)["poses"]
    assert rec["format"] == "blocks_exchange" and rec["n_images"] == 5
    back = read_poses(project.paths.root / rec["poses"])  # stored relative to the project
    assert max(max(poses[k].error_to(back[k])) for k in poses) < 1e-6
    import pycolmap

    assert pycolmap.Reconstruction(project.paths.root / rec["colmap"]).num_reg_images() == 5
    assert "imported 5 poses" in capsys.readouterr().out
    # the same block zipped (ContextCapture's .xmlz), COLMAP export as text
    import zipfile

    with zipfile.ZipFile(tmp_path / "at.xmlz", "w") as z:
        z.write(xml, "at.xml")
    assert main(["import", "poses", str(project.paths.root), str(tmp_path / "at.xmlz"), "--text"]) == 0
    rec = _imports(project)["poses"]
    assert rec["n_images"] == 5 and (project.paths.stage("import") / "colmap" / "images.txt").is_file()
    # and back in from the COLMAP model gtkit wrote
    assert main(["import", "poses", str(project.paths.root), str(project.paths.root / rec["colmap"])]) == 0
    back = read_poses(project.paths.root / _imports(project)["poses"]["poses"])
    assert _imports(project)["poses"]["format"] == "colmap"
    assert max(max(poses[k].error_to(back[k])) for k in poses) < 1e-6


def test_import_odm_single_mesh_and_points(project, site_mesh, tmp_path):
    # ODM: vertices = UTM - (integer offset), offset in coords.txt
    off = np.array([499950.0, 3999900.0, 0.0])
    odm = tmp_path / "odm"
    shifted = site_mesh.translated(np.asarray(FRAME_ORIGIN) - off)
    write_obj(odm / "odm_texturing" / "odm_textured_model_geo.obj", shifted)
    (odm / "odm_georeferencing").mkdir(parents=True)
    (odm / "odm_georeferencing" / "coords.txt").write_text("WGS84 UTM 50N\n499950 3999900\n")
    assert main(["import", "model", str(project.paths.root), str(odm)]) == 0
    m = load_model(project.paths.model / "reference.obj", FRAME)
    assert np.abs(m.bounds() - site_mesh.bounds()).max() < 1e-3  # write_obj prints 0.1 mm
    assert _imports(project)["model"]["crs"] == "EPSG:32650"
    # a single OBJ with --crs/--offset; refusing to overwrite, then overwriting
    write_obj(tmp_path / "plain.obj", shifted)
    args = ["import", "model", str(project.paths.root), str(tmp_path / "plain.obj"), "--crs", FRAME_CRS,
            "--offset", "499950,3999900,0"]
    assert main(args) == 2
    assert main(args + ["--overwrite"]) == 0
    # LAS with its CRS in the header
    import laspy

    pts = np.random.default_rng(0).uniform(-50, 50, (500, 3)) + np.asarray(FRAME_ORIGIN)
    hdr = laspy.LasHeader(point_format=2, version="1.4")
    hdr.offsets, hdr.scales = pts.min(0), [0.001] * 3
    hdr.add_crs(FRAME.crs)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.write(str(tmp_path / "cloud.laz"))
    assert main(["import", "model", str(project.paths.root), str(tmp_path / "cloud.laz")]) == 0
    rec = _imports(project)["model"]
    assert rec["format"] == "points" and rec["n_points"] == 500
    np.testing.assert_allclose(rec["bounds_world"], np.stack([pts.min(0), pts.max(0)]) - FRAME_ORIGIN, atol=2e-3)


def test_import_errors_name_the_file(project, site_mesh, tmp_path, capsys):
    # a pose file with NaN / a non-unit quaternion (non-orthonormal rotation)
    cams = {"a.jpg": Camera.pinhole(100, 80, 90.0)}
    write_intrinsics(tmp_path / "intr.txt", cams)
    for bad in ("a.jpg nan 0 0 0 1 2 3", "a.jpg 0.9 0.3 0 0 1 2 3"):
        (tmp_path / "poses.txt").write_text(bad + "\n")
        assert main(["import", "poses", str(project.paths.root), str(tmp_path / "poses.txt"),
                     "--intrinsics", str(tmp_path / "intr.txt")]) == 2
        err = capsys.readouterr().err.strip()
        assert str(tmp_path / "poses.txt") in err and len(err.splitlines()) == 1
    # good hloc file imports
    write_poses(tmp_path / "poses.txt", {"a.jpg": oblique_poses(1)[0]})
    assert main(["import", "poses", str(project.paths.root), str(tmp_path / "poses.txt"),
                 "--intrinsics", str(tmp_path / "intr.txt")]) == 0
    # a mesh with no georeference; a tiled model with an SRS nobody understands
    write_obj(tmp_path / "nogeo.obj", site_mesh)
    assert main(["import", "model", str(project.paths.root), str(tmp_path / "nogeo.obj")]) == 2
    assert "nogeo.obj" in capsys.readouterr().err
    out = write_tiled(site_mesh, tmp_path / "t", FRAME_CRS, FRAME_ORIGIN, tile_size=100.0)
    (out / "metadata.xml").write_text((out / "metadata.xml").read_text().replace(FRAME_CRS, "Lambert 93 please"))
    assert main(["import", "model", str(project.paths.root), str(out)]) == 2
    err = capsys.readouterr().err
    assert "metadata.xml" in err and "SRS cannot be understood" in err
