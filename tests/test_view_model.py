"""The 3D view's model reader (gtkit.view.model): the numpy OBJ reader gives the same triangles and
colours as gtkit.io.mesh.load_model, a big model is decimated to the asked count with its colours
and cached, a changed model is read again, and other formats go through load_model."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyvista")

from gtkit.geo import GeoFrame  # noqa: E402
from gtkit.io.mesh import Mesh, MeshPart, load_model, write_obj, write_offset_sidecar  # noqa: E402
from gtkit.project import Project  # noqa: E402
from gtkit.view.model import view_model  # noqa: E402


def _grid(n, x0, colour_fn):
    """An n x n grid of quads (2 triangles each) at x0, gently sloped; uv spans the texture."""
    g = np.linspace(0, 1, n + 1)
    X, Y = np.meshgrid(g, g)
    V = np.c_[x0 + 40 * X.ravel(), 40 * Y.ravel(), 2 * X.ravel() + Y.ravel()]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    tex = np.zeros((256, 256, 3), np.uint8)
    yy, xx = np.mgrid[0:256, 0:256]
    tex[...] = colour_fn(xx, yy)[..., None] * np.array([1, 0.5, 0.2])  # row 0 = top
    return V, F, np.c_[X.ravel(), Y.ravel()], tex


def _project(root, parts):
    frame = GeoFrame.for_lonlat(114.3, 30.5, 0.0)
    p = Project.create(root, frame, name="view-model")
    off = np.round(np.asarray(frame.origin), -2)
    mesh = Mesh(parts).translated(np.asarray(frame.origin) - off)
    write_obj(p.paths.model / "reference.obj", mesh)
    write_offset_sidecar(p.paths.model / "reference.obj", frame.crs_spec, off)
    return p


def _tri_set(V, F):
    t = np.sort(np.round(V[F], 3).reshape(len(F), -1), axis=0)
    return t[np.lexsort(t.T[::-1])]


def test_fast_reader_matches_load_model_and_decimates_with_cache(tmp_path):
    V1, F1, uv1, tex1 = _grid(30, 0, lambda x, y: (x > 128) * 200 + 30)  # dark left, bright right
    V2, F2, _uv, _t = _grid(10, 50, lambda x, y: 0 * x)
    parts = [MeshPart(V1, F1, uv=uv1, texture=tex1, name="ground"),
             MeshPart(V2, F2, colors=np.tile(np.uint8([10, 200, 30]), (len(V2), 1)), name="green")]
    p = _project(tmp_path / "site", parts)
    n = len(F1) + len(F2)
    # drawn as it is (textured) when small enough: the same triangles as load_model reads
    shown, n_in, n_shown = view_model(p, 10 * n)
    assert (n_in, n_shown) == (n, n) and len(shown) == 2
    ref = load_model(p.paths.model / "reference.obj", p.frame)
    ref_tris = _tri_set(np.concatenate([q.vertices for q in ref.parts]),
                        np.concatenate([q.faces + sum(len(r.vertices) for r in ref.parts[:k]) for k, q in enumerate(ref.parts)]))
    got = [(np.asarray(pd.points), np.asarray(pd.faces).reshape(-1, 4)[:, 1:]) for pd, _t in shown]
    off = np.cumsum([0] + [len(v) for v, _f in got])
    assert np.allclose(_tri_set(np.concatenate([v for v, _f in got]),
                                np.concatenate([f + o for (_v, f), o in zip(got, off)])), ref_tris, atol=2e-3)
    textured = [t for _pd, t in shown if t is not None]
    assert len(textured) == 1 and textured[0].dimensions == (256, 256)
    # decimated with colours when too big: dark on the left half, bright on the right, green part green
    cache_dir = p.paths.stage("view")
    shown, n_in, n_shown = view_model(p, 600)
    assert n_in == n and 200 < n_shown <= 600 and len(shown) == 1
    pd = shown[0][0]
    P, rgb = np.asarray(pd.points), np.asarray(pd.point_data["rgb"]).astype(int)
    ground = P[:, 0] < 45
    left, right = ground & (P[:, 0] < 15), ground & (P[:, 0] > 25)
    assert rgb[left, 0].mean() < 60 and rgb[right, 0].mean() > 180, (rgb[left, 0].mean(), rgb[right, 0].mean())
    assert np.abs(rgb[~ground] - [10, 200, 30]).max() <= 2
    caches = list(cache_dir.glob("model_*.npz"))
    assert len(caches) == 1
    again, _n, n2 = view_model(p, 600)  # from the cache
    assert n2 == n_shown and np.array_equal(np.asarray(again[0][0].point_data["rgb"]), np.asarray(pd.point_data["rgb"]))
    # a changed model (new texture) is read again; the old cache goes
    parts[0] = MeshPart(V1, F1, uv=uv1, texture=255 - tex1, name="ground")
    write_obj(p.paths.model / "reference.obj", Mesh(parts).translated(
        np.asarray(p.frame.origin) - np.round(np.asarray(p.frame.origin), -2)))
    changed, _n, _s = view_model(p, 600)
    rgb2 = np.asarray(changed[0][0].point_data["rgb"]).astype(int)
    P2 = np.asarray(changed[0][0].points)
    assert rgb2[(P2[:, 0] < 15), 0].mean() > 180
    assert [c.name for c in cache_dir.glob("model_*.npz")] != [c.name for c in caches]
    assert len(list(cache_dir.glob("model_*.npz"))) == 1


def test_other_formats_go_through_load_model(tmp_path):
    import trimesh

    V, F, _uv, _t = _grid(12, 0, lambda x, y: 0 * x)
    frame = GeoFrame.for_lonlat(114.3, 30.5, 0.0)
    p = Project.create(tmp_path / "site", frame, name="view-ply")
    off = np.round(np.asarray(frame.origin), -2)
    m = trimesh.Trimesh(V + np.asarray(frame.origin) - off, F, vertex_colors=np.tile([250, 20, 20, 255], (len(V), 1)),
                        process=False)
    p.paths.model.mkdir(parents=True, exist_ok=True)
    m.export(p.paths.model / "site.ply")
    write_offset_sidecar(p.paths.model / "site.ply", frame.crs_spec, off)
    shown, n_in, n_shown = view_model(p, 100)
    assert n_in == len(F) and n_shown <= 100
    pd = shown[0][0]
    assert np.allclose(np.asarray(pd.points).min(0)[:2], V.min(0)[:2], atol=4.0)  # in the world frame
    assert np.abs(np.asarray(pd.point_data["rgb"]).astype(int) - [250, 20, 20]).max() <= 2


def test_the_cache_is_written_before_the_first_open(tmp_path):
    """`gtkit model build`, `gtkit import model` and `gtkit sample create` call prepare_cache, so the
    first 3D view of a big model reads the cache (medium: 2.6 s first open vs 1.2 s cached, near idle)."""
    from gtkit.view.model import prepare_cache
    from gtkit.view.scene import ViewSettings

    V, F, uv, tex = _grid(190, 0, lambda x, y: (x > 128) * 200 + 30)  # 72,200 triangles > the view's 60k
    p = _project(tmp_path / "site", [MeshPart(V, F, uv=uv, texture=tex, name="ground")])
    line = prepare_cache(p)
    assert "cached" in line and "72200 triangles" in line, line
    (cache,) = p.paths.stage("view").glob("model_*.npz")
    stamp = cache.stat().st_mtime_ns
    shown, n_in, n_shown = view_model(p, ViewSettings().max_triangles)
    assert n_in == len(F) and 0 < n_shown <= ViewSettings().max_triangles
    assert cache.stat().st_mtime_ns == stamp and len(list(cache.parent.glob("model_*.npz"))) == 1
    assert "no model" in prepare_cache(Project.create(tmp_path / "empty", p.frame, name="empty"))
