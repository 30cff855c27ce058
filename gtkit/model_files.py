"""Where a project's reference model is, and the fingerprint that says whether it changed: read by
the stages that draw or measure the model (exports, overlays, the localization database, the
registration) from one place below them all."""
from __future__ import annotations

from pathlib import Path

from .errors import GtkitError
from .io.mesh import MESH_SUFFIXES
from .io.tiled import is_tiled
from .project import Paths, file_fingerprint

REFERENCE_MODEL = "reference.obj"


def reference_model(paths: Paths) -> Path:
    """The project's reference model: ``model/reference.obj``, else its tiled model (built by
    ``gtkit model build``: project.toml [model] tiled; imported by ``gtkit import model``:
    [imports.model]), else the only mesh in model/."""
    import tomllib

    p = paths.model / REFERENCE_MODEL
    if p.is_file():
        return p
    if paths.project_toml.is_file():
        config = tomllib.loads(paths.project_toml.read_text())
        tiled = config.get("model", {}).get("tiled")
        if tiled and (paths.root / tiled).is_dir():
            return paths.root / tiled
        imported = config.get("imports", {}).get("model", {})
        if imported.get("format") == "tiled" and Path(imported.get("source", "")).exists():
            return Path(imported["source"])
    found = sorted(f for f in paths.model.glob("*") if f.suffix.lower() in MESH_SUFFIXES) if paths.model.is_dir() else []
    if len(found) == 1:
        return found[0]
    if not found:
        raise GtkitError(f"no reference model (expected {REFERENCE_MODEL} or one mesh file); give --input", paths.model)
    raise GtkitError(f"several meshes ({', '.join(f.name for f in found)}); give --input", paths.model)


def model_fingerprint(root: Path, model: str) -> str:
    """A fingerprint of the model `model` (relative to `root`): a tiled model's metadata.xml, else the file."""
    path = Path(root) / model
    if is_tiled(path):
        return file_fingerprint((path if path.is_dir() else path.parent) / "metadata.xml")
    return file_fingerprint(path)
