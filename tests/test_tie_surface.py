"""Automatic tie points are judged by the model in 3D, as a photo sees it (issue 55): kept on smooth
surface of any orientation (ground, a flat roof, a wall), off it at edges, on a bumpy canopy, in the
air; undecided (kept by the caller) where the model does not cover the disk around them."""
from __future__ import annotations

import numpy as np

from gtkit.camera import Camera
from gtkit.io.mesh import Mesh, MeshPart
from gtkit.pose import Pose
from gtkit.render.renderer import Renderer
from gtkit.sfm.tie_surface import SmoothSurfaceSettings, measure_in_view, plane_fit, smooth_verdict


def _grid(xs, ys, z):
    """A height field z(x, y) as triangles."""
    X, Y = np.meshgrid(xs, ys)
    v = np.c_[X.ravel(), Y.ravel(), z(X, Y).ravel()]
    nx = len(xs)
    f = []
    for j in range(len(ys) - 1):
        for i in range(nx - 1):
            a = j * nx + i
            f += [[a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]]
    return MeshPart(v, np.array(f))


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return MeshPart(v, f)


def test_plane_fit_any_orientation():
    rng = np.random.default_rng(0)
    P = np.c_[rng.uniform(-1, 1, 200), np.zeros(200), rng.uniform(-1, 1, 200)]   # a wall (y = 0)
    c, n, rms = plane_fit(P + rng.normal(0, 0.001, P.shape))
    assert abs(abs(n[1]) - 1) < 1e-3 and rms < 0.002


def test_ties_on_ground_roof_and_wall_kept_edges_canopy_and_air_dropped():
    # a 100 x 100 m field (sloping 5 %), a 12 m building of 20 x 20 m, a bumpy canopy 8 m across
    def field(X, Y):
        return 0.05 * X - 0.02 * Y

    def canopy(X, Y):
        return field(X, Y) + 6.0 + 1.5 * np.sin(X * 2.1) * np.cos(Y * 1.7)

    ground = _grid(np.linspace(-50, 50, 101), np.linspace(-50, 50, 101), field)
    trees = _grid(np.linspace(-34, -26, 33), np.linspace(22, 30, 33), canopy)
    house = _box([0.0, 0.0, -1.0], [20.0, 20.0, 12.0])
    r = Renderer()
    r.add_mesh(Mesh([ground, trees, house]))
    # an oblique reference photo from the south-west, 45 deg down, about 60 m from the building
    cam = Camera.from_hfov(1024, 768, 60.0)
    C = np.array([-30.0, -40.0, 55.0])
    look = np.array([5.0, 10.0, 3.0]) - C
    z = look / np.linalg.norm(look)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = Pose.from_center(np.vstack([x, y, z]), C)
    depth = r.render(cam, pose, with_rgb=False).depth
    r.release()
    pts = {   # (point, kept) for points the photo sees
        "field": ([-10.0, -20.0, field(-10, -20)], True),
        "flat roof, middle": ([10.0, 10.0, 12.0], True),
        "wall facing the camera (x = 0), middle": ([0.0, 8.0, 5.0], True),
        "wall facing the camera (y = 0), middle": ([12.0, 0.0, 6.0], True),
        "roof edge": ([0.0, 10.0, 12.0], False),
        "foot of the wall": ([0.0, 12.0, field(0, 12)], False),
        "canopy": ([-30.0, 26.0, canopy(-30, 26)], False),
        "1.5 m above the field": ([-15.0, -15.0, field(-15, -15) + 1.5], False),
    }
    s = SmoothSurfaceSettings()
    m = measure_in_view(depth, cam, pose, np.array([p for p, _ in pts.values()]), s.radius_px, s.min_valid)
    keep, decided = smooth_verdict(m, s)
    assert decided.all(), dict(zip(pts, decided))
    assert {k: bool(v) for k, v in zip(pts, keep)} == {k: want for k, (_, want) in pts.items()}
    # the disk's radius follows the photo's pixels: about 8 px at the point's depth
    for (p, _), (_, _, radius) in zip(pts.values(), m):
        d = float(pose.transform(np.array([p]))[0, 2])
        assert abs(radius - s.radius_px * d / cam.fx) < 1e-9
    # behind the camera, or off the drawing: undecided
    m2 = measure_in_view(depth, cam, pose, np.array([[-60.0, -80.0, 0.0], [300.0, 300.0, 0.0]]), s.radius_px)
    assert not smooth_verdict(m2, s)[1].any()
