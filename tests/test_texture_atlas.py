"""A part's texture packed down to the charts its faces use renders the same views."""
import numpy as np

from gtkit.camera import Camera
from gtkit.io.mesh import Mesh, MeshPart
from gtkit.io.texture_atlas import charts, pack_charts
from gtkit.pose import Pose
from gtkit.render.renderer import Renderer


def _scattered_part(keep_share=0.08, n=48, px=1024, seed=0):
    """A 96 m square ground, a grid of n x n quads textured from one photo-like texture, of which a
    scattered ``keep_share`` of small patches is kept (as a photo textures the faces it sees best)."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = np.zeros((px, px, 3), np.float32)
    for k in (2, 8, 32):
        tex += cv2.resize(rng.uniform(0, 255, (px // k, px // k, 3)).astype(np.float32), (px, px)) / 3
    xs = np.linspace(-48, 48, n + 1)
    gx, gy = np.meshgrid(xs, xs)
    V = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    uv = np.stack([(gx.ravel() + 48) / 96, (gy.ravel() + 48) / 96], 1)
    F = []
    cells = rng.random((n, n)) < keep_share / 4
    cells |= np.roll(cells, 1, 0) | np.roll(cells, 1, 1) | np.roll(np.roll(cells, 1, 0), 1, 1)   # 2 x 2 patches
    for i in range(n):
        for j in range(n):
            if cells[i, j]:
                a = i * (n + 1) + j
                F += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    return MeshPart(V, np.array(F), uv=uv, texture=np.clip(tex, 0, 255).astype(np.uint8), name="p")


def test_charts_are_the_groups_of_faces_joined_by_vertices():
    lab = charts(np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7]]), 9)
    assert lab[0] == lab[4] != lab[5] == lab[7] and len(set(lab)) == 3   # vertex 8: a chart of its own


def test_packed_texture_is_a_fraction_and_renders_the_same():
    part = _scattered_part()
    packed = pack_charts(part)                     # margin 4, boxes aligned to 4 texels
    share = packed.texture.shape[0] * packed.texture.shape[1] / (1024 * 1024)
    assert share < 0.25, share                     # measured: 0.16 of the texels
    assert np.array_equal(packed.faces, part.faces) and np.array_equal(packed.vertices, part.vertices)
    cam = Camera.from_hfov(640, 480, 60.0)
    for z, pitch, worst, mean in ((40.0, -90.0, 1, 0.01), (60.0, -90.0, 1, 0.01), (90.0, -60.0, 255, 0.3)):
        pose = Pose.from_dji(20.0, pitch, 0.0, np.array([0.0, -5.0, z]))
        imgs = []
        for p in (part, packed):
            r = Renderer(Mesh([p]), anisotropy=1.0)
            imgs.append(r.render(cam, pose).rgb.astype(int))
            r.clear()
        drawn = imgs[0].sum(-1) > 0
        assert drawn.mean() > 0.02
        assert np.array_equal(drawn, imgs[1].sum(-1) > 0)
        d = np.abs(imgs[0] - imgs[1])[drawn]
        # measured: texture magnified or near 1:1 (levels 0-2), within 1 grey level; the oblique,
        # whose far side samples levels 3+ (chart borders mixed on the page), mean 0.1
        assert d.max() <= worst and d.mean() < mean, (z, pitch, d.max(), d.mean())
