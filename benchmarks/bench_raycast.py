"""Ray casting speed of gtkit.track.raycast (first DSM crossing, half-cell steps + bisection).

    .venv/bin/python benchmarks/bench_raycast.py [--rays 20000]

Prints rays/s for a flat DSM, a rough DSM with buildings, at steep (nadir-ish) and oblique
(20 deg below the horizon) angles, on a 1000 m x 1000 m DSM at 0.5 m (4M cells), with and
without the free-space skipping (same results, see tests/test_track_raycast.py).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtkit.track.raycast import cast_rays, dsm_from_array  # noqa: E402


def dsm(kind: str, size=1000.0, res=0.5, seed=0):
    n = int(size / res)
    rng = np.random.default_rng(seed)
    x = -size / 2 + (np.arange(n) + 0.5) * res
    X, Y = np.meshgrid(x, -x)
    h = 0.03 * X + 5 * np.sin(X / 80) * np.cos(Y / 60)
    if kind == "buildings":
        for _ in range(400):
            cx, cy = rng.uniform(-size / 2, size / 2, 2)
            w, d, ht = rng.uniform(8, 40), rng.uniform(8, 40), rng.uniform(5, 40)
            m = (np.abs(X - cx) < w / 2) & (np.abs(Y - cy) < d / 2)
            h[m] = np.maximum(h[m], h[m].max() + ht)
    return dsm_from_array(h, -size / 2, size / 2, res)


def rays(n, elev_deg, seed=1):
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(elev_deg + rng.uniform(-5, 5, n))
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    o = np.column_stack([rng.uniform(-150, 150, n), rng.uniform(-150, 150, n), np.full(n, 150.0)])
    return o, d


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rays", type=int, default=20000)
    a = ap.parse_args()
    print(f"{'DSM':10s} {'view':16s} {'rays':>7s} {'hit %':>6s} {'mean range m':>12s} {'s':>7s} {'rays/s':>9s} "
          f"{'no-skip rays/s':>14s}")
    for kind in ("flat", "buildings"):
        g = dsm(kind)
        for view, el in (("steep (75 deg)", 75.0), ("oblique (20 deg)", 20.0)):
            o, d = rays(a.rays, el)
            cast_rays(g, o[:100], d[:100])  # warm-up
            t = time.perf_counter()
            h = cast_rays(g, o, d)
            dt = time.perf_counter() - t
            m = min(a.rays, 5000)
            t = time.perf_counter()
            cast_rays(g, o[:m], d[:m], skip=False)  # without free-space skipping, for comparison
            dt0 = time.perf_counter() - t
            print(f"{kind:10s} {view:16s} {a.rays:7d} {100 * h.ok.mean():6.1f} {np.nanmean(h.distance):12.1f} "
                  f"{dt:7.2f} {a.rays / dt:9.0f} {m / dt0:14.0f}")


if __name__ == "__main__":
    main()
