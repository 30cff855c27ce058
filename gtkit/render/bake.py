"""Texture baking in UV space: paint a mesh's texture atlas from a procedural surface colour.

The mesh is drawn with its atlas uv as the clip position, so every texel the mesh covers runs
the fragment shader once, at the interpolated *source* attributes (world position, pattern uv,
vertex colour, material id). ``fwidth`` of the world position is then the world size of a
texel, so a band-limited ``surface_color`` (see :mod:`gtkit.render.renderer`) prefilters itself.
Uses the shared EGL context of :func:`gtkit.render.renderer.gl_context`.
"""
from __future__ import annotations

import numpy as np

from ..errors import GtkitError
from .renderer import _NO_PROCEDURAL, gl_context

_BAKE_VERTEX = """
#version 330
uniform vec3 offset;
in vec2 in_atlas; in vec3 in_pos; in vec2 in_uv; in vec3 in_col; in float in_mat;
out vec3 v_world; out vec2 v_uv; out vec3 v_col; out float v_mat;
void main() {
    gl_Position = vec4(in_atlas * 2.0 - 1.0, 0.0, 1.0);
    v_world = in_pos + offset; v_uv = in_uv; v_col = in_col; v_mat = in_mat;
}
"""

_BAKE_FRAGMENT = """
#version 330
uniform float gain;
in vec3 v_world; in vec2 v_uv; in vec3 v_col; in float v_mat;
layout(location=0) out vec4 out_rgb;
%(PROCEDURAL)s
void main() {
    vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    if (n.z < 0.0 && abs(n.z) > 0.2) n = -n;
    out_rgb = vec4(clamp(surface_color(v_world, n, v_uv, v_col, v_mat) * gain, 0.0, 1.0), 1.0);
}
"""


def bake_procedural(positions: np.ndarray, faces: np.ndarray, atlas_uv: np.ndarray, size: tuple[int, int],
                    glsl: str | None, *, pattern_uv: np.ndarray | None = None, colors: np.ndarray | None = None,
                    material: np.ndarray | None = None, gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Bake ``surface_color`` into a (height, width) texture.

    positions: (N, 3) world positions evaluated by the shader (may differ from the mesh's own
    vertices, e.g. a noisy model textured from the true surface); atlas_uv: (N, 2) in [0, 1],
    OpenGL convention (v up). Returns (rgb uint8 (H, W, 3) with row 0 = top, covered mask).
    """
    import moderngl

    w, h = int(size[0]), int(size[1])
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise GtkitError(f"bake size {w}x{h} out of range")
    ctx = gl_context()
    try:
        prog = ctx.program(vertex_shader=_BAKE_VERTEX,
                           fragment_shader=_BAKE_FRAGMENT % {"PROCEDURAL": glsl or _NO_PROCEDURAL})
    except Exception as e:  # noqa: BLE001 - GLSL compile errors
        raise GtkitError(f"bake shader failed to compile: {e}") from None
    n = len(positions)
    offset = positions.mean(0)
    cols = [np.asarray(atlas_uv, "f4"), (positions - offset).astype("f4"),
            np.asarray(pattern_uv if pattern_uv is not None else np.zeros((n, 2)), "f4"),
            (np.asarray(colors, "f4") / 255.0) if colors is not None else np.full((n, 3), 0.7, "f4"),
            np.asarray(material if material is not None else np.zeros(n), "f4")[:, None]]
    data = np.concatenate(cols, axis=1).astype("f4")
    vbo = ctx.buffer(data.tobytes())
    ibo = ctx.buffer(np.asarray(faces, "i4").tobytes())
    fmt, names = [], []
    for name, k in (("in_atlas", 2), ("in_pos", 3), ("in_uv", 2), ("in_col", 3), ("in_mat", 1)):
        if name in prog:
            fmt.append(f"{k}f")
            names.append(name)
        else:
            fmt.append(f"{4 * k}x")
    vao = ctx.vertex_array(prog, [(vbo, " ".join(fmt), *names)], index_buffer=ibo, index_element_size=4)
    color = ctx.renderbuffer((w, h), 4)
    fbo = ctx.framebuffer(color_attachments=[color])
    try:
        fbo.use()
        ctx.viewport = (0, 0, w, h)
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        ctx.disable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        if "offset" in prog:
            prog["offset"].value = tuple(float(v) for v in offset)
        if "gain" in prog:
            prog["gain"].value = float(gain)
        vao.render(moderngl.TRIANGLES)
        rgba = np.frombuffer(fbo.read(components=4), dtype=np.uint8).reshape(h, w, 4)[::-1]
    finally:
        for o in (vao, vbo, ibo, fbo, color, prog):
            o.release()
    return np.ascontiguousarray(rgba[..., :3]), rgba[..., 3] > 0


def fill_seams(rgb: np.ndarray, mask: np.ndarray, pad: int = 4) -> np.ndarray:
    """Extend chart borders by about ``pad`` texels into empty texels (so mip-mapping and
    bilinear lookups near a seam do not fetch the empty background)."""
    import cv2

    img = rgb.astype(np.float32)
    m = mask.astype(np.float32)
    out = img * m[..., None]
    cover = m.copy()
    k = 3
    for _ in range(pad):
        num = cv2.blur(out, (k, k))  # empty texels hold 0, so this sums covered neighbours
        den = cv2.blur(cover, (k, k))
        new = (cover == 0) & (den > 0)
        out[new] = num[new] / den[new][:, None]
        cover = np.where(new, 1.0, cover).astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)
