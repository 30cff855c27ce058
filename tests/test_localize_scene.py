"""A small synthetic site for the localization tests (no test functions here).

Land: a 300 m x 300 m textured ground (multi-scale random colour noise, so SIFT finds features
at every scale) with a few textured boxes (depth discontinuities); water: a flat uniform blue
strip east of it. Query photos are rendered at known poses with the project's renderer and
written as JPEGs with EXIF GPS and DJI XMP gimbal angles.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gtkit.camera import Camera
from gtkit.geo import GeoFrame
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.io.mesh import Mesh, MeshPart, write_obj, write_offset_sidecar
from gtkit.io.poses import write_intrinsics, write_poses
from gtkit.pose import Pose
from gtkit.project import Project

LAND = (-150.0, -150.0, 150.0, 150.0)
WATER = (150.0, -150.0, 260.0, 150.0)
QUERY_CAM = Camera.from_hfov(800, 600, 60.0)


def noise_texture(size: int = 2048, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3), np.float32)
    for octave in range(3, 10):
        n = 2 ** octave
        small = rng.random((n, n, 3)).astype(np.float32)
        img += cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC) * (0.75 ** (octave - 3))
    img -= img.min()
    img /= img.max()
    return (img * 255).astype(np.uint8)


def _quad(x0, y0, x1, y1, z, u=(0, 0, 1, 1)):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    uv = np.array([[u[0], u[1]], [u[2], u[1]], [u[2], u[3]], [u[0], u[3]]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]]), uv


def _box(cx, cy, w, h, tex_uv):
    """Five faces (no bottom) of a box, textured from a small part of the shared texture."""
    x0, x1, y0, y1 = cx - w / 2, cx + w / 2, cy - w / 2, cy + w / 2
    faces = [([x0, y0, 0], [x1, y0, 0], [x1, y0, h], [x0, y0, h]), ([x1, y0, 0], [x1, y1, 0], [x1, y1, h], [x1, y0, h]),
             ([x1, y1, 0], [x0, y1, 0], [x0, y1, h], [x1, y1, h]), ([x0, y1, 0], [x0, y0, 0], [x0, y0, h], [x0, y1, h]),
             ([x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h])]
    V, F, UV = [], [], []
    u0, v0, s = tex_uv
    for k, f in enumerate(faces):
        V += f
        UV += [[u0, v0], [u0 + s, v0], [u0 + s, v0 + s], [u0, v0 + s]]
        F += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    return np.array(V, float), np.array(F), np.array(UV, float)


def site_mesh(seed: int = 0) -> Mesh:
    tex = noise_texture(seed=seed)
    parts = []
    v, f, uv = _quad(*LAND, 0.0)
    V, F, UV = [v], [f], [uv]
    rng = np.random.default_rng(seed + 1)
    off = 4
    for k in range(6):
        cx, cy = rng.uniform(-110, 110, 2)
        bv, bf, buv = _box(cx, cy, rng.uniform(15, 30), rng.uniform(8, 25), (rng.uniform(0, 0.8), rng.uniform(0, 0.8), 0.15))
        V.append(bv)
        F.append(bf + off)
        UV.append(buv)
        off += len(bv)
    parts.append(MeshPart(np.concatenate(V), np.concatenate(F), uv=np.concatenate(UV), texture=tex, name="land"))
    wv, wf, _ = _quad(*WATER, 0.0)
    parts.append(MeshPart(wv, wf, colors=np.tile(np.array([[40, 70, 120]], np.uint8), (4, 1)), name="water"))
    return Mesh(parts)


def build_site(root: Path, queries: list[dict], seed: int = 0) -> Project:
    """A project with model/reference.obj, queries rendered at the given poses, truth and cameras.

    Each query dict: name (relative to images/), center (x, y, z), yaw, pitch, roll (true DJI
    angles) and optional prior_ypr (the angles written to its XMP; default = truth + 0.3 deg noise).
    """
    from gtkit.render.renderer import Renderer

    frame = GeoFrame.for_lonlat(8.54, 47.37, 400.0)
    proj = Project.create(root, frame, name="synthetic")
    P = proj.paths
    mesh = site_mesh(seed)
    obj = P.model / "reference.obj"
    write_obj(obj, mesh)  # stored = world; the sidecar offset = the origin
    write_offset_sidecar(obj, frame.crs_spec, frame.origin)
    r = Renderer(mesh)
    truth, cams = {}, {}
    rng = np.random.default_rng(seed + 7)
    try:
        for q in queries:
            pose = Pose.from_dji(q["yaw"], q["pitch"], q["roll"], np.asarray(q["center"], float))
            rgb = r.render(QUERY_CAM, pose).rgb
            prior = q.get("prior_ypr") or [a + rng.normal(0, 0.3) for a in (q["yaw"], q["pitch"], q["roll"])]
            lon, lat, h = frame.local_to_wgs84(np.asarray(q["center"], float))
            write_jpeg_with_meta(P.images / q["name"], rgb, lat=lat, lon=lon, alt=h, quality=95,
                                 dji={"GimbalYawDegree": prior[0], "GimbalPitchDegree": prior[1],
                                      "GimbalRollDegree": prior[2]})
            truth[q["name"]] = pose
            cams[q["name"]] = QUERY_CAM
    finally:
        r.release()
    write_poses(P.truth / "poses.txt", truth)
    write_intrinsics(P.truth / "intrinsics.txt", cams)
    write_intrinsics(P.cameras, cams)
    return proj


def default_queries() -> list[dict]:
    """Six ordinary queries, one over water, one whose IMU pitch is 60 deg off."""
    qs = [
        dict(name="queries/seq1/0001_W.jpg", center=(-60.0, -40.0, 118.0), yaw=10.0, pitch=-88.0, roll=0.0),
        dict(name="queries/seq1/0002_W.jpg", center=(30.0, 20.0, 125.0), yaw=95.0, pitch=-85.0, roll=0.5),
        dict(name="queries/seq1/0003_W.jpg", center=(45.0, -70.0, 112.0), yaw=-170.0, pitch=-89.0, roll=0.0),
        dict(name="queries/seq1/0004_W.jpg", center=(-20.0, -110.0, 115.0), yaw=5.0, pitch=-48.0, roll=1.0),
        dict(name="queries/seq1/0005_W.jpg", center=(80.0, 40.0, 122.0), yaw=-85.0, pitch=-50.0, roll=-0.5),
        dict(name="queries/seq1/0006_W.jpg", center=(-100.0, 60.0, 120.0), yaw=-95.0, pitch=-87.0, roll=0.0),
        dict(name="queries/seq2/0001_W.jpg", center=(215.0, 0.0, 110.0), yaw=0.0, pitch=-90.0, roll=0.0),   # water
        dict(name="queries/seq2/0002_W.jpg", center=(0.0, 60.0, 118.0), yaw=180.0, pitch=-60.0, roll=0.0,
             prior_ypr=[180.0, 0.0, 0.0]),                                                                   # IMU 60 off
    ]
    return qs
