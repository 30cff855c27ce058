"""Renderer benchmark: RGB + depth views per second and time to first frame.

A >= 200k-triangle terrain mesh with a 4096^2 texture, 1024x768 views from 120 m at
DJI pitch -45 deg, like the localization database. Run:  python benchmarks/bench_render.py
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def terrain(n: int = 320, size: float = 600.0, tex: int = 4096, seed: int = 0):
    from gtkit.io.mesh import Mesh, MeshPart

    rng = np.random.default_rng(seed)
    xs = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(xs, xs)
    Z = 5 * np.sin(X / 40) * np.cos(Y / 55) + rng.normal(0, 0.3, X.shape)
    v = np.stack([X, Y, Z], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    f = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    uv = (v[:, :2] + size / 2) / size
    texture = rng.integers(0, 255, (tex, tex, 3), dtype=np.uint8)
    return Mesh([MeshPart(v, f, uv=uv, texture=texture)])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--size", default="1024x768")
    args = ap.parse_args()
    from gtkit.camera import Camera
    from gtkit.pose import Pose
    from gtkit.render.renderer import Renderer

    w, h = (int(s) for s in args.size.split("x"))
    mesh = terrain()
    cam = Camera.from_hfov(w, h, 70.0)
    t0 = time.perf_counter()
    r = Renderer(mesh)
    first = r.render(cam, Pose.from_dji(0, -45, 0, [0, -100, 120]))
    t_first = time.perf_counter() - t0
    assert np.isfinite(first.depth).mean() > 0.5
    t0 = time.perf_counter()
    for k in range(args.views):
        r.render(cam, Pose.from_dji(45.0 * k, -45, 0, [np.cos(k) * 100, np.sin(k) * 100, 120]))
    dt = (time.perf_counter() - t0) / args.views
    t0 = time.perf_counter()
    for k in range(args.views):
        r.render(cam, Pose.from_dji(45.0 * k, -45, 0, [np.cos(k) * 100, np.sin(k) * 100, 120]), with_rgb=False)
    dt_d = (time.perf_counter() - t0) / args.views
    print("| mesh | triangles | texture | view | first frame (s) | RGB+depth ms/view | views/s | depth-only views/s |")
    print("|---|---|---|---|---|---|---|---|")
    print(f"| terrain | {r.n_triangles:,} | 4096^2 | {w}x{h} | {t_first:.2f} | {dt * 1000:.0f} | {1 / dt:.1f} | {1 / dt_d:.1f} |")


if __name__ == "__main__":
    main()
