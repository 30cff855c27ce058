"""The alignment measure on the small sample project: the reference model (a baked, decimated
photogrammetry-like mesh, not the true world) rendered at the TRUE pose lines up with the photo
to well under a pixel; a pose 1 m or 1 degree off is measurably misaligned.

Set GTKIT_SMALL_SAMPLE=DIR to use an already generated small sample instead of generating one."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gtkit.pose import Pose
from gtkit.project import Project
from gtkit.render.overlay import OverlayScene, alignment

MAX_SIDE = 768


@pytest.fixture(scope="module")
def sample_root(request):
    env = os.environ.get("GTKIT_SMALL_SAMPLE")
    return Path(env) if env else request.getfixturevalue("small_sample")


def _off(pose: Pose, metres=0.0, degrees=0.0) -> Pose:
    if degrees:
        return Pose.from_center(Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 1.0, 0.0])).as_matrix() @ pose.R,
                                pose.center)
    return Pose.from_center(pose.R, pose.center + np.array([metres, 0.0, 0.0]))


def test_alignment_on_the_sample_true_pose_vs_1m_1deg(sample_root):
    proj = Project.load(sample_root)
    scene = OverlayScene(proj, sample_root / "truth" / "poses.txt")  # truth intrinsics beside it
    names = scene.images()
    picks = [next(n for n in names if n.endswith("_W.jpg")), next(n for n in names if n.endswith("_N.jpg"))]
    for name in picks:
        photo, _, _, s = scene.render(name, MAX_SIDE)
        pose = scene.poses[name]
        res = []
        for p in (pose, _off(pose, metres=1.0), _off(pose, degrees=1.0)):
            _, rgb, valid, _ = scene.render(name, MAX_SIDE, pose=p)
            res.append(alignment(photo, rgb, valid, scale=s))
        true, off_m, off_deg = res
        print(name, [round(a.misalignment_px, 2) for a in res], [round(a.edge_distance_px, 2) for a in res])
        assert true.n_tiles >= 20
        assert true.misalignment_px < 1.0                       # aligned: well under a pixel
        assert off_m.misalignment_px > max(1.5, 3 * true.misalignment_px)
        assert off_deg.misalignment_px > max(4.0, 5 * true.misalignment_px)
        if name.endswith("_N.jpg"):  # nadir reference: edges are the model's own texture edges
            assert off_deg.edge_distance_px > true.edge_distance_px + 1.0
