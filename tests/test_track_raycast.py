"""Ray marching against a DSM: first crossing, refinement, misses (issue 8)."""
import numpy as np
import pytest

from gtkit.errors import GtkitError
from gtkit.track.raycast import HIT, OUTSIDE, SKY, STARTS_BELOW, cast_rays, dsm_from_array


def _grid(fn, size=200.0, cell=0.5):
    """A grid over [-size/2, size/2]^2 sampling fn(x, y) at cell centres."""
    n = int(size / cell)
    x0, y0 = -size / 2, size / 2
    xc = x0 + (np.arange(n) + 0.5) * cell
    yc = y0 - (np.arange(n) + 0.5) * cell
    X, Y = np.meshgrid(xc, yc)
    return dsm_from_array(fn(X, Y), x0, y0, cell)


def test_plane_and_slope_exact_to_centimetres():
    rng = np.random.default_rng(0)
    g = _grid(lambda x, y: 10.0 + 0.2 * x - 0.1 * y)  # bilinear reproduces a plane exactly
    o = np.column_stack([rng.uniform(-30, 30, 500), rng.uniform(-30, 30, 500), np.full(500, 150.0)])
    d = np.column_stack([rng.uniform(-0.3, 0.3, 500), rng.uniform(-0.3, 0.3, 500), -np.ones(500)])
    hits = cast_rays(g, o, d, tol=0.01)
    assert hits.ok.all()
    p = hits.points
    err = np.abs(p[:, 2] - (10.0 + 0.2 * p[:, 0] - 0.1 * p[:, 1]))
    assert err.max() < 0.02
    # agreement with the analytic intersection of ray and plane
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    nrm = np.array([-0.2, 0.1, 1.0])
    s = (10.0 - o @ nrm) / (dn @ nrm)
    assert np.abs(hits.distance - s).max() < 0.02


def test_first_crossing_is_the_building_not_the_ground_behind():
    # a 30 m tall, 6 m thick wall at x in [20, 26]; ground at 0
    g = _grid(lambda x, y: np.where((x > 20) & (x < 26), 30.0, 0.0))
    # a ray from (0, 0, 60) descending at 45 deg towards +x: reaches z = 30 at x = 30 (behind the
    # wall), so it passes over the wall top -> next crossing is the ground at x = 60
    over = cast_rays(g, [0, 0, 60], [1, 0, -1])
    assert over.ok[0] and abs(over.points[0, 0] - 60.0) < 0.05 and abs(over.points[0, 2]) < 0.05
    # a shallower ray that reaches the wall while below its top: must stop at the wall face
    # (x ~ 20.25, between the last ground cell centre and the first wall cell centre), not behind
    hit = cast_rays(g, [0, 0, 30], [1, 0, -0.25])  # z = 25 at x = 20
    assert hit.ok[0]
    x, z = hit.points[0, 0], hit.points[0, 2]
    assert 19.7 < x < 20.8 and 24.5 < z < 25.5, (x, z)
    # the point lies on the ray and on the surface to centimetres
    assert abs(z - g.height_at(x, 0.0)) < 0.05
    # a ray that clears the front edge but meets the roof (z = 30 at x = 25), not the ground at x = 325
    graze = cast_rays(g, [0, 0, 32.5], [1, 0, -0.1])
    assert graze.ok[0] and 24.5 < graze.points[0, 0] < 26.0 and abs(graze.points[0, 2] - 30) < 0.1


def test_thin_tower_is_not_stepped_over():
    # a 1 m x 1 m x 50 m tower (two cells) at x in [40, 41]: a steep-enough ray passes through its
    # column above the ground; the marcher (half-cell steps) must not skip it
    g = _grid(lambda x, y: np.where((x > 40) & (x < 41) & (np.abs(y) < 0.5), 50.0, 0.0))
    hits = cast_rays(g, [0, 0.0, 45], [1, 0, -0.3])  # z at x=40 is 33 < 50 -> hits the tower
    assert hits.ok[0] and 39.5 < hits.points[0, 0] < 41.0


def test_misses_give_a_status_and_no_coordinate():
    g = _grid(lambda x, y: np.zeros_like(x))
    h = cast_rays(g, [[0, 0, 100], [0, 0, 100], [0, 0, 100], [0, 0, -5]],
                  [[1, 0, 0.1], [1, 0, 0.0], [1, 0, -0.1], [0, 0, -1]])
    assert list(h.status) == [SKY, SKY, OUTSIDE, STARTS_BELOW]
    assert np.isnan(h.points).all()
    assert "horizon" in h.message(0) and "extent" in h.message(2)
    # a ray over a no-data hole falls through it and is reported as outside, not made up
    hole = _grid(lambda x, y: np.where(np.hypot(x, y) < 30, np.nan, 0.0))
    h2 = cast_rays(hole, [0, 0, 50], [0.01, 0, -1])
    assert h2.status[0] == OUTSIDE and np.isnan(h2.points).all()
    with pytest.raises(GtkitError):
        cast_rays(g, [0, 0, 100], [0, 0, 0])


def test_reads_a_real_dsm_geotiff_in_the_project_frame(tmp_path):
    """A GeoTIFF in a UTM CRS with a local origin: the ray is cast in the world frame."""
    import rasterio
    from rasterio.transform import Affine

    from gtkit.export.dsm import Dsm
    from gtkit.geo import GeoFrame

    frame = GeoFrame("EPSG:32650", (500000.0, 4000000.0, 100.0))
    h = np.full((40, 50), 110.0, np.float32)
    h[10:20, 20:30] = 140.0  # a 20 m x 20 m, 30 m tall block
    h[0, 0] = -9999.0
    path = tmp_path / "dsm.tif"
    with rasterio.open(path, "w", driver="GTiff", width=50, height=40, count=1, dtype="float32",
                       crs="EPSG:32650", transform=Affine(2.0, 0, 500000.0, 0, -2.0, 4000080.0),
                       nodata=-9999.0) as dst:
        dst.write(h, 1)
    dsm = Dsm.open(path, frame)
    r = cast_rays(dsm, [[55.0, 50.0, 100.0], [5.0, 5.0, 100.0]], [0, 0, -1])
    assert list(r.status) == [HIT, HIT]
    assert abs(r.points[0, 2] - 40.0) < 0.02 and abs(r.points[1, 2] - 10.0) < 0.02


def test_free_space_skipping_changes_nothing():
    """Random rays over a town of random blocks: same statuses and crossings with and without the
    block-max skipping (which only jumps over provably empty segments)."""
    rng = np.random.default_rng(5)

    def town(x, y):
        h = 2.0 * np.sin(x / 15.0) + 0.05 * y
        for _ in range(60):
            cx, cy, w, d, ht = *rng.uniform(-90, 90, 2), *rng.uniform(3, 15, 2), rng.uniform(3, 40)
            h = np.where((np.abs(x - cx) < w / 2) & (np.abs(y - cy) < d / 2), h + ht, h)
        h[(x > 60) & (y > 60)] = np.nan  # a hole without data
        return h

    g = _grid(town, cell=0.5)
    n = 3000
    el = np.radians(rng.uniform(2, 89, n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    o = np.column_stack([rng.uniform(-100, 100, (n, 2)), rng.uniform(45, 150, n)])
    fast, slow = cast_rays(g, o, d), cast_rays(g, o, d, skip=False)
    assert (fast.status == slow.status).all()
    ok = fast.ok
    assert ok.sum() > 1000 and np.abs(fast.distance[ok] - slow.distance[ok]).max() < 0.02
