"""Reading a sample site's truth back (for evaluation code and tests only).

``truth/world.ply`` holds the true geometry with per-vertex pattern uv, colour and material;
``truth/world.json`` holds the GLSL ``surface_color``, the lighting of both flights and every
generator setting. :func:`true_world_renderer` rebuilds the renderer the photos came from.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.mesh import Mesh, MeshPart
from ..render.renderer import Lighting, Renderer


def read_world_ply(path: str | Path) -> Mesh:
    """The binary PLY written by :func:`gtkit.synth.generate.write_ply` as one mesh part."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("true world mesh not found", path)
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise GtkitError("not a PLY file", path)
    head = raw[:end].decode("ascii").splitlines()
    nv = int(next(h for h in head if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in head if h.startswith("element face")).split()[-1])
    vt = np.dtype([("p", "<f8", 3), ("uv", "<f4", 2), ("c", "u1", 3), ("m", "u1")])
    ft = np.dtype([("n", "u1"), ("i", "<i4", 3)])
    body = raw[end + len(b"end_header\n"):]
    if len(body) != nv * vt.itemsize + nf * ft.itemsize:
        raise GtkitError("PLY size does not match its header (not written by the sample generator?)", path)
    v = np.frombuffer(body, vt, nv)
    f = np.frombuffer(body, ft, nf, offset=nv * vt.itemsize)
    return Mesh([MeshPart(v["p"].astype(np.float64), f["i"].astype(np.int64), uv=v["uv"].astype(np.float64),
                          colors=v["c"].copy(), material=v["m"].astype(np.float32), name="world")])


def load_world_json(root: str | Path) -> dict:
    p = Path(root) / "truth" / "world.json"
    if not p.is_file():
        raise GtkitError("not a sample project (truth/world.json missing)", p)
    return json.loads(p.read_text(encoding="utf-8"))


def true_world_renderer(root: str | Path) -> tuple[Renderer, dict[str, Lighting]]:
    """A renderer of the true world (procedural shading) and the lighting of each flight."""
    d = load_world_json(root)
    mesh = read_world_ply(Path(root) / "truth" / "world.ply")
    light = {k: Lighting(tuple(v["sun_dir"]), v["ambient"], v["gain"]) for k, v in d["lighting"].items()}
    return Renderer(mesh, d["procedural_glsl"]), light
