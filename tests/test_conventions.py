"""The conventions module: DJI angles, rotations, quaternions, pixels."""
import numpy as np
import pytest

from gtkit.conventions import (angle_between_deg, dji_to_rotation, gravity_in_camera, index_to_pixel,
                               pixel_to_index, quat_to_rotmat, rotation_angle_deg, rotation_to_dji,
                               rotmat_to_quat, wrap_deg)
from gtkit.pose import Pose

E, N, U = np.eye(3)


def axes(R):
    """Camera x (right), y (down), z (forward) expressed in world coordinates."""
    return R[0], R[1], R[2]


def test_nadir_north_up():
    x, y, z = axes(dji_to_rotation(0, -90, 0))
    np.testing.assert_allclose(z, -U, atol=1e-12)   # looks straight down
    np.testing.assert_allclose(x, E, atol=1e-12)    # image right = east
    np.testing.assert_allclose(y, -N, atol=1e-12)   # image down = south: top of image is north


def test_horizon_north():
    x, y, z = axes(dji_to_rotation(0, 0, 0))
    np.testing.assert_allclose(z, N, atol=1e-12)
    np.testing.assert_allclose(x, E, atol=1e-12)
    np.testing.assert_allclose(y, -U, atol=1e-12)


def test_yaw_90_looks_east_clockwise_from_north():
    x, y, z = axes(dji_to_rotation(90, 0, 0))
    np.testing.assert_allclose(z, E, atol=1e-12)
    np.testing.assert_allclose(x, -N, atol=1e-12)


def test_pitch_minus_45_looks_down_forward():
    _, _, z = axes(dji_to_rotation(0, -45, 0))
    np.testing.assert_allclose(z, (N - U) / np.sqrt(2), atol=1e-12)


@pytest.mark.parametrize("yaw,pitch", [(0, 0), (37, -30), (-120, -90), (200, -60)])
def test_roll_is_about_the_optical_axis(yaw, pitch):
    """Roll must turn the image about the optical axis, never tilt the optical axis
    (a known bug elsewhere applies gimbal roll about the camera's x axis)."""
    R0 = dji_to_rotation(yaw, pitch, 0)
    R1 = dji_to_rotation(yaw, pitch, 12.5)
    np.testing.assert_allclose(R1[2], R0[2], atol=1e-12)          # same optical axis
    assert angle_between_deg(R1[0], R0[0]) == pytest.approx(12.5)  # image turned by the roll


def test_positive_roll_lowers_the_right_side():
    x, _, _ = axes(dji_to_rotation(0, 0, 10))
    assert x[2] < 0 and x[2] == pytest.approx(-np.sin(np.radians(10)))


def test_dji_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(200):
        yaw, pitch, roll = rng.uniform(-180, 180), rng.uniform(-89, 89), rng.uniform(-45, 45)
        got = rotation_to_dji(dji_to_rotation(yaw, pitch, roll))
        np.testing.assert_allclose(wrap_deg(np.array(got) - [yaw, pitch, roll]), 0, atol=1e-8)


def test_gravity_in_camera():
    np.testing.assert_allclose(gravity_in_camera(dji_to_rotation(33, -90, 0)), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(gravity_in_camera(dji_to_rotation(33, 0, 0)), [0, 1, 0], atol=1e-12)


def test_quaternion_round_trip_and_order():
    R = dji_to_rotation(10, -40, 3)
    q = rotmat_to_quat(R)
    assert q[0] >= 0 and np.isclose(np.linalg.norm(q), 1)
    np.testing.assert_allclose(quat_to_rotmat(q), R, atol=1e-12)
    # (qw, qx, qy, qz): 90 deg about z
    np.testing.assert_allclose(quat_to_rotmat([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]),
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_pose_is_world_to_camera():
    C = np.array([10.0, -5.0, 120.0])
    p = Pose.from_dji(0, -90, 0, C)
    np.testing.assert_allclose(p.center, C)
    # a ground point below and north of the camera is in front and in the upper image half
    Xc = p.transform(np.array([[10.0, 5.0, 0.0]]))[0]
    assert Xc[2] == pytest.approx(120.0) and Xc[1] < 0


def test_wrap_and_angles():
    assert wrap_deg(190.0) == pytest.approx(-170.0)
    assert wrap_deg(-180.0) == 180.0
    assert rotation_angle_deg(dji_to_rotation(0, 0, 0), dji_to_rotation(3, 0, 0)) == pytest.approx(3.0)


def test_pixel_convention():
    """COLMAP: the top-left pixel's centre is (0.5, 0.5); array index (0, 0)."""
    np.testing.assert_allclose(pixel_to_index([0.5, 0.5]), [0, 0])
    np.testing.assert_allclose(index_to_pixel([3, 7]), [3.5, 7.5])


def test_pycolmap_pose_covariance_is_converted_to_rotation_vectors():
    """pycolmap's BA covariance of one camera seeing fixed points, converted by Pose.from_pycolmap,
    equals gtkit's own first-order covariance (rotation vector, translation) of the same problem,
    up to the pixel variance each assumes."""
    import pycolmap

    from gtkit.localize.pnp import pose_covariance
    from gtkit.pose import Pose

    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    truth = Pose.from_dji(30.0, -50.0, 0.0, np.array([0.0, 0.0, 100.0]))
    other = Pose.from_dji(0.0, -90.0, 0.0, np.array([42.0, 73.0, 150.0]))   # nadir over the ground seen
    X = np.c_[rng.uniform(-40, 40, (400, 2)) + [42.0, 73.0], rng.uniform(-5, 5, 400)]

    def project(p):
        pc = X @ p.R.T + p.t
        return pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2], pc[:, 2]

    uv, z = project(truth)
    uv2, z2 = project(other)
    keep = (z > 0) & (z2 > 0) & np.all((uv > 0) & (uv < [640, 480]), axis=1) & np.all((uv2 > 0) & (uv2 < [640, 480]), axis=1)
    X, uv, uv2 = X[keep], uv[keep] + rng.normal(0, 1, (keep.sum(), 2)), uv2[keep]
    assert len(X) > 50
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=640, height=480,
                                                    params=[800, 800, 320, 240], camera_id=1))
    for iid, (p, kp) in enumerate(((truth, uv), (other, uv2)), start=1):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{iid}.jpg", keypoints=kp, camera_id=1, image_id=iid),
                                         p.to_pycolmap())
    for i, x in enumerate(X):
        rec.add_point3D(x, pycolmap.Track([pycolmap.TrackElement(1, i), pycolmap.TrackElement(2, i)]))
    cfg = pycolmap.BundleAdjustmentConfig()
    cfg.add_image(1)
    cfg.add_image(2)
    cfg.set_constant_rig_from_world_pose(rec.images[2].frame_id)
    cfg.set_constant_cam_intrinsics(1)
    for pid in rec.points3D:
        cfg.add_constant_point(pid)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
    ba.solve()
    cov = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), rec, ba)
    est = Pose.from_pycolmap(rec.images[1].cam_from_world(), cov.get_cam_cov_from_world(1))
    ours = pose_covariance(est.R, est.t, X, uv, K)
    scale = np.median(np.diag(est.covariance)[3:] / np.diag(ours)[3:])     # pixel variance: 1 vs the MAD's
    np.testing.assert_allclose(est.covariance, ours * scale, rtol=0.02, atol=1e-3 * np.abs(ours * scale).max())
    assert 0.7 < scale < 1.5
