"""The terms issue 48 adds to the joint BA's covariance (gtkit/sfm/register/real_photo_terms.py), each
on a constructed case where the answer is known."""
from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from gtkit.pose import Pose, skew
from gtkit.sfm.register.real_photo_terms import (SigmaSettings, _similarity_datum, feature_noise_px,
                                                 feature_side_of, reference_shape, residual_variance_factor)
from gtkit.sfm.register.uncertainty import with_centre_covariance


def _block(noise, n_images=9, n_points=1500, seed=0, width=1000, height=800, spacing=20.0):
    """Nadir photos (a 3 x 3 grid, 100 m up) over a field, their keypoints the true projections plus
    ``noise(xy, rng)``."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=width, height=height,
                                                    params=[800.0, 800.0, width / 2, height / 2], camera_id=1))
    X = np.column_stack([rng.uniform(-80, 80, n_points), rng.uniform(-65, 65, n_points), rng.normal(0, 1, n_points)])
    R = np.diag([1.0, -1.0, -1.0])   # looking down
    obs = {}
    for k in range(n_images):
        C = np.array([spacing * (k % 3 - 1), spacing * (k // 3 - 1), 100.0])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ C)
        xc = X @ R.T - R @ C
        uv = 800.0 * xc[:, :2] / xc[:, 2:] + [width / 2, height / 2]
        inside = np.flatnonzero((uv[:, 0] > 0) & (uv[:, 0] < width) & (uv[:, 1] > 0) & (uv[:, 1] < height))
        kp = uv[inside] + noise(uv[inside], rng)
        im = pycolmap.Image(name=f"reference/{k}.jpg", keypoints=kp, camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(im, pose)
        for j, p in enumerate(inside):
            obs.setdefault(int(p), []).append(pycolmap.TrackElement(k + 1, j))
    for p, els in obs.items():
        if len(els) >= 2:
            rec.add_point3D(X[p], pycolmap.Track(els))
    return rec


def test_the_residual_field_is_one_for_independent_1px_noise_and_grows_where_residuals_move_together():
    ind = _block(lambda uv, rng: rng.normal(0, 1.0, uv.shape))
    small = _block(lambda uv, rng: rng.normal(0, 0.3, uv.shape))
    # a pattern that moves every residual of an image cell together (as a lens / rolling-shutter
    # model error would), 0.3 px, on top of 0.3 px independent noise
    pattern = _block(lambda uv, rng: rng.normal(0, 0.3, uv.shape)
                     + 0.3 * np.column_stack([np.sin(uv[:, 0] / 200.0), np.cos(uv[:, 1] / 150.0)]))
    ids = list(ind.reg_image_ids())
    f_ind, f_small, f_pat = (residual_variance_factor(r, ids, SigmaSettings()) for r in (ind, small, pattern))
    # residuals at the true points: E = sigma^2 per axis for independent noise
    assert f_ind == pytest.approx(1.0, abs=0.25) and f_small == pytest.approx(0.09, abs=0.05)
    assert f_pat > 1.0 and f_pat > 10 * f_small, (f_pat, f_small)   # residuals 0.42 px, as `small`'s


def test_a_similarity_of_every_centre_is_removed_by_the_datum_and_a_bend_is_kept():
    rng = np.random.default_rng(1)
    C = rng.uniform(-100, 100, (12, 3))
    m = C.mean(0)
    # a covariance made only of a shift, a turn and a scale of all the centres
    A = np.vstack([np.hstack([np.eye(3), -skew(c - m), (c - m)[:, None]]) for c in C])
    G = rng.normal(size=(7, 7))
    S = A @ (G @ G.T) @ A.T
    assert np.abs(_similarity_datum(C, S)).max() < 1e-9 * np.abs(S).max()
    bend = np.zeros(3 * len(C))
    bend[2::3] = ((C[:, 0] - m[0]) / 100.0) ** 2     # heights bent along x
    Sb = np.outer(bend, bend)
    kept = _similarity_datum(C, Sb)
    assert np.trace(kept) > 0.2 * np.trace(Sb)


def test_the_reference_term_adds_its_centre_covariance_exactly():
    rng = np.random.default_rng(2)
    pose = Pose(Pose.from_center(np.eye(3), np.array([3.0, -2.0, 50.0])).R,
                Pose.from_center(np.eye(3), np.array([3.0, -2.0, 50.0])).t, np.diag(rng.uniform(1e-6, 1e-4, 6)))
    M = rng.normal(size=(3, 3)) * 0.01
    c_ref = M @ M.T
    out = with_centre_covariance(pose, c_ref)
    assert np.allclose(out.center_covariance(), pose.center_covariance() + c_ref)
    assert np.allclose(out.covariance[:3, :3], pose.covariance[:3, :3])   # rotations untouched


def test_the_reference_block_uncertainty_grows_with_its_noise(tmp_path):
    def shape(noise_px):
        d = tmp_path / f"n{noise_px}" / "model"
        d.mkdir(parents=True)
        _block(lambda uv, rng: rng.normal(0, noise_px, uv.shape)).write(str(d))
        return reference_shape(d)

    quiet, loud = shape(1.0), shape(3.0)
    assert quiet is not None and loud is not None and quiet.n_photos == 9
    # fitted residuals (tracks of 2-4 photos): 1-px noise reads about 0.6, below what scales anything
    assert 0.4 < quiet.field_factor < 1.0 and quiet.variance_factor == pytest.approx(1.0, abs=0.3)
    assert loud.field_factor == pytest.approx(9.0 * quiet.field_factor, rel=0.3)
    assert loud.variance_factor == pytest.approx(9.0, rel=0.3)
    q = np.median([np.trace(g) for g in quiet.ground.values()])
    lo = np.median([np.trace(g) for g in loud.ground.values()])
    assert q > 0 and lo == pytest.approx(loud.field_factor / max(1.0, quiet.field_factor) * q, rel=0.2)


def test_a_large_reference_block_is_cut_to_the_photos_the_queries_tie_to_and_their_neighbours(tmp_path):
    d = tmp_path / "model"
    d.mkdir()
    rec = _block(lambda uv, rng: rng.normal(0, 1.0, uv.shape), spacing=70.0)   # corner photos do not overlap
    rec.write(str(d))
    near = {rec.images[e.image_id].name for p in rec.images[1].points2D if p.has_point3D()
            for e in rec.points3D[p.point3D_id].track.elements}
    assert 3 <= len(near) < 9
    cut = reference_shape(d, {"reference/0.jpg"}, SigmaSettings(max_photos=3))
    assert cut is not None and set(cut.ground) == near and cut.variance_factor is None   # (a part: no sigma0)


def test_one_pixel_of_the_features_in_the_photo_s_pixels(tmp_path):
    """Features found on the photo shrunk to ``[sfm] features.max_image_size``: their 1 px is long side /
    that size in the photo's pixels (the full-size sample: the reference block's covariance at 1 photo
    px put its cameras 0.004 m from where they are, they were 0.014 m off the truth)."""
    import json

    cam = pycolmap.Camera(model="PINHOLE", width=6000, height=4000, params=[5000.0, 5000.0, 3000.0, 2000.0])
    assert feature_noise_px(cam, 1600) == pytest.approx(3.75)
    assert feature_noise_px(cam, 8000) == 1.0 and feature_noise_px(cam, None) == 1.0
    (tmp_path / "stage.json").write_text(json.dumps({"settings": {"features": {"max_image_size": 1600}}}))
    assert feature_side_of(tmp_path) == 1600 and feature_side_of(tmp_path / "none") is None
    # the reference block's term: its 1-px covariance times (1000 / 500)^2 where the residuals are quieter
    d = tmp_path / "model"
    d.mkdir()
    _block(lambda uv, rng: rng.normal(0, 0.3, uv.shape)).write(str(d))
    one, shrunk = reference_shape(d), reference_shape(d, feature_side=500)
    assert one.field_factor < 1.0
    for n, g in one.ground.items():
        assert np.allclose(shrunk.ground[n], 4.0 * g)


def test_k2_of_centres_against_their_positions_measures_the_block_not_the_positions_stated_noise():
    """k^2 (issue 55): the residuals of a block's centres against their photos' positions after the
    best similarity, over the variance the block's covariance predicts for them. Positions off by
    sigma per axis where the block predicts that sigma read k^2 = 1; where the positions state that
    sigma as their accuracy, the residuals are theirs and k^2 reads 0 (nothing left for the block)."""
    from gtkit.sfm.register.real_photo_terms import position_misfit

    rng = np.random.default_rng(3)
    n, sig, s = 400, 0.01, 2.0
    C = rng.uniform(-50, 50, (n, 3))
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R = q * np.sign(np.linalg.det(q))
    G = s * C @ R.T + [500.0, 300.0, 20.0] + rng.normal(0, sig, (n, 3))
    pred = np.full(n, 3 * sig ** 2 / s ** 2)          # the block's units: G's metres / s
    k2, scatter, share = position_misfit(C, G, pred)
    assert k2 == pytest.approx(1.0, abs=0.1) and scatter == pytest.approx(1.54 * sig, rel=0.1) and share == 0.0
    k2, _, share = position_misfit(C, G, pred, np.full(n, sig))
    assert abs(k2) < 0.1 and share == pytest.approx(1.0, abs=0.1)
    # horizontal and vertical stated apart: (sig, sig) is the same; a vertical 2 x sig accounts for twice
    assert position_misfit(C, G, pred, np.full((n, 2), sig))[2] == pytest.approx(share)
    assert position_misfit(C, G, pred, np.tile([sig, 2 * sig], (n, 1)))[2] == pytest.approx(2.0 * share)
    k2, _, _ = position_misfit(C, G, pred / 4.0)      # a block claiming half its true sigma
    assert k2 == pytest.approx(4.0, rel=0.1)


def test_k2_from_few_photos_is_taken_at_its_upper_bound_and_the_pixel_no_finer_than_the_default():
    from gtkit.sfm.register.real_photo_terms import SIGMA_MIN_FEATURE_SIDE, k2_upper, sigma_side

    assert k2_upper(1.0, 5) > k2_upper(1.0, 7) > k2_upper(1.0, 30) > 1.0      # wide on few photos
    assert k2_upper(1.0, 5) == pytest.approx(1.91, abs=0.05) and k2_upper(1.0, 3000) < 1.03
    assert k2_upper(2.0, 7) == pytest.approx(2.0 * k2_upper(1.0, 7))
    assert SIGMA_MIN_FEATURE_SIDE == 1600
    assert sigma_side(3200) == 1600 and sigma_side(800) == 800 and sigma_side(None) is None


def _given(positions: dict, accuracy: dict | None = None):
    """``reference_shape``'s ``positions_of`` over fixed positions (and stated accuracy)."""
    return lambda names: (positions, accuracy)


def test_the_reference_term_takes_k2_only_where_the_positions_can_test_the_block(tmp_path):
    """The 9-photo block with 1-px keypoint noise against its photos' true centres: k^2 measured and
    applied (its upper bound, >= 1); the same centres with 1 m noise (GPS-like: too coarse to test a
    block's shape), or stating an accuracy that accounts for the residuals: not applied, with the
    reason, and the term as without positions."""
    d = tmp_path / "model"
    d.mkdir()
    rec = _block(lambda uv, rng: rng.normal(0, 1.0, uv.shape))
    rec.write(str(d))
    true = {im.name: np.asarray(im.projection_center(), float) for im in rec.images.values()}
    plain = reference_shape(d)
    exact = reference_shape(d, positions_of=_given(true))
    assert exact.k2_applied and exact.k2 is not None and exact.k2_n == 9 and exact.k2_factor >= 1.0
    for n, g in exact.ground.items():
        assert np.trace(g) == pytest.approx(exact.k2_factor * np.trace(plain.ground[n]), rel=1e-6)
    rng = np.random.default_rng(0)
    gps = reference_shape(d, positions_of=_given({n: c + rng.normal(0, 1.0, 3) for n, c in true.items()}))
    assert not gps.k2_applied and "scatter" in gps.k2_reason and gps.k2_factor == 1.0
    stated = reference_shape(d, positions_of=_given({n: c + rng.normal(0, 0.1, 3) for n, c in true.items()},
                                                    {n: 0.1 for n in true}))
    assert not stated.k2_applied and "stated accuracy" in stated.k2_reason
    for n, g in gps.ground.items():
        assert np.trace(g) == pytest.approx(np.trace(plain.ground[n]), rel=1e-6)


def test_a_large_reference_block_reads_no_positions(tmp_path, monkeypatch):
    """The positions are read through ``positions_of`` only for a block k^2 can test (fewer than
    K2_MAX_PHOTOS photos): the same k^2 as given directly; over it, never read, and the reason said."""
    from gtkit.sfm.register import real_photo_terms

    d = tmp_path / "model"
    d.mkdir()
    rec = _block(lambda uv, rng: rng.normal(0, 1.0, uv.shape))
    rec.write(str(d))
    true = {im.name: np.asarray(im.projection_center(), float) for im in rec.images.values()}
    asked = []

    def positions_of(names):
        asked.append(sorted(names))
        return {n: true[n] for n in names}, {}

    lazy = reference_shape(d, positions_of=positions_of)
    assert asked == [sorted(true)] and lazy.k2 == pytest.approx(reference_shape(d, positions_of=_given(true)).k2)
    monkeypatch.setattr(real_photo_terms, "K2_MAX_PHOTOS", 9)
    asked.clear()
    big = reference_shape(d, positions_of=positions_of)
    assert asked == [] and not big.k2_applied and big.k2_reason.startswith("9 photos in the block")
