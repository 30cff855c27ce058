"""Existing poses: BlocksExchange XML and COLMAP models round trip to the same poses (<= 1e-6 m,
<= 1e-6 deg), the COLMAP export opens with pycolmap, SRS conversion is consistent, bad input fails."""
import numpy as np
import pytest
from test_import_support import FRAME_CRS, FRAME_ORIGIN, oblique_poses

from gtkit.camera import Camera
from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame
from gtkit.io.blocks_exchange import read_blocks_exchange, write_blocks_exchange
from gtkit.io.colmap_model import read_colmap_model, write_colmap_model
from gtkit.io.srs import SrsToWorld
from gtkit.pose import Pose

FRAME = GeoFrame(FRAME_CRS, FRAME_ORIGIN)


def synthetic_block(n=12):
    wide = Camera("OPENCV", 1024, 768, (880.5, 881.25, 515.3, 380.9, -0.051, 0.012, 0.0004, -0.0003))
    zoom = Camera.pinhole(800, 600, 2400.0, cx=401.5, cy=298.25)
    poses, cams = {}, {}
    for i, p in enumerate(oblique_poses(n, seed=11)):
        name = f"queries/seq1/{i:04d}_{'W' if i % 2 == 0 else 'Z'}.jpg"
        poses[name], cams[name] = p, (wide if i % 2 == 0 else zoom)
    return poses, cams


def _assert_same(a: dict, b: dict, tol_m=1e-6, tol_deg=1e-6):
    assert set(a) == set(b)
    worst = max((a[k].error_to(b[k]) for k in a), key=lambda e: e[0] + e[1])
    assert worst[0] <= tol_m and worst[1] <= tol_deg, worst
    return worst


def test_blocks_exchange_round_trip_and_colmap_export(tmp_path):
    poses, cams = synthetic_block()
    xml = write_blocks_exchange(tmp_path / "block.xml", poses, cams, FRAME, image_root=tmp_path / "images")
    block = read_blocks_exchange(xml, FRAME, image_root=tmp_path / "images")
    _assert_same(poses, block.poses)
    for k in cams:
        assert block.cameras[k].model == cams[k].model
        np.testing.assert_allclose(block.cameras[k].params, cams[k].params, rtol=1e-12)
    # COLMAP export (binary and text) opens with pycolmap with the same poses
    import pycolmap

    for binary in (True, False):
        d = write_colmap_model(tmp_path / f"colmap_{binary}", block.poses, block.cameras, FRAME, binary=binary)
        rec = pycolmap.Reconstruction(str(d))
        assert rec.num_reg_images() == len(poses) and rec.num_cameras() == 2
        from_rec = {im.name: Pose.from_pycolmap(im.cam_from_world()) for im in rec.images.values()}
        _assert_same(poses, from_rec)
        p2, c2 = read_colmap_model(d, FRAME)
        _assert_same(poses, p2)
        assert all(c2[k] == block.cameras[k] for k in c2)
        # projections agree: a ground point lands on the same pixel through both
        X = np.array([[5.0, -3.0, 0.0]])
        for k in list(poses)[:3]:
            cam = c2[k]
            uv_a, _ = cam.project(poses[k].transform(X))
            uv_b, _ = Camera.from_pycolmap(rec.cameras[rec.find_image_with_name(k).camera_id]).project(
                from_rec[k].transform(X))
            assert np.abs(uv_a - uv_b).max() < 1e-6


def test_enu_block_lands_in_project_frame(tmp_path):
    """A block in ENU:lat,lon (ContextCapture's local frame): after import a ground point projects
    to the same pixel as the ENU camera sees it."""
    # 150 km east of the zone's central meridian: ENU north and grid north differ by ~0.7 deg
    lon, lat = FRAME.local_to_wgs84(np.array([150000.0, -10.0, 0.0]))[:2]
    srs = f"ENU:{lat:.10f},{lon:.10f}"
    tr = SrsToWorld(srs, FRAME)
    cam = Camera.pinhole(640, 480, 600.0)
    enu_poses = {f"p{i}.jpg": p for i, p in enumerate(oblique_poses(5, seed=5))}
    L = ['<?xml version="1.0"?>', "<BlocksExchange version=\"3.2\"><SpatialReferenceSystems>",
         f"<SRS><Id>2</Id><Definition>{srs}</Definition></SRS></SpatialReferenceSystems>",
         "<Block><SRSId>2</SRSId><Photogroups><Photogroup><ImageDimensions><Width>640</Width>"
         "<Height>480</Height></ImageDimensions><FocalLength>12</FocalLength><SensorSize>12.8</SensorSize>"
         "<CameraOrientation>XRightYDown</CameraOrientation>"
         "<PrincipalPoint><x>320</x><y>240</y></PrincipalPoint>"]
    for i, (n, p) in enumerate(enu_poses.items()):
        m = "".join(f"<M_{a}{b}>{float(p.R[a, b])!r}</M_{a}{b}>" for a in range(3) for b in range(3))
        c = p.center
        L.append(f"<Photo><Id>{i}</Id><ImagePath>D:/cc/photos/{n}</ImagePath><Pose><Rotation>{m}</Rotation>"
                 f"<Center><x>{float(c[0])!r}</x><y>{float(c[1])!r}</y><z>{float(c[2])!r}</z></Center></Pose></Photo>")
    L.append("<Photo><Id>99</Id><ImagePath>x.jpg</ImagePath></Photo>")  # not oriented: skipped
    L.append("</Photogroup></Photogroups></Block></BlocksExchange>")
    (tmp_path / "enu.xml").write_text("".join(L))
    block = read_blocks_exchange(tmp_path / "enu.xml", FRAME)
    assert block.skipped == ["x.jpg"] and set(block.poses) == set(enu_poses)
    assert block.cameras["p0.jpg"].fx == pytest.approx(600.0)
    ground_enu = np.array([[x, y, 0.5] for x in (-60, 0, 60) for y in (-60, 0, 60)], float)
    ground_world = tr.points(ground_enu)
    worst = naive = 0.0
    for n, p in enu_poses.items():
        uv_a, fa = cam.project(p.transform(ground_enu))
        uv_b, fb = cam.project(block.poses[n].transform(ground_world))
        no_rot = Pose.from_center(p.R, block.poses[n].center)       # centre converted, rotation not
        uv_c, _ = cam.project(no_rot.transform(ground_world))
        ok = fa & fb & cam.in_image(uv_a)
        worst = max(worst, float(np.abs(uv_a[ok] - uv_b[ok]).max(initial=0)))
        naive = max(naive, float(np.abs(uv_a[ok] - uv_c[ok]).max(initial=0)))
    # what is left is the grid's scale factor (~1.2e-4 here; heights are not scaled in gtkit's frame)
    assert worst < 0.25, worst
    assert naive > 5.0, naive  # the meridian convergence the rotation correction removes


def _block_with(tmp_path, m_text, center="<x>1</x><y>2</y><z>3</z>"):
    xml = (f'<BlocksExchange><SpatialReferenceSystems><SRS><Id>0</Id><Definition>{FRAME_CRS}</Definition></SRS>'
           '</SpatialReferenceSystems><Block><SRSId>0</SRSId><Photogroups><Photogroup><ImageDimensions>'
           '<Width>100</Width><Height>80</Height></ImageDimensions><FocalLengthPixels>90</FocalLengthPixels>'
           f'<Photo><Id>0</Id><ImagePath>a.jpg</ImagePath><Pose><Rotation>{m_text}</Rotation><Center>{center}'
           '</Center></Pose></Photo></Photogroup></Photogroups></Block></BlocksExchange>')
    (tmp_path / "b.xml").write_text(xml)
    return tmp_path / "b.xml"


@pytest.mark.parametrize("M,msg", [(np.eye(3) * 1.1, "not orthonormal"), (np.diag([1.0, 1.0, -1.0]), "det"),
                                   (np.full((3, 3), np.nan), "NaN")])
def test_bad_rotations_are_clear_errors(tmp_path, M, msg):
    m = "".join(f"<M_{a}{b}>{float(M[a, b])!r}</M_{a}{b}>" for a in range(3) for b in range(3))
    path = _block_with(tmp_path, m)
    with pytest.raises(GtkitError, match=msg) as e:
        read_blocks_exchange(path, FRAME)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_bad_srs_and_k3(tmp_path):
    path = _block_with(tmp_path, "".join(f"<M_{a}{b}>{float(a == b)}</M_{a}{b}>" for a in range(3) for b in range(3)))
    path.write_text(path.read_text().replace(FRAME_CRS, "EPSG:4326"))
    with pytest.raises(GtkitError, match="geographic"):
        read_blocks_exchange(path, FRAME)
    path.write_text(path.read_text().replace("EPSG:4326", "ENU:95,1"))
    with pytest.raises(GtkitError, match="ENU origin out of range"):
        read_blocks_exchange(path, FRAME)
    path.write_text(path.read_text().replace("ENU:95,1", FRAME_CRS).replace(
        "<FocalLengthPixels>", "<Distortion><K1>0.1</K1><K3>0.01</K3></Distortion><FocalLengthPixels>"))
    with pytest.raises(GtkitError, match="K3"):
        read_blocks_exchange(path, FRAME)
    b = read_blocks_exchange(path, FRAME, drop_k3=True)
    assert b.cameras["a.jpg"].model == "OPENCV" and b.poses["a.jpg"].center == pytest.approx(
        np.array([1, 2, 3]) - np.array(FRAME_ORIGIN))
