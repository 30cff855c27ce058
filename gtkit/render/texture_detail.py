"""Texture detail a set of views can show: textures finer than that are halved when they are loaded.

A 640 x 480 database view from 100 m above the ground sees 10-30 cm a pixel. Texture levels finer
than a view's pixel are never sampled (mipmapping picks the level whose texel matches the pixel's
footprint), yet they are read, decoded, uploaded and held. A model textured from full-size photos
at 2-3 cm carries 2 such levels; the samples' and Brighton Beach's built models (0.18 and 0.065 m
texels) carry none, so on them nothing is halved (their tile memory was the texture boxes, see
:mod:`gtkit.io.texture_atlas`).

The finest footprint a pixel has on a surface ``d`` metres away is ``d * cos(t)**2 / f`` (``t`` the
ray's angle off the optical axis, ``f`` the focal length in pixels: the pixel's angular size along
the radial direction), and no surface of a part lies nearer to a camera at height ``z_cam`` than
``z_cam - top`` (``top`` the part's highest vertex), so a part's texture can be halved while its texel
stays at or under ``(z_cam - top) * min cos(t)**2 / f`` without changing which texel values a view
samples (up to how the halved levels are computed: box filter here, the driver's mipmap generator
there). A part whose top is at or above the lowest camera is never coarsened.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera


@dataclass(frozen=True)
class TextureDetail:
    """What the views that will draw a model can show."""

    lowest_camera_z: float    # world z of the lowest camera centre
    pixel_angle: float        # the smallest angle a pixel subtends (rad): cos(corner)**2 / focal

    @classmethod
    def for_views(cls, camera: Camera, lowest_camera_z: float) -> "TextureDetail":
        """For views of ``camera`` (pinhole; distortion ignored) from at or above ``lowest_camera_z``."""
        f = max(camera.fx, camera.fy)
        dx = max(camera.cx, camera.width - camera.cx)
        dy = max(camera.cy, camera.height - camera.cy)
        cos2 = f * f / (f * f + dx * dx + dy * dy)
        return cls(float(lowest_camera_z), float(cos2 / f))

    def texel_limit(self, top_z: float) -> float:
        """The largest texel (m) a part whose highest point is ``top_z`` may have; 0 = keep as is."""
        return max(0.0, self.lowest_camera_z - float(top_z)) * self.pixel_angle


def part_texel(part) -> float | None:
    """The median world size of one texel (m) over a textured part's faces (None: no texture)."""
    if part.texture is None or part.uv is None or len(part.faces) == 0:
        return None
    V, F, uv = part.vertices, np.asarray(part.faces), np.asarray(part.uv, float)
    a3 = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    h, w = part.texture.shape[:2]
    t = uv[F] * (w, h)
    a2 = 0.5 * np.abs((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                      - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1]))
    ok = (a2 > 1e-9) & (a3 > 0)
    if not ok.any():
        return None
    return float(np.median(np.sqrt(a3[ok] / a2[ok])))


def halvings(texel: float, limit: float, size: int) -> int:
    """How many times a texture of ``texel`` metres can be halved staying at or under ``limit``
    (and at least 1 texel a side)."""
    if limit <= 0 or texel <= 0:
        return 0
    n = int(np.floor(np.log2(limit / texel) + 1e-9))
    return int(np.clip(n, 0, max(0, int(np.log2(max(size, 1))))))


def coarsen(part, detail: TextureDetail | None):
    """``part`` with its texture halved as often as ``detail`` allows (the part itself when not)."""
    if detail is None:
        return part
    texel = part_texel(part)
    if texel is None:
        return part
    h, w = part.texture.shape[:2]
    n = halvings(texel, detail.texel_limit(part.vertices[:, 2].max()), min(h, w))
    if n == 0:
        return part
    import cv2

    k = 2 ** n
    small = cv2.resize(part.texture, (max(1, -(-w // k)), max(1, -(-h // k))), interpolation=cv2.INTER_AREA)
    return replace(part, texture=np.ascontiguousarray(small))
