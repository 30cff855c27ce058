"""Automatic tie points are kept only where the reference model is a smooth surface."""
from __future__ import annotations

import numpy as np

from gtkit.sfm.tie_surface import HeightGrid, SmoothSurfaceSettings, on_smooth_surface


def _site() -> HeightGrid:
    """100 x 100 m at 0.5 m: a sloping field (5 %), a 12 m building of 20 x 20 m, a bumpy canopy."""
    res = 0.5
    x = (np.arange(200) + 0.5) * res
    y = 100.0 - (np.arange(200) + 0.5) * res
    X, Y = np.meshgrid(x, y)
    Z = 30.0 + 0.05 * X - 0.02 * Y
    Z[(X > 40) & (X < 60) & (Y > 40) & (Y < 60)] += 12.0
    canopy = (X - 20) ** 2 + (Y - 80) ** 2 < 8 ** 2
    Z[canopy] += 6.0 + 1.5 * np.sin(X[canopy] * 2.1) * np.cos(Y[canopy] * 1.7)
    Z[(X > 85) & (Y < 10)] = np.nan     # off the model
    return HeightGrid(Z.astype(np.float32), 0.0, 100.0, res)


def test_ties_on_ground_and_flat_roofs_kept_edges_canopy_and_air_dropped():
    g = _site()
    s = SmoothSurfaceSettings()

    def z(x, y):
        return 30.0 + 0.05 * x - 0.02 * y

    pts = {
        "field": ([10.0, 30.0, z(10, 30)], True),
        "field, sloping, 3 cm off": ([75.0, 75.0, z(75, 75) + 0.03], True),
        "flat roof, middle": ([50.0, 50.0, z(50, 50) + 12.0], True),
        "roof edge": ([40.2, 50.0, z(40.2, 50) + 12.0], False),
        "foot of the wall": ([39.0, 50.0, z(39, 50)], False),
        "canopy": ([20.0, 80.0, z(20, 80) + 6.0], False),
        "1 m above the field": ([10.0, 20.0, z(10, 20) + 1.0], False),
        "off the model": ([95.0, 5.0, z(95, 5)], False),
        "outside the grid": ([130.0, 50.0, 30.0], False),
    }
    keep = on_smooth_surface(np.array([p for p, _ in pts.values()]), g, s)
    assert {k: bool(v) for k, v in zip(pts, keep)} == {k: want for k, (_, want) in pts.items()}
    # a coarser disk reaches the building from farther away
    wide = on_smooth_surface(np.array([[37.5, 50.0, z(37.5, 50)]]), g, SmoothSurfaceSettings(radius_m=4.0))
    assert not wide[0] and on_smooth_surface(np.array([[37.5, 50.0, z(37.5, 50)]]), g, s)[0]
