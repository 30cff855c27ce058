"""``gtkit init``: a project folder made from a user's own files.

Photos are linked (or copied) into the layout gtkit expects (``images/reference/``,
``images/queries/<seq>/``); ``gcp_list.txt``, ``geo.txt`` and ``cameras.txt`` are copied in; a
surveyor's GCP coordinates file (``--gcp-points``, see :mod:`gtkit.io.gcp_points`) is checked and stored
as ``gcp/points.txt`` (clicked later in the annotator's GCP page).
The CRS is the one given, else the CRS line of the GCP / GCP coordinates / geo file, else the UTM
zone of the photos' GPS; the local origin is the data's centroid (rounded to 1 m, height 0). Returns what was found
and what is missing, for the command to print; nothing is written when the input cannot make a
project (one error listing every problem: each bad photo with its cause, each bad line of the GCP /
geo / cameras files; :mod:`gtkit.input_check`). ``skip_bad_photos`` leaves the bad photos out
knowingly: the report counts and names them and ``project.toml`` lists them
(``[imports.photos.left_out]``, name -> cause).
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import GtkitError
from .input_check import BadInputs, bad_photos_error, photo_problem
from .io.gcp_points import check_inside, points_path, read_points, write_points
from .geo import GeoFrame, parse_crs, utm_epsg
from .io.exif import read_photo_meta
from .io.odm import read_crs, read_gcp_list, read_geo_txt
from .project import PROJECT_FILE, Paths, Project

IMAGE_EXT = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


@dataclass
class InitReport:
    root: Path
    crs: str = ""
    crs_from: str = ""
    origin: tuple = ()
    reference: dict = field(default_factory=dict)   # counts: photos, gps, dji_xmp, exif_focal, sizes
    queries: dict = field(default_factory=dict)     # seq -> {photos, wide, zoom, pattern}
    gcps: dict = field(default_factory=dict)        # n, clicks, check points, missing photos
    geo: dict = field(default_factory=dict)
    cameras: int = 0
    missing: list = field(default_factory=list)     # what is missing, in words
    notes: list = field(default_factory=list)
    left_out: dict = field(default_factory=dict)    # bad photos left out (--skip-bad-photos): name -> cause


def _photos(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise GtkitError("not a folder of photos", folder)
    out = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXT)
    if not out:
        raise GtkitError(f"no photos ({', '.join(IMAGE_EXT)}) in this folder", folder)
    return out


def _cause(e: GtkitError) -> str:
    """A GtkitError's message without the file it names (the listing names it)."""
    msg = str(e)
    return msg[len(f"{e.path}: "):] if e.path is not None and msg.startswith(f"{e.path}: ") else msg


def _check_photos(groups: dict[str, list[Path]]) -> tuple[dict[Path, object], dict[str, str]]:
    """Every photo looked at: ({path: metadata} of the good ones, {'<group>/<name>': cause} of the bad)."""
    metas, bad = {}, {}
    for label, photos in groups.items():
        for p in photos:
            why = photo_problem(p)
            if why is None:
                try:
                    metas[p] = read_photo_meta(p)
                except GtkitError as e:
                    why = _cause(e)
            if why is not None:
                bad[f"{label}/{p.name}"] = why
    return metas, bad


def _check_files(gcp, geo, cameras, gcp_points) -> list[str]:
    """Every line of every given file parsed (in its own CRS: the project's is not decided yet);
    one message per file with problems, each listing all its bad lines."""
    from .io.poses import read_intrinsics

    def frame_of(f):
        try:
            spec = read_crs(f) if f is not gcp_points else (_points_crs(f) or "EPSG:3857")
        except GtkitError:
            spec = "EPSG:3857"       # the reader names the bad CRS line itself
        return GeoFrame(spec, (0.0, 0.0, 0.0))

    out = []
    for f, read in ((gcp, lambda f: read_gcp_list(f, frame_of(f))), (geo, lambda f: read_geo_txt(f, frame_of(f))),
                    (cameras, read_intrinsics), (gcp_points, lambda f: read_points(f, frame_of(f)))):
        if f is not None:
            try:
                read(f)
            except GtkitError as e:
                out.append(str(e))
    return out


def _scan(photos: list[Path], known: dict) -> tuple[dict, list]:
    metas = [known[p] for p in photos]
    sizes = sorted({f"{m.width}x{m.height}" for m in metas})
    return ({"photos": len(photos), "gps": sum(m.has_gps for m in metas),
             "dji_xmp": sum(m.has_gimbal for m in metas),
             "exif_focal": sum(bool(m.focal_mm or m.focal_35mm) for m in metas), "sizes": sizes}, metas)


def _points_crs(path) -> str | None:
    """The CRS a GCP coordinates file names on its first line (None: it names none)."""
    from .io.gcp_points import is_crs_line
    from .io.odm import parse_odm_crs

    for n, ln in enumerate(Path(path).read_text(encoding="utf-8-sig").splitlines(), 1):
        s = ln.split("#", 1)[0].strip()
        if s:
            if not is_crs_line(s):
                return None
            try:
                return parse_odm_crs(s, path)
            except GtkitError:
                raise GtkitError(f"line {n}: unknown CRS {s!r}", path) from None
    return None


def _place(src: Path, dst: Path, copy: bool) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists() or dst.is_symlink():
        dst.unlink()
    if copy:
        shutil.copy2(src, dst)
    else:
        dst.symlink_to(src.resolve())


def _usable_inputs(reference, queries, gcp, geo, cameras, gcp_points, skip_bad_photos: bool):
    """(reference photos, {seq: photos}, {photo: metadata}, {bad photo left out: cause}) after every
    photo and every file line is checked; every problem found is raised in one :class:`BadInputs`."""
    ref_photos = _photos(Path(reference))
    seqs = {Path(q).name: _photos(Path(q)) for q in queries}
    if len(seqs) != len(queries):
        raise GtkitError("two query folders have the same name; each sequence needs its own folder name")
    missing = [str(f) for f in (gcp, geo, cameras, gcp_points) if f is not None and not Path(f).is_file()]
    if missing:
        raise GtkitError(f"file not found: {', '.join(missing)}")
    known, bad = _check_photos({"reference": ref_photos, **{f"queries/{s}": ph for s, ph in seqs.items()}})
    problems = _check_files(gcp, geo, cameras, gcp_points)
    if bad and not skip_bad_photos:
        problems.insert(0, str(bad_photos_error(bad, None, "replace them, or leave them out with --skip-bad-photos")))
    if problems:
        n = len(problems)
        raise BadInputs((f"{n} inputs have problems (nothing was written): " if n > 1 else "nothing was written: ")
                        + " | ".join(problems), None, bad)
    ref_photos = [p for p in ref_photos if p in known]
    seqs = {s: [p for p in ph if p in known] for s, ph in seqs.items()}
    if not ref_photos:
        raise BadInputs(f"none of the {len(bad)} reference photos can be used", reference, bad)
    return ref_photos, {s: ph for s, ph in seqs.items() if ph}, known, bad


def init_project(root: str | Path, reference: str | Path, queries: list[str | Path] = (), crs: str | None = None,
                 gcp: str | Path | None = None, geo: str | Path | None = None, cameras: str | Path | None = None,
                 copy: bool = False, name: str | None = None, gcp_points: str | Path | None = None,
                 skip_bad_photos: bool = False) -> InitReport:
    root = Path(root)
    if (root / PROJECT_FILE).exists():
        raise GtkitError("already a gtkit project (project.toml exists); use another folder", root)
    ref_photos, seqs, known, bad = _usable_inputs(reference, queries, gcp, geo, cameras, gcp_points, skip_bad_photos)
    rep = InitReport(root, left_out=bad)
    for s in {Path(q).name for q in queries} - set(seqs):
        rep.notes.append(f"query sequence {s}: every photo is bad and left out, so it is not in the project")
    rep.reference, metas = _scan(ref_photos, known)
    q_metas = []
    for s, photos in seqs.items():
        info, m = _scan(photos, known)
        q_metas += m
        wide = [p for p in photos if p.stem.upper().endswith("_W")]
        zoom = [p for p in photos if p.stem.upper().endswith("_Z")]
        info.update(wide=len(wide), zoom=len(zoom))
        rep.queries[s] = info

    # CRS: given > the GCP / geo file's CRS line > UTM zone of the photos' GPS
    gps = [(m.lon, m.lat) for m in metas + q_metas if m.has_gps]
    if crs:
        spec, rep.crs_from = crs, "--crs"
    elif gcp is not None:
        spec, rep.crs_from = read_crs(gcp), f"{Path(gcp).name} (first line)"
    elif gcp_points is not None and _points_crs(gcp_points):
        spec, rep.crs_from = _points_crs(gcp_points), f"{Path(gcp_points).name} (first line)"
    elif geo is not None:
        spec, rep.crs_from = read_crs(geo), f"{Path(geo).name} (first line)"
    elif gps:
        lon, lat = np.median(np.array(gps), axis=0)
        spec, rep.crs_from = f"EPSG:{utm_epsg(float(lon), float(lat))}", "UTM zone of the photos' GPS"
    else:
        raise GtkitError("cannot decide the project's CRS: the photos have no GPS and no --gcp / --geo file "
                         "names one; give --crs EPSG:<code>", reference)
    c = parse_crs(spec)
    if not c.is_projected:
        raise GtkitError(f"CRS {spec!r} is not projected (metres are needed); give a projected CRS with --crs",
                         rep.crs_from)
    code = c.to_epsg()
    spec = f"EPSG:{code}" if code else spec

    # origin: the data's centroid in that CRS
    zero = GeoFrame(spec, (0.0, 0.0, 0.0))
    pts = []
    if gcp is not None:
        pts += [g.xyz for g in read_gcp_list(gcp, zero)]
    if geo is not None:
        pts += [e.xyz for e in read_geo_txt(geo, zero).values()]
    if gcp_points is not None:
        pts += [p.xyz for p in read_points(gcp_points, zero)[0]]
    if not pts and gps:
        pts = list(zero.wgs84_to_local(*np.array(gps).T, np.zeros(len(gps))))
    cen = np.nanmedian(np.array(pts), axis=0) if pts else np.zeros(3)
    frame = GeoFrame(spec, (float(round(cen[0])), float(round(cen[1])), 0.0))
    rep.crs, rep.origin = spec, frame.origin

    # GCPs: parse with the project's frame; photo names must be reference photos
    ref_names = {p.name for p in ref_photos}
    if gcp is not None:
        gcps = read_gcp_list(gcp, frame)
        clicked = {c.image for g in gcps for c in g.clicks}
        missing = sorted(n for n in clicked if Path(n).name not in ref_names)
        rep.gcps = {"n": len(gcps), "clicks": sum(len(g.clicks) for g in gcps),
                    "check_points": sorted(g.name for g in gcps if g.check),
                    "with_fewer_than_2_clicks": sorted(g.name for g in gcps if len(g.clicks) < 2),
                    "photos_not_found": missing,
                    "heights_all_equal": len({round(float(g.xyz[2]), 3) for g in gcps}) == 1 and len(gcps) > 1}
        if missing:
            rep.notes.append(f"{len(missing)} photos named in {Path(gcp).name} are not among the reference photos "
                             f"(their clicks are ignored): {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
        if rep.gcps["heights_all_equal"]:
            rep.notes.append("every GCP has the same height (heights not surveyed?): the fit accepts it and reports "
                             "the residuals; set [sfm.georegister] gcp_accuracy_m if you know their accuracy")
    points = None
    if gcp_points is not None:
        points, pspec = read_points(gcp_points, frame)
        if gps:
            ll = np.array(gps)
            C = frame.wgs84_to_local(ll[:, 0], ll[:, 1], np.zeros(len(ll)))
            check_inside(points, np.array([C[:, :2].min(0), C[:, :2].max(0)]), gcp_points, 200.0,
                         "the photos' GPS footprint")
        rep.gcps.update({"points": len(points), "points_crs": pspec,
                         "points_check": sorted(p.name for p in points if p.check)})
    if geo is not None:
        entries = read_geo_txt(geo, frame)
        all_names = ref_names | {p.name for ph in seqs.values() for p in ph}
        found = sum(1 for n in entries if Path(n).name in all_names)
        rep.geo = {"n": len(entries), "matching_photos": found,
                   "with_accuracy": sum(e.accuracy is not None for e in entries.values())}
    if cameras is not None:
        from .io.poses import read_intrinsics

        rep.cameras = len(read_intrinsics(cameras))

    # what is missing
    r = rep.reference
    if r["gps"] < r["photos"] and geo is None:
        rep.missing.append(f"{r['photos'] - r['gps']} of {r['photos']} reference photos have no GPS: they are paired by "
                           "exhaustive matching or retrieval" + ("" if gcp else "; without GPS or GCPs the block "
                                                                 "cannot be placed in the world"))
    if r["exif_focal"] < r["photos"] and cameras is None:
        rep.missing.append(f"{r['photos'] - r['exif_focal']} reference photos have no EXIF focal length and there is no "
                           "cameras.txt: the focal length is self-calibrated")
    if gcp is None and gcp_points is None:
        rep.missing.append("no gcp_list.txt: georegistration by GPS only (or give --gcp, or --gcp-points to click "
                           "them in the annotator)")
    if not seqs:
        rep.missing.append("no query sequences (add folders with --queries, one per sequence)")
    extra = {}
    for s, info in rep.queries.items():
        if info["wide"] == 0:
            extra.setdefault("sfm", {})["query_pattern"] = "*"
            rep.notes.append(f"query sequence {s}: no *_W / *_Z names, so every photo is taken as a wide photo "
                             "([sfm] query_pattern = \"*\")")

    # write: photos, files, project.toml last (a half-made folder is never a project)
    P = Paths(root)
    for p in ref_photos:
        _place(p, P.reference_images / p.name, copy)
    for s, photos in seqs.items():
        for p in photos:
            _place(p, P.query_images / s / p.name, copy)
    for src, dst in ((gcp, P.gcp_list), (geo, P.geo_txt), (cameras, P.cameras)):
        if src is not None:
            shutil.copy2(src, dst)
    if points is not None:
        write_points(points_path(P), points, frame)
    imports = {"imports": {"photos": {"reference": str(Path(reference).resolve()),
                                      "queries": [str(Path(q).resolve()) for q in queries],
                                      "mode": "copied" if copy else "linked",
                                      **({"left_out": dict(bad)} if bad else {})}}}
    Project.create(root, frame, name or root.resolve().name, extra={**extra, **imports})
    return rep
