"""Sample variants for marking GCPs in gtkit (issue 46): the GCPs' coordinates only, no clicks.

- ``gcp-points``: ``gcp_list.txt`` (the sample's clicks) moved to ``truth/gcp_list_sample.txt`` (for
  evaluation: the clicks a tool would be compared with); the GCPs' surveyed coordinates written as a
  surveyor delivers them, ``gcp_points.txt`` (CRS line, then ``name x y z acc_h acc_v``), and
  imported into the project (``gcp/points.txt``), as ``gtkit gcp import`` does. The photos keep their
  GPS, so the block is placed by it and every GCP is predicted from the start.
- ``gcp-points-no-gps``: the same, with the reference photos' GPS removed (the ``no-gps`` variant of
  :mod:`gtkit.synth.variants`): the block is placed once 3 GCPs are clicked in 2+ photos each.

``checkpoints``: every n-th GCP (from the 2nd) marked ``check``. Truth stays where it was.
"""
from __future__ import annotations

import shutil
from pathlib import Path

from ..io.gcp_points import GCPPoint, points_path, write_points
from ..io.odm import read_gcp_list
from .photo_metadata import strip_metadata

VARIANTS = ("gcp-points", "gcp-points-no-gps")
ACCURACY_M = (0.02, 0.03)   # a GNSS rover's stated 1-sigma horizontal / vertical accuracy


def apply_gcp_points_variant(root: str | Path, name: str = "gcp-points", checkpoint_every: int = 0) -> Path:
    """Turn the sample at ``root`` into ``name`` (see the module doc); returns the coordinates file."""
    from ..project import Project

    if name not in VARIANTS:
        raise ValueError(f"unknown GCP variant {name!r} (known: {', '.join(VARIANTS)})")
    root = Path(root)
    proj = Project.load(root)
    src = root / "gcp_list.txt"
    gcps = read_gcp_list(src, proj.frame)
    pts = [GCPPoint(g.name, g.xyz, *ACCURACY_M,
                    check=bool(checkpoint_every) and k % checkpoint_every == 1 % checkpoint_every)
           for k, g in enumerate(sorted(gcps, key=lambda g: g.name))]
    out = root / "gcp_points.txt"
    write_points(out, pts, proj.frame)
    write_points(points_path(proj.paths), pts, proj.frame)
    (root / "truth").mkdir(exist_ok=True)
    shutil.move(str(src), root / "truth" / "gcp_list_sample.txt")
    if name == "gcp-points-no-gps":   # the no-gps variant of gtkit.synth.variants
        for p in sorted((root / "images" / "reference").glob("*")):
            if p.suffix.lower() in (".jpg", ".jpeg"):
                strip_metadata(p, gps=True, focal=False)
    return out
