"""GCP marking over a project folder: import coordinates, read and write the clicks, predict.

The coordinates live in ``gcp/points.txt`` (``gtkit gcp import``, ``gtkit init --gcp-points``), the
clicks in ``gcp_list.txt`` (OpenDroneMap format, read by ``gtkit sfm`` / ``gtkit run``): the
annotator's GCP page and these functions read both and write ``gcp_list.txt`` atomically after
every change. A project with only a ``gcp_list.txt`` (clicked elsewhere) works as before: its GCPs
and clicks are the page's. Predictions for scripts: ``work/gcp/predicted.csv``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_text
from ..io.odm import GCP, GCPClick, read_gcp_list, write_gcp_list
from .marking import CLICK_SIGMA_PX, Block, Solution, load_block, predictions_csv, solve
from ..io.gcp_points import GCPPoint, check_inside, load_points, points_path, read_points, write_points

PREDICTED = Path("work") / "gcp" / "predicted.csv"


@dataclass
class GcpSettings:
    click_sigma_px: float = CLICK_SIGMA_PX   # a click's 1-sigma error (prediction uncertainty from clicks)
    max_px: float = 4.0            # a click farther than this from its GCP's triangulated point is left out
    outside_margin_m: float = 200.0  # a GCP farther than this outside the photos' footprint is refused


def settings_for(project, cli: dict | None = None) -> GcpSettings:
    from ..settings import resolve

    return resolve(GcpSettings(), "gcp", project, cli)


def photo_name(name: str, photos: list[str]) -> str:
    """A ``gcp_list.txt`` photo name (ODM: the file name) -> gtkit's (path under images/)."""
    if "/" in name:
        return name
    return next((n for n in photos if Path(n).name == name), name)


def reference_photos(project) -> list[str]:
    from ..sfm.blocks import list_images

    P = project.paths
    return list_images(P.reference_images, P.images)


def load_marking(project) -> tuple[list[GCPPoint], dict[str, dict[str, tuple[float, float]]]]:
    """(GCP points, clicks {GCP: {photo: (x, y)}}): the imported coordinates with the clicks of
    ``gcp_list.txt``; a GCP only in ``gcp_list.txt`` is added with its coordinates there."""
    frame, P = project.frame, project.paths
    points = {p.name: p for p in load_points(P, frame)}
    clicks: dict[str, dict[str, tuple[float, float]]] = {}
    if P.gcp_list.is_file():
        photos = reference_photos(project)
        for g in read_gcp_list(P.gcp_list, frame):
            if g.name not in points:
                points[g.name] = GCPPoint(g.name, g.xyz, None, None, g.check)
            elif g.check:
                points[g.name].check = True
            for c in g.clicks:
                clicks.setdefault(g.name, {})[photo_name(c.image, photos)] = (c.x, c.y)
    return list(points.values()), clicks


def save_clicks(project, points: list[GCPPoint], clicks: dict[str, dict[str, tuple[float, float]]]) -> Path:
    """Every click as ``gcp_list.txt`` (project CRS, full-resolution pixels, check points marked),
    atomically; photos named by file name where that is unique (as ODM names them). A GCP known only
    from ``gcp_list.txt`` that has no click left is kept in ``gcp/points.txt`` (its coordinates are
    never lost with its last click)."""
    P = project.paths
    stored = {p.name for p in load_points(P, project.frame)}
    if any(p.name not in stored and not clicks.get(p.name) for p in points):
        write_points(points_path(P), points, project.frame)
    photos = reference_photos(project)
    base = [Path(n).name for n in photos]
    unique = {n for n in base if base.count(n) == 1}
    gcps = []
    for p in points:
        c = clicks.get(p.name, {})
        gcps.append(GCP(p.name, p.xyz, [GCPClick(Path(n).name if Path(n).name in unique and n in photos else n, x, y)
                                         for n, (x, y) in sorted(c.items())], p.check))
    return write_gcp_list(project.paths.gcp_list, project.frame, gcps)


def footprint(project) -> np.ndarray | None:
    """(2, 2) min / max of x, y (local frame) of where the photos were taken: the placed reference
    block's camera centres, else the photos' GPS; None when neither is known."""
    from ..io.poses import read_poses

    P = project.paths
    f = P.reference_poses
    if f.is_file():
        C = np.array([p.center for p in read_poses(f).values()])
    else:
        from ..sfm.blocks import gps_positions

        try:
            C = np.array(list(gps_positions(project, reference_photos(project)).values())).reshape(-1, 3)
        except GtkitError:
            C = np.zeros((0, 3))
    if len(C) == 0:
        return None
    return np.array([C[:, :2].min(0), C[:, :2].max(0)])


def import_points(project, file: str | Path, crs: str | None = None, settings: GcpSettings | None = None) -> dict:
    """Read ``file`` (see :mod:`gtkit.io.gcp_points`), check it against the photos' footprint and store
    it as ``gcp/points.txt``; GCPs imported before under the same names are replaced. Returns counts
    and what matched ``gcp_list.txt``."""
    settings = settings or settings_for(project)
    pts, spec = read_points(file, project.frame, crs)
    check_inside(pts, footprint(project), file, settings.outside_margin_m, "the photos' footprint")
    old = {p.name: p for p in load_points(project.paths, project.frame)}
    old.update({p.name: p for p in pts})
    write_points(points_path(project.paths), list(old.values()), project.frame)
    _, clicks = load_marking(project)
    moved = []
    if project.paths.gcp_list.is_file():
        for g in read_gcp_list(project.paths.gcp_list, project.frame):
            p = next((q for q in pts if q.name == g.name), None)
            if p is not None and np.linalg.norm(p.xyz - g.xyz) > 1e-3:
                moved.append((g.name, float(np.linalg.norm(p.xyz - g.xyz))))
    if moved:   # the surveyor's coordinates win: gcp_list.txt follows them
        points, clicks = load_marking(project)
        save_clicks(project, points, clicks)
    return {"n": len(pts), "check_points": sorted(p.name for p in pts if p.check), "crs": spec,
            "with_accuracy": sum(p.acc_h is not None for p in pts), "total": len(old),
            "clicked": sorted(n for n in clicks if n in {p.name for p in pts}),
            "coordinates_changed": moved, "stored": points_path(project.paths)}


def current_solution(project, block: Block | None = None, settings: GcpSettings | None = None) -> Solution:
    settings = settings or settings_for(project)
    block = block or load_block(project.paths)
    points, clicks = load_marking(project)
    if not points:
        raise GtkitError("no GCPs: import their coordinates first (gtkit gcp import SITE FILE) or give a gcp_list.txt",
                         project.paths.root)
    return solve(block, points, clicks, settings.click_sigma_px, settings.max_px)


def georegistration_refit(project, sfm_settings=None):
    """The georegistration step's own refit over the mapped reference block
    (:class:`gtkit.sfm.georeg_step.Refit`): what ``gtkit sfm`` will record for the clicks in
    ``gcp_list.txt``. ``sfm_settings``: the ``[sfm]`` settings (None: as the project resolves them)."""
    from ..sfm.blocks import photo_metas
    from ..sfm.georeg_step import Refit
    from ..stages import settings_for as stage_settings

    s = sfm_settings if sfm_settings is not None else stage_settings("sfm_reference", project)
    names = reference_photos(project)
    return Refit(project, s, names, lambda: photo_metas(project, names))


def refit_lines(geo: dict | None) -> list[str]:
    """The georegistration record's GCP lines, as ``gtkit gcp status`` prints them."""
    if geo is None:
        return []
    if "error" in geo:
        return [f"georegistration: {geo['error']}"]
    out = [f"georegistration (as gtkit sfm records it): fitted to {geo.get('fitted_to') or geo.get('used')}, "
           f"RMSE {geo.get('rmse_inliers_m', float('nan')):.3f} m"]
    for name, g in (geo.get("gcp_residuals") or {}).items():
        kind = "check point" if g.get("check") else ("GCP (outlier)" if g.get("outlier") else "GCP")
        out.append(f"  {kind} {name}: " + (f"{g['err_m']:.3f} m (dx {g['dx_m']:+.3f} dy {g['dy_m']:+.3f} dz {g['dz_m']:+.3f})"
                                          if g["status"] == "ok" else g["reason"]))
    for key, what in (("gcp_rmse_m", "GCP RMSE"), ("checkpoint_rmse_m", "check point RMSE")):
        if geo.get(key) is not None:
            out.append(f"  {what} {geo[key]:.3f} m")
    return out


def predict(project, settings: GcpSettings | None = None) -> tuple[Solution, Path]:
    """``gtkit gcp predict``: every GCP's predicted position in every photo that sees it, to
    ``work/gcp/predicted.csv`` (gcp, photo, x, y, sigma_px, source, where: in the photo or near the edge)."""
    sol = current_solution(project, settings=settings)
    out = project.paths.root / PREDICTED
    write_text(out, predictions_csv(sol))
    return sol, out
