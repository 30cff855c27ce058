"""gtkit's plain mesh type: a :class:`Mesh` is a list of :class:`MeshPart` (triangles with a texture or
vertex colours, world frame). Kept apart from the readers (:mod:`gtkit.io.mesh`,
:mod:`gtkit.io.obj_geometry`) so each reader builds parts without importing the other."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class MeshPart:
    """One drawable piece: triangles with either a texture (uv + image) or vertex colours."""

    vertices: np.ndarray                 # (N, 3) float64, world frame
    faces: np.ndarray                    # (M, 3) int
    uv: np.ndarray | None = None         # (N, 2) float, OpenGL convention (v up)
    texture: np.ndarray | None = None    # (H, W, 3) uint8, row 0 = top of the image
    colors: np.ndarray | None = None     # (N, 3) uint8
    material: np.ndarray | None = None   # (N,) float32 material id (procedural shading)
    name: str = ""


@dataclass
class Mesh:
    parts: list[MeshPart] = field(default_factory=list)

    @property
    def n_triangles(self) -> int:
        return sum(len(p.faces) for p in self.parts)

    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner."""
        v = np.concatenate([p.vertices for p in self.parts])
        return np.stack([v.min(0), v.max(0)])

    def translated(self, d) -> "Mesh":
        d = np.asarray(d, dtype=np.float64)
        return Mesh([MeshPart(p.vertices + d, p.faces, p.uv, p.texture, p.colors, p.material, p.name)
                     for p in self.parts])

    def to_trimesh(self):
        """A single trimesh.Trimesh (geometry only, parts concatenated)."""
        import trimesh

        verts, faces, off = [], [], 0
        for p in self.parts:
            verts.append(p.vertices)
            faces.append(p.faces + off)
            off += len(p.vertices)
        return trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
