"""Headless OpenGL renderer (moderngl, EGL): RGB + metric depth for a camera, and top-down
orthographic RGB + height for DSM/ortho work.

One context and the uploaded mesh are reused across many views. Depth is written by the
fragment shader as float32 camera z (metres along the optical axis), so it is exact up to
float32, not quantised by the z-buffer. Pixels that see no surface are NaN.

Projection follows :mod:`gtkit.conventions`: a world point projects to the same pixel as
``Camera.project(pose.transform(X))``; a pixel's centre (j + 0.5, i + 0.5) is array[i, j].
Distorted cameras are rendered as their pinhole part, then resampled through the distortion.

Materials
    ``texture``: sample the part's texture at its uv (what a photogrammetry model is).
    ``color``: per-vertex colours.
    procedural: a GLSL function ``vec3 surface_color(vec3 p, vec3 n, vec2 uv, vec3 col, float mat)``
    given to :meth:`Renderer.add_mesh` (``p`` world position, ``n`` unit face normal), for
    scenes whose detail is defined everywhere (the sample generator's true world).
Optional sun shading (``Lighting``) multiplies the colour by ambient + diffuse from a direction.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.mesh import Mesh
from ..pose import Pose
from .frustum import boxes_in_frustum, near_far

_VERTEX = """
#version 330
uniform mat4 mvp;        // clip from world (model at its local offset)
uniform mat4 mv;         // camera from world
uniform vec3 offset;     // world position of the mesh's vertex origin
in vec3 in_pos; in vec2 in_uv; in vec3 in_col; in float in_mat;
out vec3 v_world; out vec3 v_cam; out vec2 v_uv; out vec3 v_col; out float v_mat;
void main() {
    vec4 p = vec4(in_pos, 1.0);
    gl_Position = mvp * p;
    v_cam = (mv * p).xyz;
    v_world = in_pos + offset;
    v_uv = in_uv; v_col = in_col; v_mat = in_mat;
}
"""

_FRAGMENT = """
#version 330
uniform sampler2D tex;
uniform int mode;          // 0 texture, 1 vertex colour, 2 procedural
uniform int value_mode;    // 0: write camera z (perspective depth); 1: world z (height)
uniform vec3 sun_dir;      // unit, pointing towards the sun; zero = no shading
uniform float ambient;
uniform float gain;
in vec3 v_world; in vec3 v_cam; in vec2 v_uv; in vec3 v_col; in float v_mat;
layout(location=0) out vec4 out_rgb;
layout(location=1) out float out_value;
%(PROCEDURAL)s
void main() {
    vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    if (n.z < 0.0 && abs(n.z) > 0.2) n = -n;
    vec3 c;
    if (mode == 0) c = texture(tex, v_uv).rgb;
    else if (mode == 1) c = v_col;
    else c = surface_color(v_world, n, v_uv, v_col, v_mat);
    if (dot(sun_dir, sun_dir) > 0.0) {
        float d = abs(dot(n, sun_dir));
        c *= ambient + (1.0 - ambient) * d;
    }
    out_rgb = vec4(clamp(c * gain, 0.0, 1.0), 1.0);
    out_value = value_mode == 0 ? v_cam.z : v_world.z;
}
"""

_NO_PROCEDURAL = "vec3 surface_color(vec3 p, vec3 n, vec2 uv, vec3 col, float mat) { return col; }"


@dataclass(frozen=True)
class Lighting:
    """Sun shading: direction towards the sun (world), ambient share, exposure gain."""

    sun_dir: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ambient: float = 1.0
    gain: float = 1.0


NO_LIGHT = Lighting()


@dataclass
class RenderResult:
    rgb: np.ndarray | None     # (H, W, 3) uint8
    depth: np.ndarray          # (H, W) float32: camera z in metres (or world height in ortho); NaN = nothing

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.depth)


_CTX_LOCK = threading.Lock()
_SHARED_CTX = None


def gl_context():
    """The process-wide headless EGL context (created once)."""
    global _SHARED_CTX
    with _CTX_LOCK:
        if _SHARED_CTX is None:
            import moderngl

            try:
                _SHARED_CTX = moderngl.create_standalone_context(backend="egl")
            except Exception as e:  # noqa: BLE001 - any failure here means no headless GL
                raise GtkitError(f"cannot create a headless OpenGL (EGL) context: {e}. "
                                 "Run scripts/setup.sh to install Mesa's EGL packages.") from None
        return _SHARED_CTX


class _Part:
    def __init__(self, ctx, prog, part, mode: int, origin=None, anisotropy: float = 8.0):
        # keep float32 vertex values small; a shared ``origin`` makes split meshes render identically
        self.offset = part.vertices.mean(0) if origin is None else np.asarray(origin, dtype=np.float64)
        v = (part.vertices - self.offset).astype("f4")
        n = len(v)
        uv = part.uv.astype("f4") if part.uv is not None else np.zeros((n, 2), "f4")
        col = (part.colors.astype("f4") / 255.0) if part.colors is not None else np.full((n, 3), 0.7, "f4")
        mat = part.material.astype("f4") if part.material is not None else np.zeros(n, "f4")
        data = np.concatenate([v, uv, col, mat[:, None]], axis=1).astype("f4")
        self.vbo = ctx.buffer(data.tobytes())
        self.ibo = ctx.buffer(np.asarray(part.faces, dtype="i4").tobytes())
        fmt, names = [], []
        for name, k in (("in_pos", 3), ("in_uv", 2), ("in_col", 3), ("in_mat", 1)):
            if name in prog:  # the GLSL compiler drops attributes a shader does not use
                fmt.append(f"{k}f")
                names.append(name)
            else:
                fmt.append(f"{4 * k}x")
        self.vao = ctx.vertex_array(prog, [(self.vbo, " ".join(fmt), *names)],
                                    index_buffer=self.ibo, index_element_size=4)
        self.prog = prog
        self.mode = mode
        self.texture = None
        if mode == 0:
            tex = np.ascontiguousarray(part.texture[::-1])  # GL's first row is the bottom
            self.texture = ctx.texture((tex.shape[1], tex.shape[0]), 3, tex.tobytes())
            self.texture.build_mipmaps()
            import moderngl

            self.texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            self.texture.anisotropy = anisotropy
        self.bounds = np.stack([part.vertices.min(0), part.vertices.max(0)])
        self.n_triangles = len(part.faces)

    def release(self):
        for o in (self.vao, self.vbo, self.ibo, self.texture):
            if o is not None:
                o.release()


def union_box(boxes: np.ndarray) -> np.ndarray:
    """(2, 3) box around (N, 2, 3) boxes."""
    return np.stack([boxes[:, 0].min(0), boxes[:, 1].max(0)])


class Renderer:
    """Renders uploaded meshes for many cameras. Not thread-safe; one per thread."""

    MAX_FBO = 4096

    def __init__(self, mesh: Mesh | None = None, procedural_glsl: str | None = None, anisotropy: float = 8.0):
        # anisotropy: texture filtering (1 = trilinear only). Mesa's software rasteriser (llvmpipe, the
        # CPU path) filters anisotropically at a cost that grows with the texel footprint: on the small
        # sample 15 -> 8 ms CPU a database view with 1, and 800 -> 60 ms on a view whose facades have
        # stretched texture coordinates (a render-db stall). Overlays keep 8 (sharper obliques).
        self.anisotropy = anisotropy
        self.ctx = gl_context()
        self._progs: dict[str, object] = {}
        self._parts: list[_Part] = []
        self._fbos: dict[tuple[int, int], tuple] = {}
        if mesh is not None:
            self.add_mesh(mesh, procedural_glsl)

    # --- scene ---------------------------------------------------------------------
    def _program(self, glsl: str | None):
        key = glsl or ""
        if key not in self._progs:
            frag = _FRAGMENT % {"PROCEDURAL": glsl or _NO_PROCEDURAL}
            try:
                self._progs[key] = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=frag)
            except Exception as e:  # noqa: BLE001 - GLSL compile errors
                raise GtkitError(f"shader failed to compile: {e}") from None
        return self._progs[key]

    def add_mesh(self, mesh: Mesh, procedural_glsl: str | None = None, origin=None) -> list[int]:
        """Upload a mesh; returns the ids of its parts. ``procedural_glsl`` shades every part.
        ``origin`` (world point, optional) is subtracted from vertices before the float32
        upload instead of each part's mean: pieces of one mesh uploaded with the same origin
        render bit-identically to the whole mesh uploaded with it."""
        return self.add_parts(mesh.parts, procedural_glsl, origin)

    def add_parts(self, parts, procedural_glsl: str | None = None, origin=None) -> list[int]:
        """Upload :class:`~gtkit.io.mesh.MeshPart`s one after another, as :meth:`add_mesh`;
        ``parts`` may be a generator (:meth:`gtkit.io.obj_geometry.ObjGeometry.parts`), so that
        only the part being uploaded (its decoded texture) is held besides what is uploaded."""
        prog = self._program(procedural_glsl)
        ids = []
        for part in parts:
            mode = 2 if procedural_glsl else (0 if part.texture is not None and part.uv is not None else 1)
            self._parts.append(_Part(self.ctx, prog, part, mode, origin, self.anisotropy))
            ids.append(len(self._parts) - 1)
            del part
        return ids

    def clear(self) -> None:
        for p in self._parts:
            if p is not None:
                p.release()
        self._parts = []

    def remove_parts(self, ids) -> None:
        """Free the GPU memory of some parts (tile streaming); their ids are never reused."""
        for i in ids:
            if self._parts[i] is not None:
                self._parts[i].release()
                self._parts[i] = None

    def _live(self) -> list[int]:
        return [i for i, p in enumerate(self._parts) if p is not None]

    def release(self) -> None:
        self.clear()
        for fbo, *atts in self._fbos.values():
            fbo.release()
            for a in atts:
                a.release()
        self._fbos = {}

    @property
    def n_triangles(self) -> int:
        return sum(p.n_triangles for p in self._parts if p is not None)

    def boxes(self) -> np.ndarray:
        """(N, 2, 3) world bounding boxes of the uploaded parts."""
        live = self._live()
        return np.stack([self._parts[i].bounds for i in live]) if live else np.zeros((0, 2, 3))

    def bounds(self) -> np.ndarray:
        if not self._live():
            raise GtkitError("renderer has no mesh")
        return union_box(self.boxes())

    # --- targets -------------------------------------------------------------------
    def _fbo(self, w: int, h: int):
        if (w, h) not in self._fbos:
            if w > self.MAX_FBO or h > self.MAX_FBO:
                raise GtkitError(f"render size {w}x{h} exceeds {self.MAX_FBO} pixels a side")
            color = self.ctx.renderbuffer((w, h), 4)
            value = self.ctx.renderbuffer((w, h), 1, dtype="f4")
            depth = self.ctx.depth_renderbuffer((w, h))
            fbo = self.ctx.framebuffer(color_attachments=[color, value], depth_attachment=depth)
            self._fbos[(w, h)] = (fbo, color, value, depth)
        return self._fbos[(w, h)][0]

    def _draw(self, w, h, world_to_clip, world_to_cam, value_mode, lighting, parts, with_rgb=True):
        import moderngl

        fbo = self._fbo(w, h)
        fbo.use()
        self.ctx.viewport = (0, 0, w, h)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        nan = np.float32(np.nan)
        for i in parts:
            p = self._parts[i]
            T = np.eye(4)
            T[:3, 3] = p.offset
            prog = p.prog
            prog["mvp"].write((world_to_clip @ T).T.astype("f4").tobytes())
            if "mv" in prog:
                prog["mv"].write((world_to_cam @ T).T.astype("f4").tobytes())
            for name, val in (("offset", tuple(p.offset)), ("mode", p.mode), ("value_mode", value_mode),
                              ("sun_dir", tuple(lighting.sun_dir)), ("ambient", lighting.ambient),
                              ("gain", lighting.gain)):
                if name in prog:
                    prog[name].value = val
            if p.texture is not None:
                p.texture.use(0)
                if "tex" in prog:
                    prog["tex"].value = 0
            p.vao.render(moderngl.TRIANGLES)
        value = np.frombuffer(fbo.read(components=1, attachment=1, dtype="f4"), dtype=np.float32)
        value = value.reshape(h, w)[::-1].copy()
        # background: the colour buffer's alpha stays 0 where nothing was drawn
        rgba = np.frombuffer(fbo.read(components=4, attachment=0), dtype=np.uint8).reshape(h, w, 4)[::-1]
        value[rgba[..., 3] == 0] = nan
        rgb = np.ascontiguousarray(rgba[..., :3]) if with_rgb else None
        return rgb, value

    # --- perspective -----------------------------------------------------------------
    @staticmethod
    def projection(cam: Camera, near: float, far: float) -> np.ndarray:
        """OpenGL clip-from-camera for an OpenCV camera (COLMAP pixel convention)."""
        W, H = cam.width, cam.height
        P = np.zeros((4, 4))
        P[0, 0] = 2 * cam.fx / W
        P[0, 2] = 2 * cam.cx / W - 1
        P[1, 1] = -2 * cam.fy / H
        P[1, 2] = 1 - 2 * cam.cy / H
        P[2, 2] = (far + near) / (far - near)
        P[2, 3] = -2 * far * near / (far - near)
        P[3, 2] = 1.0
        return P

    def render(self, camera: Camera, pose: Pose, *, lighting: Lighting = NO_LIGHT, with_rgb: bool = True,
               parts: list[int] | None = None, near: float | None = None, far: float | None = None) -> RenderResult:
        """RGB (uint8) and depth (float32 metres along the optical axis, NaN = background)."""
        drawn = self._live() if parts is None else parts
        if not drawn:
            raise GtkitError("renderer has no mesh to draw")
        pin = camera.pinhole_part()
        boxes = np.stack([self._parts[i].bounds for i in drawn])
        n, f = near_far(union_box(boxes), pose)
        if parts is None:  # all parts: those whose box is outside the view's frustum are not drawn
            drawn = [i for i, seen in zip(drawn, boxes_in_frustum(boxes, pin, pose)) if seen]
            if not drawn:
                return RenderResult(np.zeros((camera.height, camera.width, 3), np.uint8) if with_rgb else None,
                                    np.full((camera.height, camera.width), np.nan, np.float32))
        P = self.projection(pin, near or n, far or f)
        rgb, depth = self._draw(pin.width, pin.height, P @ pose.matrix, pose.matrix, 0, lighting, drawn, with_rgb)
        if camera.has_distortion:
            rgb, depth = distort_images(camera, rgb, depth)
        return RenderResult(rgb, depth)

    # --- orthographic top-down ---------------------------------------------------------
    def render_ortho(self, xmin: float, ymin: float, xmax: float, ymax: float, gsd: float, *,
                     lighting: Lighting = NO_LIGHT, with_rgb: bool = True, parts: list[int] | None = None,
                     tile: int = 2048, zrange: tuple[float, float] | None = None) -> RenderResult:
        """Top-down view of [xmin, xmax] x [ymin, ymax] (world) at ``gsd`` metres per pixel.

        Returns RGB and the *highest* surface height per pixel (world z), NaN where empty.
        Pixel (i, j) covers x in [xmin + j*gsd, xmin + (j+1)*gsd], y from ymax downward; its
        value is sampled at the pixel centre. Large rasters are rendered in tiles; a tile that no
        drawn part's box reaches is left empty without drawing. ``zrange`` (lowest, highest world
        z; default: the uploaded parts') sets the depth range, so a model drawn piece by piece
        gets the depth values of the whole model drawn at once.
        """
        parts = self._live() if parts is None else parts
        W = int(round((xmax - xmin) / gsd))
        H = int(round((ymax - ymin) / gsd))
        if W <= 0 or H <= 0:
            raise GtkitError(f"empty orthographic extent {W}x{H} pixels")
        if zrange is None:
            b = self.bounds()
            zrange = (float(b[0, 2]), float(b[1, 2]))
        ztop, zbot = float(zrange[1]) + 10.0, float(zrange[0]) - 10.0
        boxes = np.stack([self._parts[i].bounds for i in parts]) if parts else np.zeros((0, 2, 3))
        out_h = np.full((H, W), np.nan, np.float32)
        out_rgb = np.zeros((H, W, 3), np.uint8) if with_rgb else None
        # camera looking straight down: x_cam = east, y_cam = south, z_cam = down
        R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
        for r0 in range(0, H, tile):
            for c0 in range(0, W, tile):
                h, w = min(tile, H - r0), min(tile, W - c0)
                x0, x1 = xmin + c0 * gsd, xmin + (c0 + w) * gsd
                y1, y0 = ymax - r0 * gsd, ymax - (r0 + h) * gsd
                if not np.any((boxes[:, 0, 0] <= x1) & (boxes[:, 1, 0] >= x0)
                              & (boxes[:, 0, 1] <= y1) & (boxes[:, 1, 1] >= y0)):
                    continue  # nothing drawn here: stays empty (NaN, black)
                V = np.eye(4)
                V[:3, :3] = R
                V[:3, 3] = -R @ np.array([0.0, 0.0, ztop])
                # camera coords: x in [x0, x1], y = -world y in [-y1, -y0], z = ztop - world z
                P = np.eye(4)
                P[0, 0], P[0, 3] = 2 / (x1 - x0), -(x1 + x0) / (x1 - x0)
                P[1, 1], P[1, 3] = -2 / (y1 - y0), -(y1 + y0) / (y1 - y0)  # -y_cam = world y; top row = y1
                P[2, 2], P[2, 3] = 2 / (ztop - zbot), -1.0
                rgb, val = self._draw(w, h, P @ V, V, 1, lighting, parts, with_rgb)
                out_h[r0:r0 + h, c0:c0 + w] = val
                if with_rgb:
                    out_rgb[r0:r0 + h, c0:c0 + w] = rgb
        return RenderResult(out_rgb, out_h)


def distort_images(camera: Camera, rgb: np.ndarray | None, depth: np.ndarray):
    """Resample images rendered with ``camera.pinhole_part()`` into the distorted camera.

    Depth is resampled by nearest neighbour (no blending across edges) and scaled from the
    pinhole's z, which is unchanged by distortion (z along the optical axis)."""
    import cv2

    from ..conventions import index_to_pixel, pixel_to_index

    h, w = camera.height, camera.width
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    uv = index_to_pixel(np.stack([jj, ii], axis=-1))
    xn = camera.image_to_world(uv)
    pin = camera.pinhole_part()
    src = pixel_to_index(pin.world_to_image(xn)).astype(np.float32)
    mx, my = src[..., 0], src[..., 1]
    out_rgb = None
    if rgb is not None:
        out_rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out_d = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return out_rgb, out_d
