"""A tiny self-contained project for tests, screenshots and benchmarks (no sample generator needed).

A 240 m x 240 m textured ground with coloured blocks on it; reference photos (five-eye
style: nadir + obliques) and one query sequence are rendered from the very mesh that is also
written as the reference model, so at the true pose photo and render agree up to noise.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gtkit.camera import Camera
from gtkit.conventions import rotation_to_dji
from gtkit.geo import GeoFrame
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.io.mesh import Mesh, MeshPart, write_obj, write_offset_sidecar
from gtkit.io.poses import write_intrinsics, write_poses
from gtkit.io.tiepoints import Observation, TiePoint, write_tiepoints
from gtkit.pose import Pose
from gtkit.project import Project

HALF = 120.0


def _texture(rng, n=2048) -> np.ndarray:
    import cv2

    img = np.full((n, n, 3), 110, np.uint8)
    img[:] = rng.integers(90, 140, 3)
    for size, count in ((400, 30), (120, 250), (40, 1200), (12, 3000)):
        for _ in range(count):
            x, y = rng.integers(0, n, 2)
            w, h = rng.integers(size // 3, size, 2)
            cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), tuple(int(c) for c in rng.integers(20, 235, 3)), -1)
    for _ in range(14):  # roads
        p = rng.integers(0, n, 4)
        cv2.line(img, (int(p[0]), 0), (int(p[1]), n), (60, 60, 60), int(rng.integers(10, 25)))
        cv2.line(img, (0, int(p[2])), (n, int(p[3])), (200, 200, 190), int(rng.integers(4, 10)))
    return img


def _box(cx, cy, w, d, h, color, rng) -> MeshPart:
    x0, x1, y0, y1 = cx - w / 2, cx + w / 2, cy - d / 2, cy + d / 2
    quads = [((x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h)),  # roof
             ((x0, y0, 0), (x1, y0, 0), (x1, y0, h), (x0, y0, h)),
             ((x1, y0, 0), (x1, y1, 0), (x1, y1, h), (x1, y0, h)),
             ((x1, y1, 0), (x0, y1, 0), (x0, y1, h), (x1, y1, h)),
             ((x0, y1, 0), (x0, y0, 0), (x0, y0, h), (x0, y1, h))]
    v, f, c = [], [], []
    for k, q in enumerate(quads):
        base = len(v)
        v += list(q)
        f += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
        shade = 1.0 if k == 0 else 0.55 + 0.1 * k
        c += [np.clip(np.asarray(color) * shade, 0, 255)] * 4
    return MeshPart(np.array(v, float), np.array(f), colors=np.array(c, np.uint8), name=f"box{len(v)}")


def demo_mesh(seed: int = 0) -> Mesh:
    rng = np.random.default_rng(seed)
    g = 16
    xs = np.linspace(-HALF, HALF, g + 1)
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    uv = np.stack([(X.ravel() + HALF) / (2 * HALF), (Y.ravel() + HALF) / (2 * HALF)], 1)
    F = []
    for i in range(g):
        for j in range(g):
            a = i * (g + 1) + j
            F += [(a, a + 1, a + g + 2), (a, a + g + 2, a + g + 1)]
    parts = [MeshPart(V, np.array(F), uv=uv, texture=_texture(rng), name="ground")]
    for _ in range(14):
        cx, cy = rng.uniform(-90, 90, 2)
        parts.append(_box(cx, cy, *rng.uniform(8, 25, 2), rng.uniform(5, 30), rng.integers(40, 230, 3), rng))
    return Mesh(parts)


def _look_at(C, target) -> Pose:
    z = np.asarray(target, float) - C
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0, 0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose.from_center(np.stack([x, y, z]), C)


def make_demo_project(root: str | Path, *, size=(640, 480), n_query=3, seed: int = 0,
                      n_tiepoints: int = 0, photo_scale: int = 1) -> Project:
    """Write the demo project into ``root`` and return it. ``photo_scale`` > 1 upsamples the
    photos (for big-image benchmarks; intrinsics scaled to match)."""
    import cv2

    from gtkit.render.renderer import Renderer

    root = Path(root)
    frame = GeoFrame.for_lonlat(114.05, 22.55, 0.0)
    proj = Project.create(root, frame, "demo")
    P = proj.paths
    rng = np.random.default_rng(seed + 1)
    mesh = demo_mesh(seed)
    write_obj(P.model / "reference.obj", mesh)
    write_offset_sidecar(P.model / "reference.obj", frame.crs_spec, frame.origin)
    rend = Renderer(mesh)
    cam = Camera.from_hfov(size[0], size[1], 70.0)
    poses, cams = {}, {}
    shots = []
    for k, (dx, dy) in enumerate(((-40, -40), (40, 40))):
        C = np.array([dx, dy, 110.0])
        for eye, off in (("N", (0, 0)), ("F", (0, 70)), ("B", (0, -70)), ("L", (-70, 0)), ("R", (70, 0))):
            tgt = np.array([dx + off[0], dy + off[1] + (0.01 if eye == "N" else 0), 0.0])
            shots.append((f"reference/R01_{k:03d}_{eye}.jpg", _look_at(C, tgt)))
    for k in range(n_query):
        C = np.array([-30 + 25 * k, -70 + 10 * k, 60.0 + 5 * k])
        shots.append((f"queries/seq1/{k:04d}_W.jpg", _look_at(C, [C[0] + 5, C[1] + 60, 0.0])))
    big = cam.scaled(photo_scale) if photo_scale != 1 else cam
    for name, pose in shots:
        img = rend.render(cam, pose).rgb
        if photo_scale != 1:
            img = cv2.resize(img, (big.width, big.height), interpolation=cv2.INTER_CUBIC)
        noise = rng.normal(0, 3, img.shape)
        img = np.clip(img + noise, 0, 255).astype(np.uint8)
        lon, lat, h = frame.local_to_wgs84(pose.center)
        yaw, pitch, roll = rotation_to_dji(pose.R)
        write_jpeg_with_meta(P.images / name, img, lat=float(lat), lon=float(lon), alt=float(h),
                             dji={"GimbalYawDegree": yaw, "GimbalPitchDegree": pitch, "GimbalRollDegree": roll,
                                  "AbsoluteAltitude": float(h)}, quality=90)
        poses[name], cams[name] = pose, big
    write_intrinsics(P.cameras, cams)
    write_intrinsics(P.truth / "intrinsics.txt", cams)
    write_poses(P.truth / "poses.txt", poses)
    if n_tiepoints:
        q = [n for n in poses if n.startswith("queries/")]
        r = [n for n in poses if n.startswith("reference/")]
        tps = [TiePoint(f"tp{i:05d}", [Observation(q[i % len(q)], *rng.uniform(1, (big.width - 1, big.height - 1))),
                                       Observation(r[i % len(r)], *rng.uniform(1, (big.width - 1, big.height - 1)))],
                        source="simulated") for i in range(n_tiepoints)]
        write_tiepoints(P.tiepoints, tps)
    rend.release()
    return proj
