"""The reference block's georegistration as a step of its own (issue 57): a GCP click or a ``geo.txt``
edit re-runs seconds of work, not the SfM.

``gtkit sfm SITE --block reference`` runs two steps, each with its own fingerprint:

1. **mapping** (features, matches, the mapper, the final intrinsics BA): fingerprinted on the photos,
   ``cameras.txt``, the CRS and the SfM settings other than ``[sfm.georegister]`` and
   ``hold_by_positions`` (:func:`mapping_key`). Its unplaced models are kept in
   ``work/sfm_reference/mapped/`` (``models/<k>/``, pycolmap binary, and ``mapped.json``: the record
   with the key, what the mapper did, each model's photos, the photos' match diagnostics).
2. **georegistration** (the Sim(3) by GPS and GCPs, :func:`georegister_models`; the pose-prior BA that
   holds the block to its positions; the block's model, poses, intrinsics, ``block.json`` and the
   reference report): it reads ``gcp_list.txt``, ``geo.txt``, ``[sfm.georegister]`` and the mapped
   models, and runs whenever the stage's record does not match (its inputs include both files).

What ``geo.txt`` means for each step: its positions pair the photos for matching and weakly hold
the incremental mapper's BA; a seeded block (RTK positions + gimbal attitude) is made from them, each
photo starting at its own (gtkit.sfm.seeded). So a ``geo.txt`` edit that moves positions re-runs only
the georegistration (its Sim(3) and pose-prior BA take the new positions; ``block.json`` ``mapping``
says how far they moved since the mapping), except for a seeded block, which is mapped again
(:func:`reusable`). The mapping also re-runs when the edit changes what the mapper is
(:func:`mapping_inputs`: which photos have a position, whether the block can be seeded), and with
``--force``. Measured (docs/benchmarks.md, issue 57): after one more GCP click the block's poses are
those of a full re-run (0.0 mm, tiny, small and medium samples; the step 0.6 / 3.2 / 27 CPU s, most of
it the pose-prior BA, gtkit.sfm.prior_ba); after a position moved 0.5 m on the shared Brighton photos
(incremental mapper), 0.0006 mm from a full re-run's. Inputs that differ by rounding (geo.txt at
0.1 mm) give blocks within 0.06 mm of each other.

The annotator's GCP page shows the residuals of this same function on the same mapped models
(:func:`refit`), so what it shows is what ``gtkit sfm`` will record.
"""
from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..io.atomic import write_json
from ..io.odm import GCP, read_gcp_list
from ..project import file_fingerprint, settings_dict, settings_key
from .geometry import RegistrationError
from .georegister import check_gcp_clicks, georegister

MAPPED = "mapped"          # work/sfm_reference/mapped/: the unplaced models and their record
RECORD = "mapped.json"
log = logging.getLogger(__name__)
# SfM settings that only the georegistration reads: changing them keeps the mapping
PLACEMENT_SETTINGS = ("georegister", "hold_by_positions")


@dataclass
class MappedBlock:
    """What the mapping step hands the georegistration: the models (largest first, unplaced) and
    its record (JSON: summary fields, models_info, duplicates, the intrinsics policy, the mapper's
    record, each photo's match diagnostics, seconds)."""
    models: list[pycolmap.Reconstruction]
    record: dict = field(default_factory=dict)
    reused: bool = False


def mapping_settings(settings) -> dict:
    """The SfM settings the mapping step depends on (all but :data:`PLACEMENT_SETTINGS`)."""
    d = settings_dict(settings)
    return {k: v for k, v in d.items() if k not in PLACEMENT_SETTINGS}


def mapping_inputs(project, names: list[str], positions: dict, seedable: tuple[bool, str] | None) -> dict:
    """The mapping's inputs: the photos, cameras.txt, the CRS, and what the photos' positions decide
    about the mapper (which photos have one, whether the block can be seeded), not the positions."""
    P = project.paths
    return {"images": {n: file_fingerprint(P.images / n) for n in names},
            "cameras": file_fingerprint(P.cameras), "crs": [project.frame.crs_spec, list(project.frame.origin)],
            "positioned": sorted(positions), "seedable": None if seedable is None else bool(seedable[0])}


def mapping_key(settings, inputs: dict) -> str:
    return settings_key({"settings": mapping_settings(settings), "inputs": inputs})


def moved_positions(used: dict, now: dict) -> dict[str, float]:
    """{photo: metres} of the positions that moved more than 1 mm since the mapping used them."""
    d = {n: float(np.linalg.norm(np.asarray(now[n]) - np.asarray(used[n]))) for n in now if n in used}
    return {n: v for n, v in d.items() if v > 1e-3}


def positions_moved(used: dict, now: dict) -> dict:
    """How far the photos' positions moved since the mapping was paired (and weakly held) with them
    (``used``: the mapping record's, ``now``: geo.txt / EXIF as they are): the georegistration takes
    the new ones, the mapped shape stays (``--force`` maps again with them)."""
    moved = moved_positions(used, now)
    out = {"positions_moved_since_mapping": len(moved)}
    if moved:
        worst = max(moved, key=moved.get)
        out["largest_move_m"] = {"photo": worst, "m": round(moved[worst], 4)}
        log.info("reference block: %d photo positions moved since the mapping (largest %s: %.3f m); the "
                 "georegistration takes them, the mapped shape stays (gtkit sfm --force maps with them)",
                 len(moved), worst, moved[worst])
    return out


def reusable(mapped: MappedBlock, positions: dict) -> tuple[bool, str]:
    """Whether the georegistration may start from ``mapped`` with the photos' positions as they are now
    (the key already matched), and why not. A seeded block is made from its positions (each photo
    starts at its own, held there by a BA): a moved one re-maps. Any other block is only paired and
    weakly held by them: the georegistration takes the moved ones."""
    if (mapped.record.get("mapper_record") or {}).get("name") != "seeded":
        return True, ""
    moved = moved_positions(mapped.record.get("positions") or {}, positions)
    if not moved:
        return True, ""
    worst = max(moved, key=moved.get)
    return False, (f"{len(moved)} positions moved since the seeded mapping started from them (largest {worst}: "
                   f"{moved[worst]:.3f} m): mapped again")


def _jsonable_policy(policy: dict) -> dict:
    return {k: sorted(v) if isinstance(v, set) else v for k, v in policy.items()}


def policy_from_record(rec: dict) -> dict:
    sets = ("constant_cameras", "exif_focal", "self_calibrate")
    return {k: set(v) if k in sets else v for k, v in rec.items()}


def save_mapped(out: Path, mapped: MappedBlock, key: str) -> None:
    """The mapped models and their record under ``out/mapped/`` (the record last: a half-written
    folder is never taken for a finished mapping)."""
    d = out / MAPPED
    (d / RECORD).unlink(missing_ok=True)
    tmp = d / "models.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    for k, r in enumerate(mapped.models):
        (tmp / str(k)).mkdir(parents=True)
        r.write(tmp / str(k))
    shutil.rmtree(d / "models", ignore_errors=True)
    tmp.rename(d / "models")
    rec = dict(mapped.record)
    rec["policy"] = _jsonable_policy(rec["policy"])
    write_json(d / RECORD, {"key": key, **rec, "n_models": len(mapped.models)})


def load_mapped(out: Path, key: str | None) -> MappedBlock | None:
    """The mapped models kept in ``out/mapped/`` when their record's key is ``key`` (None: whatever
    is there); None when there are none or they were made from other inputs."""
    d = out / MAPPED
    try:
        rec = json.loads((d / RECORD).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if key is not None and rec.get("key") != key:
        return None
    try:
        models = [pycolmap.Reconstruction(str(d / "models" / str(k))) for k in range(int(rec.get("n_models", 0)))]
    except (ValueError, RuntimeError):
        return None
    rec["policy"] = policy_from_record(rec["policy"])
    return MappedBlock(models, rec, reused=True)


def block_gcps(project, names: list[str], gcps: list[GCP] | None = None) -> list[GCP]:
    """The block's GCPs (``gcp_list.txt`` when ``gcps`` is None) with their clicks named as gtkit
    names photos (ODM: the file name; gtkit: the path under images/)."""
    P = project.paths
    if gcps is None:
        gcps = read_gcp_list(P.gcp_list, project.frame) if P.gcp_list.is_file() else []
    for g in gcps:
        for c in g.clicks:
            if "/" not in c.image:
                c.image = next((n for n in names if Path(n).name == c.image), c.image)
    return gcps


def stated_gcp_accuracy(project) -> dict[str, tuple]:
    """{GCP: (stated horizontal, vertical) metres} from ``gcp/points.txt``'s accuracy columns (the
    surveyor's coordinates, ``gtkit gcp import``); {} without the file."""
    from ..io.gcp_points import load_points

    return {p.name: (p.acc_h, p.acc_v if p.acc_v is not None else p.acc_h)
            for p in load_points(project.paths, project.frame) if p.acc_h is not None}


def georegister_models(gcps: list[GCP], names: list[str], kind: str, georegister_settings, models: list,
                       models_info: list[dict], duplicate: dict, positions: dict, accuracy: dict, metas: dict,
                       summary: dict, gcp_accuracy: dict | None = None) -> list[int]:
    """Each model not a duplicate georegistered by the GPS and GCPs, in place (the first that places
    goes into ``summary``); returns the models kept (all that were placed, else the first).
    ``gcp_accuracy``: :func:`stated_gcp_accuracy` (only the accuracy claimed reads it)."""
    kept = [0]
    if gcps and kind == "reference":
        summary["gcp_clicks_outside_block"] = check_gcp_clicks(gcps, names)
    geo_models = []
    for k, r in enumerate(models):
        if k in duplicate:
            continue
        try:
            g = georegister(r, positions, gcps, georegister_settings, accuracy, metas, gcp_accuracy=gcp_accuracy)
            models_info[k]["georegistration"] = {kk: g[kk] for kk in ("n_inliers", "rmse_inliers_m", "gcp_median_err_m")}
            geo_models.append((k, g))
        except RegistrationError as e:
            models_info[k]["georegistration"] = {"error": str(e)}
    if geo_models:
        kept = [k for k, _ in geo_models]
        summary["georegistration"] = geo_models[0][1]
        summary["frame"] = "project world frame"
    else:
        summary["georegistration"] = {"error": models_info[0]["georegistration"]["error"]}
        summary["frame"] = "arbitrary SfM frame (georegistration failed)"
    return kept


class Refit:
    """The georegistration's Sim(3) over the reference block's mapped models, for a page that edits the
    clicks and for ``gtkit gcp status`` (:func:`gtkit.gcp.site.georegistration_refit` builds one): the
    models, photo metadata and positions are read once; :meth:`run` fits copies of the models to the
    GCPs with :func:`georegister_models`, the step's own function, and returns
    ``summary["georegistration"]`` as ``gtkit sfm`` records it for these clicks (the pose-prior BA that
    follows it does not enter the GCP residuals). ``available`` False (and ``why``) where the project
    has no mapped models yet. ``metas``: a function giving {photo: PhotoMeta} (called only when needed)."""

    def __init__(self, project, settings, names: list[str], metas):
        from ..photo_positions import positions_and_accuracy

        self.project, self.settings, self.names = project, settings, names
        self.mapped = load_mapped(project.paths.stage("sfm_reference"), None)
        self.available = self.mapped is not None and bool(self.mapped.models)
        self.why = "" if self.available else "no mapped reference block yet (gtkit sfm SITE --block reference)"
        if self.available:
            self.metas = metas()
            self.positions, self.accuracy = positions_and_accuracy(project, names, self.metas)

    def run(self, gcps: list[GCP] | None = None) -> dict | None:
        """The georegistration record for ``gcps`` (None: ``gcp_list.txt`` as it is now, as the step
        reads it); a failed fit: ``{"error": why}``."""
        if not self.available:
            return None
        import copy

        rec = self.mapped.record
        models = [pycolmap.Reconstruction(r) for r in self.mapped.models]
        info = copy.deepcopy(rec["models_info"])
        summary: dict = {}
        gcps = block_gcps(self.project, self.names, copy.deepcopy(gcps) if gcps is not None else None)
        georegister_models(gcps, self.names, "reference", self.settings.georegister, models, info,
                           {int(k): v for k, v in rec["duplicate"].items()}, self.positions, self.accuracy,
                           self.metas, summary, stated_gcp_accuracy(self.project))
        return summary["georegistration"]
