"""Orthophoto, mesh and coordinate exports, measured on the analytic scene of test_export."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from gtkit.errors import GtkitError
from test_export import (BUILDINGS, FILE_OFFSET, FRAME, _inside, building_color, dsm_errors, edge_distance,
                         make_project, scene_mesh, texture_rgb)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    return make_project(tmp_path_factory.mktemp("export_products") / "site")


def test_orthophoto_colours_and_georeference(project):
    import rasterio

    from gtkit.export import ortho

    out = ortho.run(project, ortho.OrthoSettings(cog=True))
    with rasterio.open(out) as src:
        assert src.crs.to_epsg() == 32650 and src.count == 4 and src.overviews(1)
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        t = src.transform
        assert t.a == 0.25 and t.c == 500123.0 and t.f == 4000556.0  # texel 0.21 m -> 0.25 m cells
        rgba = src.read()
    rgb, alpha = rgba[:3].transpose(1, 2, 0).astype(float), rgba[3]
    assert alpha.mean() > 0.99 * 255  # the model covers its whole extent
    H, W = alpha.shape
    X, Y = np.meshgrid(0.0 + (np.arange(W) + 0.5) * 0.25, 100.0 - (np.arange(H) + 0.5) * 0.25)
    roofs = np.zeros(X.shape, int) - 1
    for k, b in enumerate(BUILDINGS):
        roofs[_inside(b, X, Y)] = k
    away = edge_distance(X, Y) > 0.5
    ground = (roofs < 0) & away
    expect = texture_rgb(X / 120.0, Y / 100.0)
    err_ground = np.abs(rgb[ground] - expect[ground])
    err_roof = np.concatenate([np.abs(rgb[(roofs == k) & away] - building_color(k)) for k in range(len(BUILDINGS))])
    print(f"ortho: ground median {np.median(err_ground):.2f} DN p95 {np.percentile(err_ground, 95):.2f} DN; "
          f"roofs max {err_roof.max():.1f} DN")
    assert np.median(err_ground) < 2.0 and np.percentile(err_ground, 95) < 6.0
    assert err_roof.max() <= 1.0  # true ortho: roofs sit on their footprints, no lean


def test_mesh_export_obj_ply_glb_in_project_crs(project):
    import trimesh

    from gtkit.export import mesh_export
    from gtkit.io.mesh import load_model, read_offset_sidecar

    ref = scene_mesh()
    for fmt in ("obj", "glb", "ply"):
        out = mesh_export.run(project, mesh_export.MeshExportSettings(format=fmt))
        assert out == project.paths.mesh_export / f"model.{fmt}"
        crs, off = read_offset_sidecar(out)
        side = json.loads((out.parent / f"model.{fmt}.offset.json").read_text())
        assert crs == "EPSG:32650" and list(off) == [500123.0, 4000456.0, 0.0] and "axes" in side
        if fmt == "ply":
            tm = trimesh.load(out, process=False)
            assert len(tm.faces) == ref.n_triangles
            v = np.asarray(tm.vertices) + off - np.asarray(FRAME.origin)
            assert np.allclose(v.min(0), ref.bounds()[0], atol=1e-3) and np.allclose(v.max(0), ref.bounds()[1], atol=1e-3)
            continue
        back = load_model(out, FRAME)  # through its sidecar, back into the project's world frame
        assert back.n_triangles == ref.n_triangles
        assert np.allclose(back.bounds(), ref.bounds(), atol=1e-3)
        assert any(p.texture is not None for p in back.parts)


def test_decimated_mesh_keeps_the_surface(project, tmp_path):
    from gtkit.export import dsm, mesh_export
    from gtkit.io.mesh import load_model

    out = mesh_export.run(project, mesh_export.MeshExportSettings(format="obj", decimate=300),
                          out_dir=tmp_path / "dec")
    m = load_model(out, FRAME)
    assert m.n_triangles <= 340 and any(p.texture is not None for p in m.parts)
    # the DSM of the decimated mesh still matches the analytic surface (planar terrain, boxes)
    err, edge, _ = dsm_errors(dsm.run(project, dsm.DsmSettings(resolution=0.5), input=out, out=tmp_path / "d.tif"))
    print(f"decimated to {m.n_triangles} triangles: DSM median {np.median(err):.4f} m p95 {np.percentile(err, 95):.4f} m")
    assert np.percentile(err, 95) < 0.01


def test_coordinates_csv_geojson_geotxt(project, tmp_path):
    from pyproj import Transformer

    from gtkit.export import coordinates
    from gtkit.io.poses import write_poses
    from gtkit.pose import Pose

    cams = {"reference/R01_003_N.jpg": Pose.from_dji(30.0, -90.0, 0.0, [10.0, 20.0, 120.0]),
            "queries/seq1/0004_W.jpg": Pose.from_dji(-120.5, -35.0, 1.5, [60.0, -40.0, 180.0])}
    pose_file = tmp_path / "poses.txt"
    write_poses(pose_file, cams)
    targets = tmp_path / "targets.csv"
    lon, lat = Transformer.from_crs("EPSG:32650", "EPSG:4326", always_xy=True).transform(500200.0, 4000500.0)
    targets.write_text(f"id,time,lon,lat,height\ncar,12.5,{lon!r},{lat!r},55.25\nlost,13.0,,,\n")
    (project.paths.gcp_list).write_text("EPSG:32650\n500130.5 4000470.25 52.0 100.5 200.5 reference/R01_003_N.jpg gcp7\n"
                                        "500130.5 4000470.25 52.0 300.5 210.5 reference/R01_004_N.jpg gcp7\n")
    files = coordinates.run(project, coordinates.CoordinatesSettings(poses=str(pose_file), targets=str(targets)))
    assert {"cameras.csv", "cameras_wgs84.geojson", "cameras_crs.geojson", "geo.txt", "targets.csv",
            "targets_wgs84.geojson", "targets_crs.geojson"} <= set(files)
    text = files["cameras.csv"].read_text()
    assert text.startswith("# easting/northing: EPSG:32650") and "ellipsoidal" in text.splitlines()[0]
    rows = {r["name"]: r for r in csv.DictReader(text.splitlines()[1:])}
    r = rows["queries/seq1/0004_W.jpg"]
    assert float(r["easting"]) == pytest.approx(500183.0, abs=1e-4)
    assert float(r["northing"]) == pytest.approx(4000416.0, abs=1e-4)
    assert float(r["height"]) == pytest.approx(230.0, abs=1e-4)
    assert (float(r["yaw"]), float(r["pitch"]), float(r["roll"])) == pytest.approx((-120.5, -35.0, 1.5), abs=1e-3)
    elon, elat = Transformer.from_crs("EPSG:32650", "EPSG:4326", always_xy=True).transform(500183.0, 4000416.0)
    assert float(r["lon"]) == pytest.approx(elon, abs=1e-8) and float(r["lat"]) == pytest.approx(elat, abs=1e-8)
    gj = json.loads(files["cameras_wgs84.geojson"].read_text())
    f0 = [f for f in gj["features"] if f["properties"]["name"] == "queries/seq1/0004_W.jpg"][0]
    assert f0["geometry"]["coordinates"] == pytest.approx([elon, elat, 230.0], abs=1e-8)
    assert "ellipsoidal" in gj["gtkit"]["heights"]
    gc = json.loads(files["cameras_crs.geojson"].read_text())
    assert gc["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32650"
    geo = files["geo.txt"].read_text().splitlines()
    assert geo[0] == "EPSG:32650"
    g = {ln.split()[0]: [float(v) for v in ln.split()[1:]] for ln in geo[1:]}
    assert g["0004_W.jpg"] == pytest.approx([500183.0, 4000416.0, 230.0, -120.5, -35.0, 1.5], abs=1e-3)
    t = {r["name"]: r for r in csv.DictReader(files["targets.csv"].read_text().splitlines()[1:])}
    assert float(t["car"]["easting"]) == pytest.approx(500200.0, abs=1e-3) and t["car"]["time"] == "12.5"
    assert float(t["gcp_gcp7"]["northing"]) == pytest.approx(4000470.25, abs=1e-4)
    assert len(t) == 2  # the GCP observed in two photos is one target; "lost" has no coordinates
    # the tracking stage's CSV (x,y,z in the CRS, label, time) is the default targets file
    project.paths.tracks.write_text("# gtkit track\nlabel,time,image,x,y,z,lon,lat,h,status\n"
                                    f"car,1.0,q/1_Z.jpg,500210.0,4000510.0,56.0,{lon!r},{lat!r},56.0,ok\n")
    files = coordinates.run(project, coordinates.CoordinatesSettings(poses=str(pose_file)))
    t = list(csv.DictReader(files["targets.csv"].read_text().splitlines()[1:]))
    car = [r for r in t if r["name"] == "car"][0]
    assert float(car["easting"]) == pytest.approx(500210.0) and car["image"] == "q/1_Z.jpg" and "x" not in car


def test_cli_export_mesh_and_bad_inputs(project, tmp_path, capsys):
    from gtkit.cli import main
    from gtkit.io.mesh import write_offset_sidecar

    assert main(["export", "mesh", str(project.paths.root), "--format", "ply", "--out-dir", str(tmp_path)]) == 0
    assert (tmp_path / "model.ply").is_file() and (tmp_path / "model.ply.offset.json").is_file()
    # a model in another CRS: a one-line error naming the file, exit code 2
    bad = make_project(tmp_path / "bad")
    write_offset_sidecar(bad.paths.model / "reference.obj", "EPSG:4978", FILE_OFFSET)
    assert main(["export", "ortho", str(bad.paths.root)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "reference.obj" in err and "does not match the project CRS" in err
    assert main(["export", "dsm", str(project.paths.root), "--input", "x.obj", "--offset", "1,2"]) == 2
    assert "--offset needs three numbers" in capsys.readouterr().err
    with pytest.raises(GtkitError, match=r"nocloud\.xyz: not a mesh or point cloud"):
        from gtkit.export import dsm

        (tmp_path / "nocloud.xyz").write_text("1 2 3\n")
        dsm.run(project, dsm.DsmSettings(), input=tmp_path / "nocloud.xyz", out=tmp_path / "x.tif")
