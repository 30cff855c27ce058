"""What the 3D view draws and at what size (:class:`ViewSettings`), apart from the scene code so the
model cache (:mod:`gtkit.view.model`), the scene (:mod:`gtkit.view.scene`) and its child process
(:mod:`gtkit.view.process`) read it without importing one another in a circle."""
from __future__ import annotations

from dataclasses import dataclass

LAYERS = ("model", "reference", "queries", "gcps", "tiepoints", "targets")
SNAPSHOTS = ("oblique", "top")


@dataclass
class ViewSettings:
    max_triangles: int = 60_000       # the model is decimated to at most this many triangles (frame time
                                      # on CPU rendering grows with them; 60k at 1280x800: see docs/view.md)
    width: int = 1280                 # snapshot size, pixels
    height: int = 800
    frustum_m: float | None = None    # frustum depth; default 3 % of the site's diagonal
    residual_scale: float = 50.0      # GCP residual vectors drawn this many times longer
    snapshots: tuple[str, ...] = SNAPSHOTS
    layers: tuple[str, ...] = LAYERS  # what is drawn ("tracks" is taken for "targets")
    legend: bool = True
