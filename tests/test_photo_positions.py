"""gtkit.photo_positions: a photo's position is geo.txt's where the file places it, else its EXIF GPS
+ altitude; the registration's GPS prior (a query photo searched at its GPS position, or looking the
way its nearest reference photos do) takes the same position."""
from __future__ import annotations

import numpy as np
import pycolmap

from gtkit.geo import GeoFrame
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.photo_positions import PhotoPositions, positions_and_accuracy
from gtkit.project import Project
from gtkit.sfm.blocks import gps_positions_and_accuracy
from gtkit.sfm.register import RegisterSettings
from gtkit.sfm.register.reference import ReferenceBlock

FRAME = GeoFrame("EPSG:32615", (576700.0, 5188160.0, 0.0))
A, B = "queries/seq1/a.jpg", "queries/seq1/b.jpg"


def _project(tmp_path) -> Project:
    """Two query photos with EXIF GPS; geo.txt moves the first 30 m east and 5 m up (accuracy 2 / 3 m)."""
    proj = Project.create(tmp_path / "p", FRAME)
    rgb = np.zeros((40, 60, 3), np.uint8)
    for n in (A, B):
        (proj.paths.images / n).parent.mkdir(parents=True, exist_ok=True)
        write_jpeg_with_meta(proj.paths.images / n, rgb, lat=46.843, lon=-91.995, alt=200.0)
    exif = FRAME.wgs84_to_local(-91.995, 46.843, 200.0)
    e, n = FRAME.origin[0] + exif[0] + 30.0, FRAME.origin[1] + exif[1]
    proj.paths.geo_txt.write_text(f"EPSG:32615\na.jpg {e:.3f} {n:.3f} 205.0 0 0 0 2.0 3.0\n")
    return proj


def test_geo_txt_first_else_exif(tmp_path):
    proj = _project(tmp_path)
    exif = FRAME.wgs84_to_local(-91.995, 46.843, 200.0)
    reader = PhotoPositions(proj)
    a, b = reader.get(A), reader.get(B)
    assert a.source == "geo.txt" and a.accuracy_m == 3.0
    np.testing.assert_allclose(a.xyz, exif + [30.0, 0.0, 5.0], atol=1e-3)
    assert b.source == "exif" and b.accuracy_m is None
    np.testing.assert_allclose(b.xyz, exif, atol=1e-9)
    assert reader.centre("queries/seq1/missing.jpg") is None    # unreadable and not in geo.txt
    pos, acc = positions_and_accuracy(proj, [A, B])
    pos_b, acc_b = gps_positions_and_accuracy(proj, [A, B])    # the SfM's reader, which this one replaces
    assert acc == acc_b == {A: 3.0}
    assert a.accuracy_hv == (2.0, 3.0) and positions_and_accuracy(proj, [A, B], per_axis=True)[1] == {A: (2.0, 3.0)}
    for n in (A, B):
        np.testing.assert_array_equal(pos[n], pos_b[n])


def test_register_prior_takes_the_geo_txt_position(tmp_path):
    proj = _project(tmp_path)
    ref_dir = tmp_path / "ref_model"
    ref_dir.mkdir()
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=60, height=40, params=[50.0, 30.0, 20.0], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    ref_pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([-100.0, 0.0, -50.0]))
    rec.add_image_with_trivial_frame(pycolmap.Image(name="reference/r.jpg", keypoints=np.zeros((0, 2)),
                                                    camera_id=1, image_id=1), ref_pose)
    rec.write(ref_dir)
    ref = ReferenceBlock(proj, ref_dir, tmp_path / "none.db", RegisterSettings())
    geo = PhotoPositions(proj).get(A).xyz
    searched = ref.attitude_search(A)
    assert searched and all(np.allclose(p.center, geo, atol=1e-6) for _, p in searched)
    near = ref.neighbour_priors(A)   # at its position, at its own height and at its reference neighbour's
    np.testing.assert_allclose(near[0].center, geo, atol=1e-6)
    np.testing.assert_allclose(near[1].center, [geo[0], geo[1], 50.0], atol=1e-6)
    exif = FRAME.wgs84_to_local(-91.995, 46.843, 200.0)
    np.testing.assert_allclose(ref.attitude_search(B)[0][1].center, exif, atol=1e-6)


def test_prior_pose_is_the_geo_txt_position_with_the_gimbal_attitude(tmp_path):
    """The pose the photo's metadata claims, as the registration's priors, the 3D view and the
    annotator's reference ranking read it: geo.txt's position where it places the photo, the DJI
    gimbal's attitude; a photo without gimbal angles claims no pose."""
    from gui.ranking import OverlapRanker

    from gtkit.pose import Pose
    from gtkit.view.scene import prior_poses

    proj = _project(tmp_path)
    gimbal = {"GimbalYawDegree": 40.0, "GimbalPitchDegree": -60.0, "GimbalRollDegree": 0.0}
    for n in (A, B):
        write_jpeg_with_meta(proj.paths.images / n, np.zeros((40, 60, 3), np.uint8), lat=46.843, lon=-91.995,
                             alt=200.0, dji=gimbal)
    exif = FRAME.wgs84_to_local(-91.995, 46.843, 200.0)
    want = {A: Pose.from_dji(40.0, -60.0, 0.0, exif + [30.0, 0.0, 5.0]), B: Pose.from_dji(40.0, -60.0, 0.0, exif)}
    readers = {"photo_positions": PhotoPositions(proj).prior_pose, "view": lambda n: prior_poses(proj, [n])[n],
               "annotator": OverlapRanker(proj.paths, proj.frame).pose}
    for who, read in readers.items():
        for n, p in want.items():
            got = read(n)
            np.testing.assert_allclose(got.center, p.center, atol=1e-3, err_msg=f"{who} {n}")   # geo.txt: mm
            np.testing.assert_allclose(got.R, p.R, atol=1e-9, err_msg=f"{who} {n}")
    write_jpeg_with_meta(proj.paths.images / B, np.zeros((40, 60, 3), np.uint8), lat=46.843, lon=-91.995, alt=200.0)
    assert PhotoPositions(proj).prior_pose(B) is None          # GPS but no gimbal: no attitude to claim
