"""The headless renderer against analytic geometry: depth, projection, ortho, mesh files."""
import numpy as np
import pytest

from gtkit.camera import Camera
from gtkit.io.mesh import Mesh, MeshPart, load_model, read_mesh_file, write_obj, write_offset_sidecar
from gtkit.pose import Pose
from gtkit.render.renderer import Renderer


def box(lo, hi, color):
    """Axis-aligned box as 12 triangles with one colour."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return MeshPart(v, f, colors=np.tile(np.asarray(color, np.uint8), (8, 1)))


def textured_ground(size=200.0, z=0.0, tex_px=1024, seed=0):
    s = size / 2
    v = np.array([[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    tex = np.random.default_rng(seed).integers(0, 255, (tex_px, tex_px, 3), dtype=np.uint8)
    return MeshPart(v, f, uv=uv, texture=tex)


def analytic_plane_depth(cam, pose, z_plane=0.0):
    ii, jj = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([jj + 0.5, ii + 0.5], -1).reshape(-1, 2)
    d_world = cam.rays(uv) @ pose.R
    C = pose.center
    s = (z_plane - C[2]) / d_world[:, 2]
    X = C + s[:, None] * d_world
    return pose.transform(X)[:, 2].reshape(cam.height, cam.width), X.reshape(cam.height, cam.width, 3), s


@pytest.fixture(scope="module")
def ground():
    return Renderer(Mesh([textured_ground()]))


@pytest.mark.parametrize("dji", [(0, -90, 0), (30, -45, 5), (-140, -20, -3)])
def test_plane_depth_matches_analytic(ground, dji):
    cam = Camera.pinhole(640, 480, 520, cx=318.0, cy=243.5)
    pose = Pose.from_dji(*dji, [3.0, -7.0, 60.0])
    out = ground.render(cam, pose)
    z, X, s = analytic_plane_depth(cam, pose)
    inside = (np.abs(X[..., :2]).max(-1) < 99.0) & (s.reshape(z.shape) > 0)
    assert inside.mean() > 0.2
    valid = np.isfinite(out.depth)
    assert valid[inside].mean() > 0.999 and not valid[~inside & (np.abs(X[..., :2]).max(-1) > 101)].any()
    rel = np.abs(out.depth[inside & valid] - z[inside & valid]) / z[inside & valid]
    assert rel.max() < 1e-3           # the bar: 0.1 %
    assert np.median(rel) < 1e-5      # float32 depth is far better than that


def test_box_depth_matches_analytic():
    r = Renderer(Mesh([box([-5, -5, 0], [5, 5, 20], (200, 50, 50)), textured_ground(size=300)]))
    cam = Camera.pinhole(400, 400, 300)
    pose = Pose.from_dji(0, -90, 0, [0.0, 0.0, 100.0])
    out = r.render(cam, pose)
    # the roof (z = 20) is 80 m away along the optical axis; ground is 100 m
    roof = out.depth[190:210, 190:210]
    np.testing.assert_allclose(roof, 80.0, rtol=1e-5)
    assert np.nanmax(out.depth) == pytest.approx(100.0, rel=1e-5)
    assert tuple(out.rgb[200, 200]) == (200, 50, 50)


@pytest.mark.parametrize("model,params", [
    ("PINHOLE", (700.0, 690.0, 330.0, 235.0)),
    ("OPENCV", (700.0, 700.0, 320.0, 240.0, -0.12, 0.03, 0.0005, -0.0003)),
])
def test_point_lands_on_its_projected_pixel(model, params):
    """Small bright cubes at known 3D points: the rendered blob's centroid is where
    Camera.project says, within 0.5 px (pixel-centre convention included)."""
    cam = Camera(model, 640, 480, params)
    rng = np.random.default_rng(5)
    pose = Pose.from_dji(20, -55, 4, [0.0, -60.0, 90.0])
    centres = rng.uniform([-25, -5, 0], [25, 30, 10], (6, 3))
    parts = [box(c - 0.6, c + 0.6, (255, 255, 255)) for c in centres]
    plane = MeshPart(np.array([[-500, -500, -1], [500, -500, -1], [500, 500, -1], [-500, 500, -1.0]]),
                     np.array([[0, 1, 2], [0, 2, 3]]), colors=np.zeros((4, 3), np.uint8))
    r = Renderer(Mesh([*parts, plane]))
    out = r.render(cam, pose)
    gray = out.rgb[..., 0].astype(float)
    import cv2

    n, labels = cv2.connectedComponents((gray > 40).astype(np.uint8))
    uv_true, front = cam.project(pose.transform(centres))
    assert front.all() and cam.in_image(uv_true, 20).all()
    errs = []
    for uv in uv_true:
        j, i = (uv - 0.5).round().astype(int)
        lab = labels[i, j]
        assert lab > 0
        ii, jj = np.nonzero(labels == lab)
        w = gray[ii, jj]
        centroid = np.array([np.sum(jj * w), np.sum(ii * w)]) / w.sum() + 0.5  # pixel convention
        errs.append(np.linalg.norm(centroid - uv))
    # a cube's blob centroid is not exactly its centre's projection (perspective); ~0.1 px here
    assert max(errs) < 0.5, errs


def test_ortho_heights_and_georeferenced_pixels():
    r = Renderer(Mesh([box([10, 20, 0], [30, 25, 42.0], (255, 0, 0)), textured_ground(size=100, z=1.5)]))
    res = r.render_ortho(-50, -50, 50, 50, 0.5)
    assert res.depth.shape == (200, 200)
    # pixel (i, j) centre: x = -50 + (j + .5) * 0.5, y = 50 - (i + .5) * 0.5
    i, j = int((50 - 22.5) / 0.5), int((20 + 50) / 0.5)
    assert res.depth[i, j] == pytest.approx(42.0, abs=1e-4)
    assert tuple(res.rgb[i, j]) == (255, 0, 0)
    assert res.depth[10, 10] == pytest.approx(1.5, abs=1e-4)
    # tiling gives the same raster
    tiled = r.render_ortho(-50, -50, 50, 50, 0.5, tile=64)
    np.testing.assert_array_equal(tiled.depth, res.depth)


def test_obj_round_trip_renders_identically(tmp_path):
    from gtkit.geo import GeoFrame

    mesh = Mesh([textured_ground(size=120, tex_px=256), box([0, 0, 0], [10, 10, 15], (10, 200, 30))])
    frame = GeoFrame("EPSG:32650", (500000.0, 3370000.0, 20.0))
    offset = np.array([500100.0, 3370050.0, 0.0])
    stored = mesh.translated(np.asarray(frame.origin) - offset)   # vertices = CRS - offset
    path = write_obj(tmp_path / "model" / "reference.obj", stored, texture_format="png")
    write_offset_sidecar(path, "EPSG:32650", offset)
    loaded = load_model(path, frame)
    cam = Camera.pinhole(320, 240, 250)
    pose = Pose.from_dji(10, -60, 0, [5.0, -40.0, 70.0])
    a = Renderer(mesh).render(cam, pose)
    b = Renderer(loaded).render(cam, pose)
    np.testing.assert_allclose(a.depth, b.depth, rtol=1e-4, equal_nan=True)
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean() < 1.0
    # a CRS that does not match the project is an error naming the file
    from gtkit.errors import GtkitError

    with pytest.raises(GtkitError, match="does not match the project CRS"):
        load_model(path, GeoFrame("EPSG:32615"))
    parts = sorted(read_mesh_file(path).parts, key=lambda p: len(p.faces))
    assert [len(p.faces) for p in parts] == [2, 12]
    assert tuple(parts[1].colors[0]) == (10, 200, 30)


def _triangles(part, uv=None) -> list:
    """A part's triangles as a sorted list, each its corners (x y z [u v]) from its smallest corner
    on (the winding kept): the same list for the same triangles in any order or vertex numbering."""
    c = part.vertices if uv is None else np.concatenate([part.vertices, uv], 1)
    return sorted(min(tuple(np.roll(t, -k, 0).ravel()) for k in range(3)) for t in c[part.faces])


def test_obj_streamed_parts_are_trimesh_parts_and_render_the_same(tmp_path):
    """gtkit.io.mesh.model_parts (numpy reader, one material and one texture at a time) gives the
    parts load_model (trimesh) gives: the same textures, the same (vertex, uv) corners and
    triangles, the same colours for untextured parts; the renders are identical. A file with
    polygons and relative indices is read the same, and a vertex-coloured OBJ goes through trimesh."""
    from gtkit.geo import GeoFrame
    from gtkit.io.mesh import model_parts

    mesh = Mesh([textured_ground(size=120, tex_px=256), textured_ground(size=40, z=3.0, tex_px=128, seed=1),
                 box([0, 0, 0], [10, 10, 15], (10, 200, 30))])
    frame = GeoFrame("EPSG:32650", (500000.0, 3370000.0, 20.0))
    offset = np.array([500100.0, 3370050.0, 0.0])
    path = write_obj(tmp_path / "m" / "reference.obj", mesh.translated(np.asarray(frame.origin) - offset))
    write_offset_sidecar(path, "EPSG:32650", offset)
    ref = load_model(path, frame)
    got = list(model_parts(path, frame))
    assert sorted(p.name for p in got) == sorted(p.name for p in ref.parts)
    for a in ref.parts:
        b = next(p for p in got if p.name == a.name)
        assert (a.texture is None) == (b.texture is None)
        if a.texture is not None:
            np.testing.assert_array_equal(a.texture, b.texture)
            assert _triangles(a, a.uv) == _triangles(b, b.uv)
            assert len(a.vertices) == len(b.vertices)
        else:
            np.testing.assert_array_equal(a.colors, b.colors)
            assert _triangles(a) == _triangles(b)
    cam = Camera.pinhole(320, 240, 250)
    for pose in (Pose.from_dji(10, -60, 0, [5.0, -40.0, 70.0]), Pose.from_dji(100, -30, 0, [-30.0, 5.0, 25.0])):
        a = Renderer(ref).render(cam, pose)
        r = Renderer()
        r.add_parts(model_parts(path, frame))
        b = r.render(cam, pose)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
    # polygons (a quad as a fan) and relative indices: the same triangles as trimesh reads
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 1\nf 1 2 3 4\nf -4 5 -3\n")
    a, b = read_mesh_file(tmp_path / "q.obj").parts, list(model_parts(tmp_path / "q.obj"))
    assert len(a) == len(b) == 1 and len(b[0].faces) == len(a[0].faces) == 3
    assert _triangles(a[0]) == _triangles(b[0])
    np.testing.assert_array_equal(a[0].colors, b[0].colors)
    # vertex colours are not kept by the numpy reader: such a file is read by trimesh
    (tmp_path / "c.obj").write_text("v 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 0 1 0 1 0 0\nf 1 2 3\n")
    assert tuple(next(model_parts(tmp_path / "c.obj")).colors[0]) == (255, 0, 0)


def test_parts_outside_the_frustum_are_not_drawn_and_the_view_is_unchanged():
    """Drawing all parts culls those whose box the view cannot see; the image and depth are those of
    every part drawn, and a view of no part is empty."""
    boxes = [box([x, y, 0], [x + 8, y + 8, 5 + (x + y) % 13], (40 + x % 200, 90, 160)) for x in range(-400, 401, 100)
             for y in range(-400, 401, 100)]
    r = Renderer(Mesh(boxes + [textured_ground(size=900)]))
    cam = Camera.pinhole(320, 240, 260)
    drawn = []
    orig = r._draw
    r._draw = lambda *a, **k: (drawn.append(len(a[6])), orig(*a, **k))[1]
    for dji, c in (((0, -90, 0), [50.0, 50.0, 80.0]), ((60, -30, 0), [-300.0, -250.0, 40.0]),
                   ((-150, -60, 0), [390.0, 10.0, 120.0])):
        pose = Pose.from_dji(*dji, c)
        culled, everything = r.render(cam, pose), r.render(cam, pose, parts=list(range(len(boxes) + 1)))
        assert np.array_equal(culled.rgb, everything.rgb)
        assert np.array_equal(culled.depth, everything.depth, equal_nan=True)
        assert np.isfinite(culled.depth).mean() > 0.3
    assert drawn[0] < 10 and max(drawn[0::2]) < len(boxes) and set(drawn[1::2]) == {len(boxes) + 1}
    away = r.render(cam, Pose.from_dji(0, 30, 0, [2000.0, 0.0, 50.0]))  # looking up, off the site
    assert not np.isfinite(away.depth).any() and not away.rgb.any()


def test_ray_box_fraction_bounds_the_rendered_fraction():
    """The database's free probe: the share of a grid of rays meeting the parts' boxes is never
    (beyond the grid's sampling) below the share of pixels that see the model."""
    from gtkit.render.frustum import ray_box_fraction

    r = Renderer(Mesh([box([-200, -200, 0], [200, 200, 2], (90, 90, 90)), box([40, 40, 0], [55, 70, 30], (200, 0, 0))]))
    cam = Camera.pinhole(320, 240, 277)
    rng = np.random.default_rng(3)
    seen = []
    for _ in range(40):
        pose = Pose.from_dji(rng.uniform(-180, 180), rng.uniform(-90, -20), 0,
                             [*rng.uniform(-280, 280, 2), rng.uniform(40, 150)])
        rendered = float(np.isfinite(r.render(cam, pose, with_rgb=False).depth).mean())
        bound = ray_box_fraction(cam, pose, r.boxes())
        assert bound >= rendered - 0.01
        seen.append((rendered, bound))
    seen = np.array(seen)
    assert (seen[:, 0] < 0.4).sum() >= 5 and (seen[:, 0] > 0.6).sum() >= 5     # both kinds of view drawn
    assert np.median(seen[:, 1] - seen[:, 0]) < 0.05                          # and the bound is tight


def test_ray_box_fraction_of_many_boxes_is_each_ray_against_every_box():
    """With hundreds of overlapping boxes (a photo-built model: a part per photo) the probe skips
    boxes outside the frustum and rays already met; the share is the same as every grid ray tested
    against every box."""
    from gtkit.render.frustum import ray_box_fraction

    rng = np.random.default_rng(5)
    lo = rng.uniform(-400, 300, (300, 3)) * [1, 1, 0.05]
    boxes = np.stack([lo, lo + rng.uniform(5, 250, (300, 3)) * [1, 1, 0.2]], axis=1)
    cam = Camera.pinhole(320, 240, 277)
    u, v = np.meshgrid((np.arange(40) + 0.5) * 8, (np.arange(30) + 0.5) * 8)
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)
    shares = []
    for _ in range(30):
        pose = Pose.from_dji(rng.uniform(-180, 180), rng.uniform(-90, -10), 0,
                             [*rng.uniform(-600, 600, 2), rng.uniform(40, 200)])
        d = rays @ pose.R
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (boxes[None, :, 0] - pose.center) / d[:, None]
            t1 = (boxes[None, :, 1] - pose.center) / d[:, None]
            enter = np.nanmax(np.minimum(t0, t1), axis=2)
            leave = np.nanmin(np.maximum(t0, t1), axis=2)
        every = float((leave >= np.maximum(enter, 0.0)).any(axis=1).mean())
        assert ray_box_fraction(cam, pose, boxes) == every
        shares.append(every)
    assert min(shares) < 0.3 and max(shares) > 0.9
