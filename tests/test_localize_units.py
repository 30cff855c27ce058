"""Unit tests of the localization parts on synthetic data with known answers."""
from __future__ import annotations

import numpy as np
import pytest

from gtkit.camera import Camera
from gtkit.conventions import angle_between_deg, dji_to_rotation, gravity_in_camera, index_to_pixel
from gtkit.localize.grid import grid_positions, make_views
from gtkit.localize.lift import lift, sample_depth
from gtkit.localize.pnp import PnPSettings, gravity_pnp_ransac
from gtkit.localize.localize import rank_candidates
from gtkit.localize.prior import footprint_filter, gps_filter, look_at_points, predicted_overlap, rotation_filter
from gtkit.pose import Pose

CAM = Camera.pinhole(800, 600, 700.0)


def _project(pose, X):
    uv, front = CAM.project(pose.transform(X))
    return uv, front


def _scene(rng, n):
    return np.c_[rng.uniform(-80, 80, n), rng.uniform(-60, 60, n), rng.uniform(0, 15, n)]


def test_p3p_ransac_recovers_pose_with_outliers_and_gravity():
    rng = np.random.default_rng(0)
    truth = Pose.from_dji(30.0, -60.0, 2.0, [10.0, -90.0, 120.0])
    X = _scene(rng, 400)
    uv, front = _project(truth, X)
    keep = front & CAM.in_image(uv)
    X, uv = X[keep], uv[keep] + rng.normal(0, 0.5, (keep.sum(), 2))
    out = rng.random(len(uv)) < 0.5
    uv[out] = rng.uniform([0, 0], [800, 600], (out.sum(), 2))
    g = gravity_in_camera(dji_to_rotation(33.0, -60.3, 2.2))  # IMU prior: yaw is irrelevant to gravity
    r = gravity_pnp_ransac(uv, X, CAM, g, PnPSettings())
    assert r.ok, r.reason
    dp, dr = r.pose.error_to(truth)
    assert dp < 0.3 and dr < 0.1
    assert r.n_rejected_gravity > 0 and r.gravity_err_deg < 2.0
    assert abs(r.n_inliers - (~out).sum()) < 0.05 * len(uv)


def test_gravity_check_beats_a_wrong_but_popular_hypothesis():
    """55% of the matches support a pose whose gravity is 8 deg off the IMU; 45% the true one."""
    rng = np.random.default_rng(1)
    truth = Pose.from_dji(0.0, -70.0, 0.0, [0.0, -40.0, 110.0])
    wrong = Pose.from_dji(5.0, -62.0, 0.0, [3.0, -60.0, 105.0])
    Xa, Xb = _scene(rng, 200), _scene(rng, 250)
    ua, fa = _project(truth, Xa)
    ub, fb = _project(wrong, Xb)
    X = np.r_[Xa[fa], Xb[fb]]
    uv = np.r_[ua[fa], ub[fb]] + rng.normal(0, 0.3, (fa.sum() + fb.sum(), 2))
    g = gravity_in_camera(truth.R)
    plain = gravity_pnp_ransac(uv, X, CAM, g, PnPSettings(gravity_deg=None))
    guided = gravity_pnp_ransac(uv, X, CAM, g, PnPSettings())
    assert plain.ok and plain.pose.error_to(wrong)[0] < 0.5          # the majority wins without gravity
    assert guided.ok and guided.pose.error_to(truth)[0] < 0.3        # gravity picks the true pose
    assert guided.pose.error_to(truth)[1] < 0.1


def test_prior_60_deg_off_is_a_failure_with_reason():
    rng = np.random.default_rng(2)
    truth = Pose.from_dji(0.0, -80.0, 0.0, [0.0, 0.0, 120.0])
    X = _scene(rng, 200)
    uv, f = _project(truth, X)
    g = gravity_in_camera(dji_to_rotation(0.0, -20.0, 0.0))
    r = gravity_pnp_ransac(uv[f], X[f], CAM, g, PnPSettings())
    assert not r.ok and r.pose is None
    assert "gravity" in r.reason and r.n_rejected_gravity > 0.99 * r.n_hypotheses


def test_too_few_matches_is_a_failure():
    r = gravity_pnp_ransac(np.zeros((5, 2)), np.zeros((5, 3)), CAM, None, PnPSettings())
    assert not r.ok and "too few" in r.reason


def test_lifting_bilinear_exact_on_a_plane_and_rejects_edges_and_background():
    cam = Camera.pinhole(64, 48, 50.0)
    pose = Pose.from_dji(0.0, -90.0, 0.0, [0.0, 0.0, 100.0])  # nadir over a plane z = 0
    depth = np.full((48, 64), 100.0, np.float32)
    depth[:, 40:] = 80.0       # a 20 m step (a roof) from column 40 on
    depth[:5, :5] = np.nan     # background in the top-left corner
    uv = np.array([[10.3, 20.7], [0.5, 30.5], [5.2, 5.2], [39.9, 20.0], [50.0, 30.0], [4.6, 3.0]])
    X, ok = lift(uv, depth, cam, pose)
    assert ok.tolist() == [True, True, False, False, True, False]
    # the lifted points of valid pixels are exact: they reproject onto themselves at the right depth
    back, _ = cam.project(pose.transform(X[ok]))
    assert np.abs(back - uv[ok]).max() < 1e-9
    assert np.allclose(X[[0, 1], 2], 0.0) and np.isclose(X[4, 2], 20.0)
    # pixel convention: the centre of array element (0, 0) is pixel (0.5, 0.5)
    d, ok2 = sample_depth(np.arange(12, dtype=np.float32).reshape(3, 4) + 1000, index_to_pixel(np.array([[1.0, 1.0], [1.5, 1.0]])))
    assert ok2.all() and np.allclose(d, [1005.0, 1005.5])


def test_rotation_prior_filter_wraps_angles():
    views = np.array([[179.0, -45.0, 0.0], [-179.0, -45.0, 0.0], [120.0, -45.0, 0.0],
                      [179.0, -90.0, 0.0], [-146.0, -45.0, 0.0]])
    m = rotation_filter([-178.0, -40.0, 0.0], views, 30.0)
    assert m.tolist() == [True, True, False, False, False]
    assert gps_filter([0, 0], np.array([[10.0, 0, 0], [0, 60.0, 0]]), 50.0).tolist() == [True, False]


def test_grid_views_and_dji_mapping():
    views = make_views((0.0, 0.0, 100.0, 100.0), 5.0, (100.0, 150.0), (50.0, 75.0), (0.0, 45.0), 45.0)
    assert len(grid_positions(0, 0, 100, 100, 50)) == 9 and len(grid_positions(0, 0, 100, 100, 75)) == 4
    assert len(views) == (9 + 4) * 16 and len({v.name for v in views}) == len(views)
    down = np.array([0.0, 0.0, -1.0])
    for v in views[:16]:
        assert v.center[2] == 105.0
        axis = v.pose().R[2]  # optical axis in world coordinates
        assert angle_between_deg(axis, down) == pytest.approx(v.paper_pitch, abs=1e-6)
    oblique = [v for v in views if v.paper_pitch == 45.0 and v.yaw == 90.0][0]
    assert oblique.pitch == -45.0 and oblique.pose().R[2][0] > 0.7   # yaw 90 looks east


def test_vlad_ranks_the_same_place_first():
    from gtkit.localize.descriptors import Vlad

    rng = np.random.default_rng(3)
    places = [rng.integers(0, 60, (300, 128)).astype(np.uint8) for _ in range(5)]
    vlad = Vlad.train(np.concatenate(places), k=16)
    G = np.stack([vlad.describe(p) for p in places])
    for i, p in enumerate(places):
        q = vlad.describe(p[rng.choice(300, 200, replace=False)])  # a partial view of place i
        assert int(np.argmax(G @ q)) == i


def test_vlad_of_many_images_at_once_is_the_vlad_of_each():
    """The database's global descriptors are computed in batches (one matrix product, residuals summed
    with reduceat): they equal the textbook per-image VLAD (np.add.at of residuals, float64)."""
    from gtkit.localize.descriptors import Vlad
    from gtkit.localize.features import unit_descriptors

    rng = np.random.default_rng(5)
    words = rng.integers(0, 120, (16, 128))          # descriptors near 16 words: no near-ties in the assignment
    images = [np.clip(words[rng.integers(0, 16, n)] + rng.integers(-8, 9, (n, 128)), 0, 255).astype(np.uint8)
              for n in (300, 0, 1, 7, 250)]
    vlad = Vlad.train(np.concatenate(images), k=16)

    def textbook(desc):
        v = np.zeros(vlad.centers.shape)
        if len(desc):
            x, c = unit_descriptors(desc).astype(np.float64), vlad.centers.astype(np.float64)
            a = ((x[:, None] - c[None]) ** 2).sum(-1).argmin(1)
            np.add.at(v, a, x - c[a])
        n = np.linalg.norm(v, axis=1, keepdims=True)
        v = np.sign(v) * np.sqrt(np.abs(np.where(n > 0, v / np.maximum(n, 1e-12), 0)))
        return v.ravel() / max(np.linalg.norm(v), 1e-12)

    G = vlad.describe_many(images, batch_rows=400)   # several batches, an image never split
    assert G.shape == (5, vlad.dim) and G.dtype == np.float32
    for g, im in zip(G, images):
        np.testing.assert_allclose(g, textbook(im), atol=1e-4)   # float32 vs float64 (signed sqrt near 0)
        np.testing.assert_array_equal(g, vlad.describe(im))
    assert not G[1].any()                              # no descriptors: the zero vector


def test_look_at_points_meet_the_ground_where_the_axis_does():
    ground = 19.0
    # an oblique query 62 m above ground, DJI pitch -33, yaw -135 (looking south-west)
    q = Pose.from_dji(-135.0, -33.0, 0.0, [5.0, 110.0, ground + 62.0])
    nadir = Pose.from_dji(40.0, -90.0, 0.0, [-20.0, 30.0, ground + 100.0])
    up = Pose.from_dji(90.0, 10.0, 0.0, [0.0, 0.0, ground + 50.0])  # above the horizon: capped
    C = np.array([q.center, nadir.center, up.center])
    A = np.array([q.R[2], nadir.R[2], up.R[2]])
    la = look_at_points(C, A, ground, max_dist=300.0)
    d = 62.0 / np.tan(np.radians(33.0))
    expect_q = np.array([5.0, 110.0]) + d * np.array([np.sin(np.radians(-135.0)), np.cos(np.radians(-135.0))])
    assert np.allclose(la[0], expect_q, atol=1e-6)
    assert np.allclose(la[1], [-20.0, 30.0], atol=1e-6)
    assert np.allclose(la[2], [300.0, 0.0], atol=1e-6)  # yaw 90 = east, 300 m ahead
    # the ray through the look-at point really lies on the axis (check in 3D)
    X = np.r_[la[0], ground]
    assert CAM.project(q.transform(X[None]))[0][0] == pytest.approx([400.0, 300.0], abs=1e-6)


def test_footprint_prior_pairs_a_low_oblique_query_with_a_high_view_of_the_same_ground():
    ground = 0.0
    target = np.array([0.0, 0.0])
    # query 60 m up, pitch -33, looking north at the target; database views 100 m up, pitch -45
    dq = 60.0 / np.tan(np.radians(33.0))
    q = Pose.from_dji(0.0, -33.0, 0.0, [0.0, -dq, 60.0])
    same = Pose.from_dji(0.0, -45.0, 0.0, [0.0, -100.0, 100.0])       # looks at the target
    above = Pose.from_dji(0.0, -90.0, 0.0, [0.0, -dq, 100.0])         # nadir, right above the query
    la_q = look_at_points(q.center[None], q.R[2][None], ground)[0]
    assert np.allclose(la_q, target, atol=1e-6)
    V = np.array([same.center, above.center])
    la_v = look_at_points(V, np.array([same.R[2], above.R[2]]), ground)
    assert footprint_filter(la_q, la_v, 30.0).tolist() == [True, False]
    # a camera-centre radius keeps the wrong one (right above the query) and drops the right one
    # (7.6 m away) -- the point of comparing where the cameras look
    assert gps_filter(q.center[:2], V, 5.0).tolist() == [False, True]


def test_predicted_overlap_is_the_share_of_the_prior_ground_a_view_sees():
    # nadir query 100 m over flat ground (footprint 200 m x 150 m); views 100 m up, nadir, shifted east
    cam = Camera.pinhole(800, 600, 400.0)
    q = Pose.from_dji(0.0, -90.0, 0.0, [0.0, 0.0, 100.0])
    shifts = [0.0, 50.0, 100.0, 150.0, 250.0]
    views = [Pose.from_dji(0.0, -90.0, 0.0, [dx, 0.0, 100.0]) for dx in shifts]
    VR, Vt = np.array([v.R for v in views]), np.array([v.t for v in views])
    ov = predicted_overlap(q.center, q.R, cam, VR, Vt, cam, 0.0, grid=(40, 30))
    # the shifted footprint keeps (200 - dx) / 200 of the query's ground
    assert np.allclose(ov, [1.0, 0.75, 0.5, 0.25, 0.0], atol=0.03)
    # an oblique 60 m query and a 45 deg view of the same ground overlap more than the nadir view
    # right above the query (where the look-at rule and the camera-centre rule disagree)
    dq = 60.0 / np.tan(np.radians(33.0))
    qo = Pose.from_dji(0.0, -33.0, 0.0, [0.0, -dq, 60.0])
    same = Pose.from_dji(0.0, -45.0, 0.0, [0.0, -100.0, 100.0])
    above = Pose.from_dji(0.0, -90.0, 0.0, [0.0, -dq, 100.0])
    o = predicted_overlap(qo.center, qo.R, cam, np.array([same.R, above.R]), np.array([same.t, above.t]), cam, 0.0)
    assert o[0] > 0.95 and o[1] < 0.6
    # a camera that sees no ground (looking up) predicts nothing
    up = Pose.from_dji(0.0, 30.0, 0.0, [0.0, 0.0, 100.0])
    assert predicted_overlap(up.center, up.R, cam, VR, Vt, cam, 0.0).tolist() == [0.0] * 5


def test_predicted_overlap_counts_only_ground_seen_from_a_similar_direction():
    """With ``angle_deg`` a view that sees the query's ground from far off the query's direction counts
    less: the medium sample's failures (views of the same ground 23-34 deg away won the plain overlap)."""
    cam = Camera.pinhole(800, 600, 400.0)
    # a query 45 deg below the horizon, 150 m up, looking north at the ground ~150 m ahead
    q = Pose.from_dji(0.0, -45.0, 0.0, [0.0, -150.0, 150.0])
    same = Pose.from_dji(0.0, -45.0, 0.0, [0.0, -160.0, 160.0])      # the same direction, 10 m further
    # a 70-deg-off-nadir view 350 m back, its axis on the query's look-at point: the ground seen 25 deg off
    d = 150.0 / np.tan(np.radians(20.0))
    far = Pose.from_dji(0.0, -20.0, 0.0, [0.0, -d, 150.0])
    VR, Vt = np.array([same.R, far.R]), np.array([same.t, far.t])
    plain = predicted_overlap(q.center, q.R, cam, VR, Vt, cam, 0.0)
    weighted = predicted_overlap(q.center, q.R, cam, VR, Vt, cam, 0.0, angle_deg=(15.0, 35.0))
    assert plain[1] > 0.9 and plain[0] > 0.9                  # both see the query's ground
    assert weighted[0] > 0.9 * plain[0]                       # the same direction keeps its overlap
    assert weighted[1] < 0.6 * plain[1] and weighted[1] < weighted[0] - 0.3
    # beyond the second angle nothing counts; within the first everything does
    assert predicted_overlap(q.center, q.R, cam, VR, Vt, cam, 0.0, angle_deg=(0.1, 0.2))[1] == 0.0
    assert np.allclose(predicted_overlap(q.center, q.R, cam, VR, Vt, cam, 0.0, angle_deg=(89.0, 90.0)), plain)


def test_rank_candidates_puts_the_position_prior_first_and_fills_up():
    score = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    keep = np.array([True, True, False, True, True, True])
    near = np.array([False, False, True, True, False, True])
    assert rank_candidates(score, keep, None, 4).tolist() == [0, 1, 3, 4]
    assert rank_candidates(score, keep, near, 4).tolist() == [3, 5, 0, 1]  # index 2 fails keep
    assert rank_candidates(score, keep, near, 10).tolist() == [3, 5, 0, 1, 4]
    assert rank_candidates(score, np.zeros(6, bool), near, 3).tolist() == []


def test_pose_covariance_matches_the_scatter_of_noisy_solutions():
    """With independent pixel noise (what the first-order formula assumes, inflation 1) the squared
    Mahalanobis norm of the 6-dof error of each solution follows a chi-square with 6 dof."""
    from scipy.spatial.transform import Rotation
    from scipy.stats import chi2

    rng = np.random.default_rng(3)
    truth = Pose.from_dji(-20.0, -45.0, 0.0, [30.0, -150.0, 110.0])
    X = _scene(rng, 300)
    uv0, front = _project(truth, X)
    keep = front & CAM.in_image(uv0)
    X, uv0 = X[keep], uv0[keep]
    m2, sig = [], []
    for _ in range(120):
        r = gravity_pnp_ransac(uv0 + rng.normal(0, 1.0, uv0.shape), X, CAM, None,
                               PnPSettings(covariance_inflation=1.0, min_iterations=20))
        assert r.ok and r.pose.covariance is not None
        dr = Rotation.from_matrix(truth.R @ r.pose.R.T).as_rotvec()   # truth = exp(dr) estimate
        x = np.r_[dr, truth.t - r.pose.t]
        m2.append(x @ np.linalg.solve(r.pose.covariance, x))
        sig.append(np.degrees(np.sqrt(np.trace(r.pose.covariance[:3, :3]))))
    med = float(np.median(m2))
    assert 0.7 * chi2.median(6) < med < 1.4 * chi2.median(6), med
    assert 0.85 < np.mean(np.array(m2) < chi2.ppf(0.95, 6)) <= 1.0
    assert 0.0 < np.median(sig) < 0.1   # sub-0.1 deg from 1 px noise on ~260 points


def test_sift_keypoints_are_unbiased_in_the_gtkit_pixel_convention():
    """An image and its 180-degree rotation (no resampling): a point p maps to (W, H) - p, so
    detections p + b and (W, H) - p + b reveal the bias b of the extractor."""
    import cv2
    from scipy.spatial import cKDTree

    from gtkit.localize.features import SiftExtractor

    rng = np.random.default_rng(0)
    img = cv2.resize((rng.random((120, 160, 3)) * 255).astype(np.uint8), (640, 480), interpolation=cv2.INTER_CUBIC)
    ex = SiftExtractor(max_keypoints=2000, max_side=1024)
    a, b = ex.extract(img), ex.extract(img[::-1, ::-1].copy())
    back = np.array([640.0, 480.0]) - b.kp
    d, j = cKDTree(back).query(a.kp)
    m = d < 0.8
    assert m.sum() > 300
    bias = np.median(a.kp[m] - back[j[m]], axis=0) / 2
    assert np.all(np.abs(bias) < 0.02), bias


def test_center_covariance_matches_sampled_centres():
    """Pose.center_covariance (first order) against centres of poses drawn from the covariance."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-6 + np.diag([1e-6] * 3 + [1e-2] * 3)
    p = Pose(Pose.from_dji(40.0, -50.0, 1.0, [100.0, -200.0, 150.0]).R,
             Pose.from_dji(40.0, -50.0, 1.0, [100.0, -200.0, 150.0]).t, covariance=cov)
    d = rng.multivariate_normal(np.zeros(6), cov, 20000)
    C = np.array([Pose(Rotation.from_rotvec(x[:3]).as_matrix() @ p.R, p.t + x[3:]).center for x in d])
    emp = np.cov(C.T)
    assert np.allclose(p.center_covariance(), emp, rtol=0.05, atol=0.02 * np.abs(emp).max())


def test_depth_files_round_trip_compactly_and_old_layouts_still_read(tmp_path):
    """A database view's depth: uint16 steps of the view's largest depth / 65535, each row
    differenced modulo 2**16 and deflated; background stays NaN; the earlier 'depth_q' layout reads."""
    from gtkit.localize.database import _existing_fraction, read_depth, write_depth

    yy, xx = np.mgrid[0:480, 0:640]
    depth = (120.0 + 0.05 * xx + 0.1 * yy + 8.0 * ((xx // 80 + yy // 60) % 2)).astype(np.float32)
    depth[:40] = np.nan                                   # sky
    write_depth(tmp_path / "v.npz", depth, 0.92)
    back = read_depth(tmp_path / "v.npz")
    step = np.nanmax(depth) / 65535
    assert np.array_equal(np.isnan(back), np.isnan(depth))
    assert np.nanmax(np.abs(back - depth)) <= step / 2 + 1e-4
    assert (tmp_path / "v.npz").stat().st_size < depth.size * 2 / 4        # under a quarter of raw uint16
    assert _existing_fraction(tmp_path / "v.npz") == pytest.approx(0.92)
    write_depth(tmp_path / "dropped.npz", None, 0.1)
    assert read_depth(tmp_path / "dropped.npz") is None and _existing_fraction(tmp_path / "dropped.npz") == 0.1
    q = np.where(np.isnan(depth), 0, np.rint(np.nan_to_num(depth) / step)).astype(np.uint16)
    np.savez_compressed(tmp_path / "old.npz", depth_q=q, depth_scale=np.float64(step), valid_fraction=0.92)
    old = read_depth(tmp_path / "old.npz")
    assert np.array_equal(np.isnan(old), np.isnan(depth)) and np.nanmax(np.abs(old - back)) <= step * 1.01


def test_feature_file_view_list_is_kept_beside_it_and_used_only_while_it_matches(tmp_path):
    """Listing a feature file's views visits every group (1 ms a view): the list is kept beside the
    file, and a list that no longer describes the file (replaced, or written by a run killed between
    the two) is not trusted."""
    import json

    from gtkit.localize import feature_store
    from gtkit.localize.features import Features

    rng = np.random.default_rng(0)

    def feats(n):
        return {f"r{i // 4}/v{i}": Features(rng.random((5, 2)), rng.integers(0, 255, (5, 128), dtype=np.uint8), (64, 48))
                for i in range(n, n + 8)}

    path = tmp_path / "features.h5"
    feature_store.write_part(path, feats(0))
    feature_store.write_part(path, feats(8))
    feature_store.merge_parts(path)
    index = feature_store.views_index(path)
    assert set(json.loads(index.read_text())["views"]) == set(feats(0)) | set(feats(8))
    assert feature_store.stored_views(path) == set(feats(0)) | set(feats(8))
    # the list is what is read: a view listed but not in the file shows it was used, not the file
    rec = json.loads(index.read_text())
    index.write_text(json.dumps({**rec, "views": rec["views"] + ["listed/only"]}))
    assert "listed/only" in feature_store.stored_views(path)
    index.write_text(json.dumps(rec))
    # the file grown by a later run: the list follows it
    feature_store.write_part(path, feats(16))
    feature_store.merge_parts(path)
    assert feature_store.stored_views(path) == set(feats(0)) | set(feats(8)) | set(feats(16))
    # a list stamped for another file is ignored, the file scanned and the list rewritten
    index.write_text(json.dumps({"stamp": [1, 2, 3], "views": ["stale"]}))
    assert feature_store.stored_views(path) == set(feats(0)) | set(feats(8)) | set(feats(16))
    assert "stale" not in json.loads(index.read_text())["views"]
    index.write_text("{not json")
    assert len(feature_store.stored_views(path)) == 24


def test_imu_off_by_7_deg_relaxed_gate_keeps_a_strongly_supported_pose_only():
    """The IMU as the outlier (small seed 23, seq2/0003_W: gimbal pitch 5.65 deg off, its true pose
    refused in every round): a pose 7 deg from the IMU's gravity is kept when most matches agree on
    it, and refused, with what the retry found, when only a few do."""
    rng = np.random.default_rng(3)
    truth = Pose.from_dji(20.0, -40.0, 0.0, [0.0, -120.0, 100.0])
    X = _scene(rng, 500)
    uv, f = _project(truth, X)
    f &= CAM.in_image(uv)
    X, uv = X[f], uv[f] + rng.normal(0, 0.5, (f.sum(), 2))
    g = gravity_in_camera(dji_to_rotation(20.0, -33.0, 0.0))          # 7 deg off in pitch
    strict = gravity_pnp_ransac(uv, X, CAM, g, PnPSettings(gravity_relaxed_deg=None))
    assert not strict.ok and "gravity" in strict.reason
    r = gravity_pnp_ransac(uv, X, CAM, g, PnPSettings())
    assert r.ok and r.gravity_relaxed and r.summary()["gravity_relaxed"], r.reason
    dp, dr = r.pose.error_to(truth)
    assert dp < 0.3 and dr < 0.1 and 6.0 < r.gravity_err_deg < 8.0
    out = np.ones(len(uv), bool)
    out[:60] = False
    uv_w = uv.copy()
    uv_w[out] = rng.uniform([0, 0], [800, 600], (out.sum(), 2))       # 60 true matches of ~400
    w = gravity_pnp_ransac(uv_w, X, CAM, g, PnPSettings())
    assert not w.ok and "with the gravity gate at 15 deg" in w.reason, w.reason
