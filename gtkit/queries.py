"""The query photos of a project and their intrinsics, each decided in one place.

Which photos are queries: ``[sfm] query_pattern`` (:data:`QUERY_PATTERN`, the SfM settings' default too:
``"*_W.*"``; ``gtkit init`` writes ``"*"`` for sequences without ``_W`` / ``_Z`` names), a glob
inside every ``images/queries/<seq>/`` folder. The query SfM, registration, localization and the
database grid all read :func:`query_photos`.

A query photo's intrinsics (:func:`query_cameras`), first found wins:

1. ``cameras.txt`` (the override: a line for the photo),
2. the photo's own sequence SfM (``work/sfm_queries/<seq>/intrinsics.txt``: the photo, else a
   registered photo of the same camera in that sequence),
3. the reference block's calibration of the same camera (``work/sfm_reference/intrinsics.txt``: a
   reference photo with the same EXIF make, model, size and focal length; for photos without EXIF
   camera identity, the reference's one camera of their size: the rule of
   :func:`reference_calibrations`, which the query SfM follows too),
4. the EXIF focal length: the 35 mm-equivalent (``f = f35 / 36 mm x longer side``, a 36 mm wide
   frame, as the sample sites and :mod:`gtkit.track.calibrate` take it), else the focal length in
   mm and the focal-plane resolution (``FocalPlaneXResolution``: pixels per sensor unit).

Each camera comes with a short line saying where it came from; a photo with none of these is a
one-line error naming it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .camera import Camera
from .errors import GtkitError
from .io.exif import camera_key  # noqa: F401 (named here too: which query photos share a camera)
from .io.poses import INTRINSICS
from .project import IMAGE_EXT, Project
from .settings import apply_overrides



QUERY_PATTERN = "*_W.*"   # [sfm] query_pattern's default (gtkit.sfm.blocks.SfmSettings takes it from here)


@dataclass(frozen=True)
class _QuerySelection:
    query_pattern: str = QUERY_PATTERN


def query_pattern(project: Project) -> str:
    """``[sfm] query_pattern`` resolved (project.toml > default; no flag sets it), checked as the
    SfM's own settings check it, without reading the rest of ``[sfm]`` (which the SfM checks)."""
    sec = project.section("sfm") if project is not None else {}
    if "query_pattern" not in sec:
        return QUERY_PATTERN
    got = apply_overrides(_QuerySelection(), {"query_pattern": sec["query_pattern"]}, "sfm",
                          project.paths.project_toml)
    return got.query_pattern


def query_photos(project: Project, seq: str | None = None, pattern: str | None = None) -> list[str]:
    """The query photos (names relative to ``images/``, sorted) of every sequence, or of ``seq``:
    the images of ``images/queries/<seq>/`` matching ``[sfm] query_pattern`` (or ``pattern``)."""
    P = project.paths
    pattern = pattern or query_pattern(project)
    seqs = [seq] if seq is not None else P.query_sequences()
    out = []
    for s in seqs:
        d = P.query_images / s
        if d.is_dir():
            out += [p.relative_to(P.images).as_posix() for p in d.glob(pattern)
                    if p.is_file() and p.suffix.lower() in IMAGE_EXT]
    return sorted(out)


# --- intrinsics ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class QueryCamera:
    camera: Camera
    source: str        # where it came from, e.g. "cameras.txt", "work/sfm_queries/seq1/intrinsics.txt"


def _focal_plane_px_per_mm(path: Path) -> float | None:
    """Pixels per mm on the sensor from EXIF FocalPlaneXResolution / ResolutionUnit, scaled to the
    stored image when EXIF states the original width (PixelXDimension)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            sub = im.getexif().get_ifd(0x8769)
            w = im.size[0]
    except OSError:
        return None
    res, unit = sub.get(0xA20E), sub.get(0xA210, 2)
    if not res:
        return None
    mm = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}.get(int(unit))
    if mm is None:
        return None
    px_mm = float(res) / mm
    exif_w = sub.get(0xA002)
    return px_mm * (w / float(exif_w)) if exif_w else px_mm


def exif_camera(path: Path, meta=None) -> QueryCamera | None:
    """A pinhole camera from the photo's EXIF focal length (see the module doc), or None."""
    from .io.exif import read_photo_meta

    m = meta or read_photo_meta(path)
    side = max(m.width, m.height)
    if m.focal_35mm:
        return QueryCamera(Camera.pinhole(m.width, m.height, m.focal_35mm / 36.0 * side),
                           f"EXIF 35 mm-equivalent focal {m.focal_35mm:g} mm")
    if m.focal_mm:
        px_mm = _focal_plane_px_per_mm(path)
        if px_mm:
            return QueryCamera(Camera.pinhole(m.width, m.height, m.focal_mm * px_mm),
                               f"EXIF focal {m.focal_mm:g} mm x focal-plane resolution {px_mm:.1f} px/mm")
    return None


def _read(path: Path) -> dict[str, Camera]:
    from .io.poses import read_intrinsics

    return read_intrinsics(path) if path.is_file() else {}


def _key(project: Project, name: str) -> tuple | None:
    from .io.exif import read_photo_meta

    try:
        return camera_key(read_photo_meta(project.paths.images / name, require=()))
    except GtkitError:
        return None


def reference_calibrations(project: Project, names: list[str]) -> tuple[dict[str, Camera], dict[str, str]]:
    """({photo: the reference block's calibration of the same camera}, {photo: by what rule}) for
    photos that are not reference photos. "The same camera": EXIF make, model, image size and focal
    length equal; photos without EXIF camera identity (no make, model or focal: scanned or stripped
    photos) are taken for the reference camera of their size where the reference block has exactly
    one camera of that size without identity either ("same sensor"). The query SfM
    (:mod:`gtkit.sfm.block_cameras`) and :func:`query_cameras` both follow this rule."""
    f = project.paths.reference_intrinsics
    if not f.is_file():
        return {}, {}
    ref = _read(f)
    by_key: dict[tuple, list[tuple[str, Camera]]] = {}   # each distinct calibration with its first photo
    for n, c in sorted(ref.items()):
        k = _key(project, n)
        if k is not None and all(c != d for _, d in by_key.setdefault(k, [])):
            by_key[k].append((n, c))
    cams, why = {}, {}
    for n in names:
        k = _key(project, n)
        if k is None or k not in by_key:
            continue
        first, cam = by_key[k][0]
        if k[0] or k[1]:
            cams[n], why[n] = cam, f"same camera as {first} (EXIF make, model, size, focal)"
        elif k[4] is None and len(by_key[k]) == 1:
            cams[n], why[n] = cam, (f"same sensor as {first} (no EXIF camera identity; the reference's one camera "
                                    "of this size)")
    return cams, why


def query_cameras(project: Project, names: list[str]) -> dict[str, QueryCamera]:
    """Each query photo's intrinsics and their source, in the order of the module doc; a photo
    with none is a :class:`GtkitError` naming it."""
    from .io.exif import read_photo_meta

    P = project.paths
    rel = lambda p: p.relative_to(P.root).as_posix()  # noqa: E731
    override = _read(P.cameras)
    seq_cams: dict[str, dict[str, Camera]] = {}
    metas: dict[str, object] = {}
    ref = None

    def meta(name: str):
        if name not in metas:
            metas[name] = read_photo_meta(P.images / name)
        return metas[name]

    out: dict[str, QueryCamera] = {}
    for n in names:
        if n in override:
            out[n] = QueryCamera(override[n], "cameras.txt")
            continue
        parts = Path(n).parts
        seq = parts[1] if len(parts) > 2 and parts[0] == "queries" else None
        if seq is not None:
            f = P.stage("sfm_queries") / seq / INTRINSICS
            if seq not in seq_cams:
                seq_cams[seq] = _read(f)
            cams = seq_cams[seq]
            if n in cams:
                out[n] = QueryCamera(cams[n], rel(f))
                continue
            same = [m for m in sorted(cams) if (P.images / m).is_file() and camera_key(meta(m)) == camera_key(meta(n))]
            if same:
                out[n] = QueryCamera(cams[same[0]], f"{rel(f)} (same camera as {same[0]})")
                continue
        if ref is None:   # read once, for every photo that gets this far
            ref = reference_calibrations(project, [m for m in names if m not in out])
        ref_cam, ref_why = ref
        if n in ref_cam:   # the same camera or sensor, by the rule the SfM's own blocks follow
            out[n] = QueryCamera(ref_cam[n], f"work/sfm_reference/intrinsics.txt ({ref_why[n]})")
            continue
        ex = exif_camera(P.images / n, meta(n))
        if ex is None:
            raise GtkitError("no intrinsics for this query photo: no line in cameras.txt, not calibrated by "
                             "'gtkit sfm --block queries', no reference photo of the same camera, and no EXIF "
                             "focal length", P.images / n)
        out[n] = ex
    return out
