"""The ``plain-grass`` sample variant: a large field of grass without detail, where dense matching
finds nothing and the DSM has a real gap (issue 57).

A square in the west of the reference flight's area (``share`` of the flight's width across, centred
at 30 % of that width from its western edge) is painted one plain grass colour: the terrain's
procedural texture (roads, crops, clutter, micro-detail) is replaced there by a single colour, lit by
the sun as the rest of the ground (its relief still shades it); trees, buildings and GCP targets
keep their textures. The reference photos are rendered again from the truth (same poses, cameras,
lighting, blur and noise as the generator's), their metadata (EXIF, XMP) kept byte for byte; the
query photos keep the textured ground (they are not what the DSM is made from). The sample's own
reference model is removed, so ``gtkit run`` / ``gtkit model build`` builds one from the photos.
``truth/plain_area.json`` says where the plain square is.
"""
from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from .photo_metadata import _segments

HOOK = "vec3 terrain_color(vec3 p, float fp) {\n    vec2 q = p.xy;\n"
GRASS = (0.33, 0.46, 0.21)


def plain_square(root: Path, share: float = 0.5) -> tuple[float, float, float]:
    """(centre x, centre y, half side) of the plain square, world metres (from the reference poses)."""
    from ..io.poses import read_poses
    from ..project import Paths

    truth = read_poses(Paths(root).truth_poses)
    c = np.array([p.center for n, p in truth.items() if n.startswith("reference/")])
    lo, hi = c[:, :2].min(0), c[:, :2].max(0)
    width = float(min(hi - lo))
    return float(lo[0] + 0.3 * (hi[0] - lo[0])), float(0.5 * (lo[1] + hi[1])), 0.5 * share * width


def plain_glsl(glsl: str, square: tuple[float, float, float], colour=GRASS) -> str:
    if HOOK not in glsl:
        raise ValueError("the sample's shader has no terrain_color to patch (generator changed?)")
    cx, cy, half = square
    test = (f"    if (abs(q.x - ({cx:.4f})) < {half:.4f} && abs(q.y - ({cy:.4f})) < {half:.4f}) "
            f"return vec3({colour[0]:.3f}, {colour[1]:.3f}, {colour[2]:.3f});\n")
    return glsl.replace(HOOK, HOOK + test, 1)


def _replace_pixels(path: Path, rgb: np.ndarray, quality: int) -> None:
    """``path``'s image data replaced by ``rgb`` (JPEG ``quality``), its metadata segments kept."""
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, "JPEG", quality=quality)
    old, new = path.read_bytes(), buf.getvalue()
    out = bytearray(b"\xff\xd8")
    import struct

    for marker, payload in _segments(old):          # the photo's metadata (APP1 EXIF / XMP, ...)
        if marker is not None and 0xE1 <= marker <= 0xEF:
            out += bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload
    for marker, payload in _segments(new):          # the new image (tables, frame, scan)
        if marker is None:
            out += payload
            break
        if not (0xE0 <= marker <= 0xEF):
            out += bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(bytes(out))
    tmp.replace(path)


def apply_plain_grass(root: str | Path, share: float = 0.5) -> dict:
    """Turn the sample at ``root`` into the ``plain-grass`` variant (see the module doc)."""
    from ..io.poses import read_intrinsics, read_poses
    from ..project import Paths
    from ..render.renderer import Lighting, Renderer
    from . import photos
    from .settings import settings_from_dict
    from .truth import load_world_json, read_world_ply

    root = Path(root)
    P = Paths(root)
    d = load_world_json(root)
    s = settings_from_dict(d["settings"])
    square = plain_square(root, share)
    glsl = plain_glsl(d["procedural_glsl"], square)
    light = Lighting(tuple(d["lighting"]["reference"]["sun_dir"]), d["lighting"]["reference"]["ambient"],
                     d["lighting"]["reference"]["gain"])
    truth, cams = read_poses(P.truth_poses), read_intrinsics(P.truth_intrinsics)
    r = Renderer(read_world_ply(P.truth / "world.ply"), glsl)
    rng = np.random.default_rng([int(s.seed), 57])
    rs = s.reference
    names = sorted(n for n in truth if n.startswith("reference/") and (P.images / n).is_file())
    try:
        for n in names:
            rgb, _depth, _ = photos.render_view(r, cams[n], truth[n], light)
            img = photos.degrade(rgb, rng, blur_sigma=rs.blur_sigma_px, noise_sigma=rs.noise_sigma)
            _replace_pixels(P.images / n, img, rs.jpeg_quality)
    finally:
        r.release()
    if P.model.is_dir():
        shutil.rmtree(P.model)
    info = {"square_centre_xy": [square[0], square[1]], "half_side_m": square[2], "colour": list(GRASS),
            "what": "terrain painted one plain grass colour inside the square (reference photos only)",
            "photos_rerendered": len(names)}
    (P.truth / "plain_area.json").write_text(json.dumps(info, indent=1))
    return info
