"""Import stages: bring a survey delivery's reference model and existing poses into a project.

``import_model(project, source, settings)`` accepts
    * a tiled OBJ model (a folder with ``metadata.xml`` and ``Tile_+XXX_+YYY`` tiles,
      :mod:`gtkit.io.tiled`): referenced in place, its spatial index cached in ``work/import/``;
    * an OpenDroneMap project (or its ``odm_textured_model_geo.obj``, :mod:`gtkit.io.odm_model`);
    * a single OBJ/PLY/GLB mesh with an offset sidecar or ``crs``/``offset`` settings;
    * a point cloud (LAS/LAZ, PLY without faces, :mod:`gtkit.io.pointcloud`) for DSM-only work.
    Single meshes are written to ``model/reference.obj`` (+ offset sidecar) in the project frame,
    point clouds to ``model/points.ply`` (+ sidecar), so later stages find them where they look.

``import_poses(project, source, settings)`` accepts a ContextCapture BlocksExchange XML (or a
``.xmlz``), a COLMAP model folder (text or binary), a kapture folder (read by kapture's loader), or
an hloc/UAVD4L pose file (with ``settings.intrinsics``, else ``queries_with_intrinsics.txt`` beside
it, else the project's ``cameras.txt``); it writes ``work/import/poses.txt`` + ``intrinsics.txt``
(gtkit's formats, project frame) and ``work/import/colmap/`` (a COLMAP model that opens in COLMAP's
GUI). What ``gtkit export dataset`` writes reads back this way (its hloc file, COLMAP model or
kapture folder); such a source's frame is checked against the project's (``dataset.json``), and its
poses' covariances (``pseudo_gt_uncertainty.txt``) come along into ``work/import/covariances.txt``.

Both record what was imported and from where in ``project.toml`` (``[imports.model]``,
``[imports.poses]``).
"""
from __future__ import annotations

import logging
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .errors import GtkitError
from .io.poses import INTRINSICS, POSES
from .project import Project

log = logging.getLogger(__name__)

STAGE = "import"


@dataclass
class ModelImportSettings:
    crs: str | None = None          # CRS of a single mesh / point cloud when neither file nor sidecar states one
    offset: tuple | None = None     # added to stored coordinates to give CRS coordinates (default: 0, or the file's)
    copy: bool = True               # write single meshes / point clouds into model/ (tiled models stay in place)
    overwrite: bool = False         # replace an existing model/reference.obj or model/points.ply


@dataclass
class PoseImportSettings:
    intrinsics: str | None = None   # intrinsics file (name MODEL W H params) for an hloc/UAVD4L pose file
    drop_k3: bool = False           # BlocksExchange: ignore a non-zero K3 (no gtkit camera model has it)
    colmap_binary: bool = True      # the COLMAP export's format


def _project(p) -> Project:
    return p if isinstance(p, Project) else Project.load(p)


def detect_model_kind(source: Path) -> str:
    from .io.odm_model import find_odm_model
    from .io.pointcloud import POINT_SUFFIXES, is_point_cloud

    source = Path(source)
    if not source.exists():
        raise GtkitError("model source not found", source)
    if (source.is_dir() and (source / "metadata.xml").is_file()) or source.name == "metadata.xml":
        return "tiled"
    if find_odm_model(source) is not None:
        return "odm"
    if source.is_dir():
        raise GtkitError("folder is neither a tiled model (metadata.xml) nor an OpenDroneMap project", source)
    s = source.suffix.lower()
    if is_point_cloud(source):
        return "points"
    if s in POINT_SUFFIXES or s in (".obj", ".glb", ".gltf", ".off", ".stl"):
        return "mesh"
    raise GtkitError("unknown model format (expected a tiled model folder, an ODM project, OBJ/PLY/GLB, LAS/LAZ)",
                     source)


def _write_single_mesh(project: Project, mesh, settings: ModelImportSettings) -> Path:
    from .io.mesh import write_obj, write_offset_sidecar

    out = project.paths.model / "reference.obj"
    if out.exists() and not settings.overwrite:
        raise GtkitError("the project already has a reference model (use --overwrite to replace it)", out)
    write_obj(out, mesh)
    write_offset_sidecar(out, project.frame.crs_spec, project.frame.origin)
    return out


def import_model(project, source: str | Path, settings: ModelImportSettings | None = None) -> dict:
    """Read a delivered model into the project's frame (see the module doc); returns a summary."""
    project = _project(project)
    settings = settings or ModelImportSettings()
    source = Path(source).resolve()
    frame = project.frame
    kind = detect_model_kind(source)
    info: dict = {"format": kind}
    if kind == "tiled":
        from .io.tiled import read_tiled

        index = project.paths.stage(STAGE) / "tiles_index.json"
        model = read_tiled(source, frame, index_path=index, write_index=True)
        smallest = min(model.tiles.values(), key=lambda t: t.size)
        model.load_tile(smallest.name)  # one real read, so a broken delivery fails now, not mid-export
        info.update(srs=model.srs, srs_origin=[float(v) for v in model.srs_origin], n_tiles=len(model),
                    index=str(index))
        bounds = model.bounds()
    elif kind == "points":
        from .io.pointcloud import read_point_cloud

        pc = read_point_cloud(source, frame, settings.crs, settings.offset)
        info.update(crs=pc.crs, n_points=int(len(pc.xyz)))
        bounds = pc.bounds()
        if settings.copy:
            info["copied_to"] = str(_write_points(project, pc, settings))
    else:
        from .io.odm_model import read_georeferenced_mesh, read_odm_model

        if kind == "odm":
            mesh, crs, off = read_odm_model(source, frame)
        else:
            mesh, crs, off = read_georeferenced_mesh(source, frame, settings.crs, settings.offset)
        info.update(crs=crs, offset=[float(v) for v in off], n_triangles=int(mesh.n_triangles))
        bounds = mesh.bounds()
        if settings.copy:
            info["copied_to"] = str(_write_single_mesh(project, mesh, settings))
    if not np.all(np.isfinite(bounds)):
        raise GtkitError("model coordinates are not finite after conversion", source)
    info["bounds_world"] = bounds.tolist()
    project.record_import("model", source, **_toml_safe(info))
    log.info("imported %s model from %s: %s", kind, source, {k: v for k, v in info.items() if k != "bounds_world"})
    return info


def _write_points(project: Project, pc, settings: ModelImportSettings) -> Path:
    import trimesh

    from .io.atomic import atomic_path
    from .io.mesh import write_offset_sidecar

    out = project.paths.model / "points.ply"
    if out.exists() and not settings.overwrite:
        raise GtkitError("the project already has a point cloud (use --overwrite to replace it)", out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cloud = trimesh.PointCloud(pc.xyz, colors=pc.rgb)
    with atomic_path(out) as tmp:
        cloud.export(str(tmp), file_type="ply")
    write_offset_sidecar(out, project.frame.crs_spec, project.frame.origin)
    return out


def _toml_safe(d: dict) -> dict:
    """TOML has no None: drop missing values."""
    return {k: v for k, v in d.items() if v is not None}


# --- poses ---------------------------------------------------------------------------------

def detect_pose_kind(source: Path) -> str:
    from .io.colmap_model import is_colmap_model
    from .io.kapture_poses import kapture_folder

    source = Path(source)
    if not source.exists():
        raise GtkitError("pose source not found", source)
    if is_colmap_model(source):
        return "colmap"
    if kapture_folder(source) is not None:
        return "kapture"
    if source.is_dir():
        raise GtkitError("folder is neither a COLMAP model (cameras.bin/txt, images.bin/txt) nor a kapture folder "
                         "(sensors/sensors.txt)", source)
    s = source.suffix.lower()
    if s in (".xml", ".xmlz"):
        return "blocks_exchange"
    if s == ".txt":
        return "hloc"
    raise GtkitError("unknown pose format (expected BlocksExchange .xml/.xmlz, a COLMAP model folder, a kapture "
                     "folder, or a pose file 'name qw qx qy qz tx ty tz')", source)


def exported_dataset(source: Path) -> Path | None:
    """The ``gtkit export dataset`` folder that holds ``source`` (its hloc file, COLMAP model or kapture
    folder: ``dataset.json`` up to three levels up), or None."""
    from .dataset.folder import read_sheet

    return next((d for d in list(Path(source).absolute().parents)[:3] if read_sheet(d) is not None), None)


def check_dataset_frame(dataset: Path, frame) -> None:
    """A dataset exported in another frame than ``frame`` is refused in one line."""
    from .dataset.folder import SHEET_JSON, read_sheet
    from .geo import parse_crs

    f = dataset / SHEET_JSON
    site = (read_sheet(dataset) or {}).get("site") or {}
    if not parse_crs(site.get("crs"), f).equals(frame.crs) or not np.allclose(site.get("origin"), frame.origin, atol=1e-9):
        raise GtkitError(f"the dataset's frame {site.get('crs')} {site.get('origin')} differs from the project's "
                         f"{frame.crs_spec} {list(frame.origin)}", f)


def read_pose_source(source: Path, frame=None, intrinsics: str | Path | None = None) -> tuple[str, dict, dict]:
    """(kind, poses, cameras) of a COLMAP model, a kapture folder or an hloc pose file, in the frame they
    state (checked against ``frame`` where they state one). An hloc file's cameras come from
    ``intrinsics``, else ``queries_with_intrinsics.txt`` beside it, else none ({})."""
    source = Path(source)
    kind = detect_pose_kind(source)
    if kind == "blocks_exchange":
        raise GtkitError("a BlocksExchange file needs a project (gtkit import poses DIR SOURCE)", source)
    dataset = exported_dataset(source)
    if dataset is not None and frame is not None:
        check_dataset_frame(dataset, frame)
    if kind == "colmap":
        from .io.colmap_model import read_colmap_model

        poses, cams = read_colmap_model(source, frame)
        return kind, poses, cams
    if kind == "kapture":
        from .io.kapture_poses import read_kapture_poses

        poses, cams = read_kapture_poses(source)
        return kind, poses, cams
    from .io.poses import read_intrinsics, read_poses

    poses = read_poses(source)
    beside = source.parent / "queries_with_intrinsics.txt"
    intr = intrinsics or (beside if beside.is_file() else None)
    return kind, poses, read_intrinsics(intr) if intr else {}


def _unzip_xmlz(source: Path, tmp_dir: Path) -> Path:
    try:
        with zipfile.ZipFile(source) as z:
            names = [n for n in z.namelist() if n.lower().endswith(".xml")]
            if not names:
                raise GtkitError("XMLZ archive holds no .xml file", source)
            z.extract(names[0], tmp_dir)
            return tmp_dir / names[0]
    except zipfile.BadZipFile:
        raise GtkitError("not a valid XMLZ (zip) archive", source) from None


def read_any_poses(project: Project, source: Path, settings: PoseImportSettings) -> tuple[str, dict, dict, list]:
    """(kind, poses, cameras, skipped) from any supported pose source, in the project frame."""
    kind = detect_pose_kind(source)
    frame = project.frame
    if kind == "blocks_exchange":
        from .io.blocks_exchange import read_blocks_exchange

        xml = source
        if source.suffix.lower() == ".xmlz":
            xml = _unzip_xmlz(source, project.paths.stage(STAGE) / "xmlz")
        block = read_blocks_exchange(xml, frame, image_root=project.paths.images, drop_k3=settings.drop_k3)
        return kind, block.poses, block.cameras, block.skipped
    beside = source.parent / "queries_with_intrinsics.txt"
    if kind == "hloc" and not settings.intrinsics:
        if beside.is_file():
            settings.intrinsics = str(beside)
        elif project.paths.cameras.is_file():
            settings.intrinsics = str(project.paths.cameras)
        else:
            raise GtkitError("a pose file needs intrinsics: give --intrinsics FILE (name MODEL W H params)", source)
    kind, poses, cams = read_pose_source(source, frame, settings.intrinsics)
    missing = sorted(set(poses) - set(cams))
    if missing:
        raise GtkitError(f"no intrinsics for {len(missing)} posed images (e.g. {missing[0]})",
                         settings.intrinsics if kind == "hloc" else source)
    return kind, poses, {k: cams[k] for k in poses}, []


def import_poses(project, source: str | Path, settings: PoseImportSettings | None = None) -> dict:
    """Read existing poses into the project frame; write gtkit pose/intrinsics files and a COLMAP model."""
    from .io.colmap_model import write_colmap_model
    from .io.poses import write_intrinsics, write_poses

    project = _project(project)
    settings = settings or PoseImportSettings()
    source = Path(source).resolve()
    kind, poses, cams, skipped = read_any_poses(project, source, settings)
    out = project.paths.stage(STAGE)
    out.mkdir(parents=True, exist_ok=True)
    header = f"imported from {source} ({kind}); frame {project.frame.crs_spec} origin {list(project.frame.origin)}"
    write_poses(out / POSES, poses, header=header)
    write_intrinsics(out / INTRINSICS, cams)
    n_cov = _import_covariances(source, poses, out)
    colmap = write_colmap_model(out / "colmap", poses, cams, project.frame, binary=settings.colmap_binary)
    info = {"format": kind, "n_images": len(poses), "n_skipped": len(skipped), "n_cameras": len(set(cams.values())),
            "poses": str(out / POSES), "intrinsics": str(out / INTRINSICS), "colmap": str(colmap),
            "n_covariances": n_cov,
            "settings": _toml_safe(asdict(settings))}
    project.record_import("poses", source, **info)
    log.info("imported %d poses (%s) from %s; %d photos without a pose skipped", len(poses), kind, source, len(skipped))
    return info


def _import_covariances(source: Path, poses: dict, out: Path) -> int:
    """The covariances of a ``gtkit export dataset`` source's poses (its ``pseudo_gt_uncertainty.txt``)
    into ``out/covariances.txt``; an earlier import's file removed otherwise. Returns how many."""
    from .dataset.formats import COLMAP, HLOC, HLOC_POSES, UNCERTAINTY, read_uncertainty
    from .dataset.kapture_tree import KAPTURE
    from .io.poses import COVARIANCES, write_covariances

    (out / COVARIANCES).unlink(missing_ok=True)
    dataset = exported_dataset(source)
    if dataset is None:
        return 0
    side = dataset / UNCERTAINTY      # only for the dataset's own pose files, not a method's result kept there
    own = {(dataset / p).resolve() for p in (f"{HLOC}/{HLOC_POSES}", f"{COLMAP}/queries", f"{KAPTURE}/query")}
    if Path(source).resolve() not in own or not side.is_file():
        return 0
    cov = {n: c for n, (_sp, _sr, c) in read_uncertainty(side).items() if n in poses}
    if cov:
        write_covariances(out / COVARIANCES, cov)
    return len(cov)


def export_colmap(project, out_dir: str | Path, poses_file: str | Path | None = None,
                  intrinsics_file: str | Path | None = None, binary: bool = True) -> Path:
    """A project's poses (default: the imported ones) as a COLMAP model folder."""
    from .io.colmap_model import write_colmap_model
    from .io.poses import read_intrinsics, read_poses

    project = _project(project)
    d = project.paths.stage(STAGE)
    poses = read_poses(poses_file or d / POSES)
    cams = read_intrinsics(intrinsics_file or d / INTRINSICS)
    return write_colmap_model(out_dir, poses, cams, project.frame, binary=binary)
