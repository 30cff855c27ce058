"""Textures finer than the views can show are halved on load, and the views do not change."""
import numpy as np
import pytest

from gtkit.camera import Camera
from gtkit.io.mesh import Mesh, MeshPart
from gtkit.pose import Pose
from gtkit.render.renderer import Renderer
from gtkit.render.texture_detail import TextureDetail, coarsen, halvings, part_texel


def _ground(size_m=200.0, px=4096, top=0.0, seed=0):
    """A flat square of ``size_m`` at height ``top`` with a ``px`` texture of random blobs (all
    scales, like a photo), so every mipmap level differs from the next."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = np.zeros((px, px, 3), np.float32)
    for k in (4, 16, 64, 256):
        small = rng.uniform(0, 255, (px // k, px // k, 3)).astype(np.float32)
        tex += cv2.resize(small, (px, px), interpolation=cv2.INTER_LINEAR) / 4
    s = size_m / 2
    V = np.array([[-s, -s, top], [s, -s, top], [s, s, top], [-s, s, top]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    return MeshPart(V, F, uv=uv, texture=np.clip(tex, 0, 255).astype(np.uint8), name="ground")


def test_texel_size_and_halvings():
    p = _ground(200.0, 4096)
    assert part_texel(p) == pytest.approx(200.0 / 4096, rel=1e-6)
    assert halvings(0.05, 0.099, 4096) == 0 and halvings(0.05, 0.1, 4096) == 1 and halvings(0.05, 0.41, 4096) == 3
    assert halvings(0.05, 1e9, 64) == 6            # never below one texel a side
    cam = Camera.from_hfov(640, 480, 60.0)
    d = TextureDetail.for_views(cam, 100.0)
    f = cam.fx
    assert d.pixel_angle == pytest.approx(f / (f * f + 320 ** 2 + 240 ** 2))
    assert d.texel_limit(40.0) == pytest.approx(60.0 * d.pixel_angle)
    assert d.texel_limit(120.0) == 0.0             # a part above the lowest camera is never coarsened
    assert coarsen(_ground(200.0, 256, top=120.0), d).texture.shape == (256, 256, 3)


def test_coarsened_textures_render_the_same_views_with_a_sixteenth_of_the_texels():
    cam = Camera.from_hfov(640, 480, 60.0)
    full = _ground(100.0, 4096)                     # 2.4 cm texels, under views 100 m or more above
    detail = TextureDetail.for_views(cam, 100.0)
    small = coarsen(full, detail)
    # limit 100 m * cos^2 / f = 0.119 m: two halvings to 9.8 cm (19.5 cm would be over it)
    assert small.texture.shape == (1024, 1024, 3)
    diffs = []
    for z, pitch in ((100.0, -90.0), (100.0, -45.0), (120.0, -50.0), (130.0, -60.0)):
        pose = Pose.from_dji(30.0, pitch, 0.0, np.array([0.0, -20.0, z]))
        imgs = []
        for part in (full, small):
            r = Renderer(Mesh([part]), anisotropy=1.0)
            out = r.render(cam, pose)
            r.clear()
            imgs.append(out.rgb.astype(float))
        ok = imgs[0].sum(-1) > 0
        assert ok.mean() > 0.15
        diffs.append(np.abs(imgs[0] - imgs[1])[ok])
    d = np.concatenate(diffs)
    # measured: every pixel within 2 grey levels, mean 1.0 (the driver's mipmaps and the box filter
    # round differently: 0.375 after one halving); no texel detail is lost
    assert d.mean() < 1.5 and d.max() <= 3
