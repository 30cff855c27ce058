"""The query photos co-estimated with a small reference block (gtkit.sfm.register.coestimate): where it
applies, and how a co-estimated pose carries its sigma. Measured against the surveyed truth end to end in
tests/test_real_truth.py (fountain-P11, every run) and docs/benchmarks.md (stop 64)."""
from __future__ import annotations

import numpy as np
import pycolmap

from gtkit.pose import Pose
from gtkit.sfm.register.coestimate import carry_over, why_not
from gtkit.sfm.register.settings import CoestimateSettings


def _block(n_photos: int) -> pycolmap.Reconstruction:
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=3072, height=2048, params=[2760.0, 1536.0, 1024.0, 0.0],
                          camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    for i in range(n_photos):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"reference/{i:04d}.jpg", camera_id=1, image_id=i + 1),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([float(i), 0.0, 0.0])))
    return rec


def test_only_a_small_block_held_by_its_positions_is_coestimated():
    held = {"applied": True, "sigma_h_m": 0.005, "sigma_v_m": 0.005}
    on = CoestimateSettings()
    assert why_not(_block(7), held, on) is None
    assert why_not(_block(41), held, on) == "41 photos in the reference block (co-estimated up to 40)"
    assert "not held by its positions" in why_not(_block(7), {"applied": False, "reason": "GCPs only"}, on)
    assert "not held by its positions" in why_not(_block(7), None, on)
    assert why_not(_block(7), held, CoestimateSettings(enabled=False)) == "off ([register.coestimate] enabled = false)"


def test_a_coestimated_pose_carries_its_joint_sigma_and_its_move():
    rng = np.random.default_rng(4)
    joint = Pose.from_center(np.eye(3), np.array([3.0, -2.0, 50.0]))
    joint = Pose(joint.R, joint.t, np.diag(rng.uniform(1e-6, 1e-4, 6)))
    turn = pycolmap.Rotation3d(np.array([0.0, 0.002, 0.0, 1.0])).matrix()    # 0.23 deg about y
    moved = Pose.from_center(turn, joint.center + np.array([0.002, 0.0, -0.001]))
    covs, floors = {"q/a": joint.covariance}, {"q/a": 1e-5}
    per_image = {"q/a": {"sigma_pos_m": 0.01, "sigma_terms": {"ba_m": 0.01}}, "q/b": {}}
    out = carry_over({"q/a": joint, "q/b": Pose.identity()}, covs, per_image, floors,
                     {"q/a": moved, "q/b": Pose.from_center(np.eye(3), np.array([0.0, 0.0, 0.003]))})
    d = moved.center - joint.center
    assert np.allclose(out["q/a"].center, moved.center)
    # its centre covariance is the joint pose's plus the move, exactly (the covariance carried to the
    # new pose, not read at its new translation: 5e-6 m^2 apart here)
    assert np.allclose(out["q/a"].center_covariance(), joint.center_covariance() + np.outer(d, d), rtol=0, atol=1e-10)
    assert covs["q/a"] is out["q/a"].covariance and floors["q/a"] == 1e-5 + float(d @ d)
    assert per_image["q/a"]["coestimated_moved_m"] == per_image["q/a"]["sigma_terms"]["coestimation_m"] \
        == float(np.linalg.norm(d))
    assert per_image["q/a"]["sigma_pos_m"] == float(np.sqrt(np.trace(out["q/a"].center_covariance())))
    # a pose without a covariance moves and stays without one (unverified, as before)
    assert out["q/b"].covariance is None and per_image["q/b"]["coestimated_moved_m"] == 0.003


def test_a_pose_whose_sigma_exceeds_its_distance_to_the_scene_is_unverified():
    """tiny rtk-few seed 0 (8 reference photos): 7 photos were "registered" 185 m off with a median sigma
    of 1,453 m, 100 m above the ground; a pose with such a sigma says nothing about where it was taken."""
    from gtkit.sfm.register.uncertainty import unverify_uninformative

    per_image = {"q/far": {"sigma_pos_m": 1453.1, "scene_depth_m": 101.0},
                 "q/fine": {"sigma_pos_m": 0.08, "scene_depth_m": 60.0},
                 "q/none": {"unverified": "the final BA gave this photo no covariance", "scene_depth_m": 90.0},
                 "q/blind": {"sigma_pos_m": 5.0, "scene_depth_m": 0.0}}   # sees no point: not judged here
    assert unverify_uninformative(per_image) == ["q/far"]
    assert per_image["q/far"]["unverified"].startswith("its position sigma (1.45e+03 m) is larger than its distance")
    assert "unverified" not in per_image["q/fine"] and "unverified" not in per_image["q/blind"]
    assert per_image["q/none"]["unverified"] == "the final BA gave this photo no covariance"


def test_query_photos_join_the_reference_camera_only_where_its_calibration_stays_within_its_own_uncertainty():
    from gtkit.sfm.register.coestimate import _why_not_joined

    held = {"applied": True, "residual_median_m": {"before": 0.002, "after": 0.002}, "n_priors": 7}

    def check(d2):
        return {1: {"parts": ["focal", "principal point", "distortion"], "before": [2759.1, 1520.6, 1008.1, 0.0],
                    "after": [2773.6, 1489.4, 1058.8, 0.006], "d2": d2, "limit": 18.47}}
    assert _why_not_joined(held, check(7.1)) is None            # the 3-photo block's change (entry every 2nd)
    why = _why_not_joined(held, check(1262.1))                  # another camera of the same size (10 % zoom)
    assert "another camera of the same size" in why and "focal 2774 px" in why and "limit 18" in why, why
    assert "could not be computed" in _why_not_joined(held, check(None))
    assert "only 2 photos" in _why_not_joined({"applied": False, "reason": "only 2 photos with a usable position"},
                                              check(1.0))
    moved = {"applied": True, "residual_median_m": {"before": 0.002, "after": 1.456}}
    assert "moved the block off its positions" in _why_not_joined(moved, check(1.0))
