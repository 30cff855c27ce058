"""Variants of a sample project that reproduce what real photo sets bring: no GPS in the photos,
no focal length anywhere, GCPs surveyed without heights. Each edits a copy in place; truth stays.

- ``no-gps``: EXIF GPS and the DJI XMP packet removed from the reference photos (losslessly: only
  the metadata segments of the JPEG are rewritten).
- ``no-focal``: EXIF focal lengths removed from the reference photos and their ``cameras.txt`` lines
  dropped (nothing tells the focal length).
- ``flat-gcps``: every GCP of ``gcp_list.txt`` at one height (their mean), as in deliveries whose
  heights were never surveyed.
- ``checkpoints``: every other GCP marked ``check`` in ``gcp_list.txt``.
- ``survey-geo``: a ``geo.txt`` of the reference photos' true camera centres with 5 mm accuracy
  columns, as public benchmark sets with surveyed camera positions ship (combine with ``no-gps``).
- ``no-gcps``: ``gcp_list.txt`` removed (the photos' GPS alone places the block).
- ``no-attitude``: the DJI XMP packet (gimbal and flight angles, DJI altitudes) removed from every
  photo, reference and queries; EXIF GPS (position and GPSAltitude) kept.
- ``consumer-gps``: a consumer camera's GPS on every photo: horizontal error of ~10 m (a bias for
  the flight plus a slowly wandering error), the altitude off by an offset and drifting 60 m over
  the flight in capture order, and no XMP attitude (as the hidden real site of issue 33: GPS ~12 m
  off, altitude climbing 317 -> 431 m, no gimbal angles).
- ``query-gps-5`` / ``query-gps-15``: the query photos' GPS degraded to ~5 / ~15 m (horizontal and
  vertical, the altitude with a slow drift); their XMP attitude kept, its altitude rewritten too.
- ``nadir-heldout``: a nadir mapping flight with photos held out of it, as a user checks a site
  with its own photos (the hidden real site of issue 33: 75 nadir photos, 15 held out): only the
  five-eye block's nadir photos stay reference photos; every 5th of them (in capture order, from
  the 3rd) becomes a query in ``images/queries/heldout/`` (truth poses under the new names), the
  sample's own query sequences, their clicks (``tiepoints.json``) and ``cameras.txt`` go, and
  ``[sfm] query_pattern = "*"`` (as ``gtkit init`` writes it). Apply after a GPS variant so the
  held-out photos keep the flight's GPS errors.
- ``facade-proxy``: the closest honest proxy of a terrestrial facade capture the sample can give
  (its photos are aerial): the whole world turned 90 deg about the east axis through the block's
  centre, so that the ground becomes a wall and the photos look at it level (the nadir photos and the
  east- and west-looking obliques) or 45 deg up or down (the other obliques); ``geo.txt`` gives the turned
  camera centres with 5 mm accuracy columns (3 mm noise), the photos lose EXIF GPS and XMP attitude
  (as the real sets: no EXIF focal/attitude, surveyed centres), ``gcp_list.txt`` goes, and
  ``truth/poses.txt`` is turned the same way (``truth/facade_proxy.json`` says how). What it does not
  cover: real level photos' look (sky, perspective of a facade) and a short arc of few photos (see
  ``level_block`` for that, at the georegistration's level).
- ``rtk-few``: RTK with few photos: 8 reference photos kept (spread over the block, the rest
  deleted), their centres in ``geo.txt`` at 2 cm (2 cm noise, accuracy columns 0.02), EXIF GPS
  removed (XMP attitude kept), ``gcp_list.txt`` removed.
- ``gcp-half``: every GCP click in ``gcp_list.txt`` halved, as when the GCPs were clicked on
  half-size copies of the photos (web GCP editors); combine with ``no-gps`` so the GCPs carry the
  georegistration.
- ``gcp-points`` / ``gcp-points-no-gps``: the GCPs' surveyed coordinates only (no clicks), with or
  without the photos' GPS (:mod:`gtkit.synth.gcp_points_variant`, for marking GCPs in gtkit).
- ``plain-grass``: a square of grass without detail (half the reference flight's width across) in the
  reference photos, re-rendered from the truth; the sample's model removed so that ``gtkit run``
  builds one from the photos (:mod:`gtkit.synth.plain_variant`; the DSM's gaps, issue 57).
"""
from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
from PIL import Image

from ..project import Paths
from .photo_metadata import _GPS_IFD, _rewrite, _segments, _write_segments, strip_metadata  # noqa: F401

VARIANTS = ("no-gps", "no-focal", "flat-gcps", "checkpoints", "survey-geo", "no-gcps", "no-attitude", "consumer-gps",
            "query-gps-5", "query-gps-15", "nadir-heldout", "facade-proxy", "rtk-few", "gcp-half",
            "gcp-points", "gcp-points-no-gps",   # these two: gtkit.synth.gcp_points_variant
            "plain-grass")                       # gtkit.synth.plain_variant
# (which photos, horizontal sigma m, altitude offset sigma m, altitude drift over the flight m, strip XMP)
_GPS_VARIANTS = {"consumer-gps": ("all", 10.0, 10.0, 60.0, True),
                 "query-gps-5": ("queries", 5.0, 5.0, 5.0, False),
                 "query-gps-15": ("queries", 15.0, 15.0, 15.0, False)}
def degrade_gps(root: Path, photos: list[Path], sigma_h: float, alt_offset_sigma: float, alt_drift_m: float,
                strip_xmp: bool, seed: int) -> dict[str, list[float]]:
    """Consumer-grade GPS on ``photos`` (in capture order): horizontal error = a bias for the flight
    (sigma ``sigma_h``/2 per axis) + an AR(1) error wandering along the flight (sigma ``sigma_h``
    per axis overall), altitude = + an offset (``alt_offset_sigma``) + a linear drift of
    ``alt_drift_m`` from the first photo to the last + 1 m noise. Returns {photo: [dx, dy, dz]}."""
    from ..io.exif import read_photo_meta
    from ..project import Project

    frame = Project.load(root).frame
    rng = np.random.default_rng(seed)
    metas = {p: read_photo_meta(p) for p in photos}
    order = sorted((p for p in photos if metas[p].has_gps and metas[p].altitude is not None),
                   key=lambda p: (metas[p].timestamp or "", p.name))
    n = len(order)
    if n == 0:
        return {}
    bias = rng.normal(0.0, sigma_h / 2.0, 2)
    rho, walk, e = 0.9, np.zeros((n, 2)), rng.normal(0.0, 1.0, 2)
    for i in range(n):
        e = rho * e + np.sqrt(1 - rho ** 2) * rng.normal(0.0, 1.0, 2)
        walk[i] = e
    walk *= sigma_h * np.sqrt(0.75)   # bias + walk: sigma_h per axis overall
    dz = rng.normal(0.0, alt_offset_sigma) + alt_drift_m * np.linspace(0.0, 1.0, n) + rng.normal(0.0, 1.0, n)
    out = {}
    for i, p in enumerate(order):
        m = metas[p]
        c = frame.wgs84_to_local(m.lon, m.lat, m.altitude)
        d = np.array([bias[0] + walk[i, 0], bias[1] + walk[i, 1], dz[i]])
        lon, lat, h = frame.local_to_wgs84(c + d)
        xmp = "drop" if strip_xmp else "keep"
        if not strip_xmp and m.abs_alt is not None:
            from ..io.exif import _xmp_packet

            pkt = _xmp_packet(p.read_bytes())
            xmp = re.sub(r'(drone-dji:AbsoluteAltitude=")[^"]*(")', lambda mm: f"{mm.group(1)}{h:+.2f}{mm.group(2)}", pkt)
            if m.rel_alt is not None:
                xmp = re.sub(r'(drone-dji:RelativeAltitude=")[^"]*(")',
                             lambda mm: f"{mm.group(1)}{m.rel_alt + d[2]:+.2f}{mm.group(2)}", xmp)
        _rewrite(p, gps=(float(lat), float(lon), float(h)), xmp=xmp)
        out[p.relative_to(root / "images").as_posix()] = [float(v) for v in d]
    return out


def apply_variant(root: str | Path, name: str, seed: int = 0) -> None:
    """Turn the sample project at ``root`` into the variant ``name`` (see the module doc). ``seed``
    draws the GPS errors of the GPS variants (they are written to ``truth/gps_errors_<name>.json``)."""
    root = Path(root)
    refs = sorted(p for p in (root / "images" / "reference").glob("*") if p.suffix.lower() in (".jpg", ".jpeg"))
    queries = sorted(p for p in (root / "images" / "queries").glob("*/*") if p.suffix.lower() in (".jpg", ".jpeg"))
    if name == "no-gcps":
        (root / "gcp_list.txt").unlink(missing_ok=True)
    elif name == "no-attitude":
        for p in refs + queries:
            _rewrite(p, xmp="drop")
    elif name in _GPS_VARIANTS:
        which, sh, so, drift, strip = _GPS_VARIANTS[name]
        errors = {}
        if which == "all":
            errors.update(degrade_gps(root, refs, sh, so, drift, strip, seed))
        seqs = sorted({p.parent for p in queries})
        for k, seq in enumerate(seqs):  # each sequence is its own flight
            errors.update(degrade_gps(root, [p for p in queries if p.parent == seq], sh, so, drift * 0.25 if which == "all"
                                      else drift, strip, seed * 1000 + k + 1))
        if (root / "truth").is_dir():
            import json

            (root / "truth" / f"gps_errors_{name}.json").write_text(json.dumps(errors, indent=0))
    elif name == "no-gps":
        for p in refs:
            strip_metadata(p, gps=True, focal=False)
    elif name == "no-focal":
        for p in refs:
            strip_metadata(p, gps=False, focal=True)
        cams = root / "cameras.txt"
        if cams.is_file():
            keep = [ln for ln in cams.read_text().splitlines() if not ln.split(maxsplit=1)[:1] or
                    not ln.split(maxsplit=1)[0].startswith("reference/")]
            cams.write_text("\n".join(keep) + "\n")
    elif name in ("flat-gcps", "checkpoints"):
        f = root / "gcp_list.txt"
        lines = f.read_text().splitlines()
        rows = [ln.split() for ln in lines[1:] if ln.strip() and not ln.startswith("#")]
        if name == "flat-gcps":
            z = sum(float(r[2]) for r in rows) / len(rows)
            for r in rows:
                r[2] = f"{z:.3f}"
        else:
            names = sorted({r[6] for r in rows})
            checks = set(names[1::2])
            for r in rows:
                if r[6] in checks:
                    r[7:] = ["check"]
        f.write_text(lines[0] + "\n" + "\n".join(" ".join(r) for r in rows) + "\n")
    elif name == "survey-geo":
        from ..io.poses import read_poses
        from ..project import Project

        proj = Project.load(root)
        truth = read_poses(Paths(root).truth_poses)
        rows = [proj.frame.local_to_crs(p.center) for n, p in sorted(truth.items()) if n.startswith("reference/")]
        names = [n for n in sorted(truth) if n.startswith("reference/")]
        (root / "geo.txt").write_text(proj.frame.crs_spec + "\n" + "".join(
            f"{n} {x:.4f} {y:.4f} {z:.4f} 0 0 0 0.005 0.005\n" for n, (x, y, z) in zip(names, rows)))
    elif name == "nadir-heldout":
        _nadir_heldout(root, refs, queries)
    elif name == "facade-proxy":
        _facade_proxy(root, refs, seed)
    elif name == "rtk-few":
        _rtk_few(root, refs, seed)
    elif name == "gcp-half":
        f = root / "gcp_list.txt"
        lines = f.read_text().splitlines()
        out = [lines[0]]
        for ln in lines[1:]:
            r = ln.split()
            if len(r) >= 6 and not ln.startswith("#"):
                r[3], r[4] = f"{float(r[3]) / 2:.2f}", f"{float(r[4]) / 2:.2f}"
            out.append(" ".join(r))
        f.write_text("\n".join(out) + "\n")
    elif name in ("gcp-points", "gcp-points-no-gps"):
        from .gcp_points_variant import apply_gcp_points_variant

        apply_gcp_points_variant(root, name)
    elif name == "plain-grass":
        from .plain_variant import apply_plain_grass

        apply_plain_grass(root)
    else:
        raise ValueError(f"unknown sample variant {name!r} (known: {', '.join(VARIANTS)})")


def _drop_exif_gps(p: Path) -> None:
    """EXIF GPS removed from ``p``, its XMP packet (attitude) kept."""
    data = p.read_bytes()
    exif = Image.open(io.BytesIO(data)).getexif()
    exif.get_ifd(_GPS_IFD).clear()
    exif.pop(_GPS_IFD, None)
    _write_segments(p, data, exif, "keep")


def _write_geo(root: Path, centres: dict, accuracy: float) -> None:
    from ..project import Project

    frame = Project.load(root).frame
    (root / "geo.txt").write_text(frame.crs_spec + "\n" + "".join(
        f"{n} {x:.4f} {y:.4f} {z:.4f} 0 0 0 {accuracy} {accuracy}\n"
        for n, (x, y, z) in ((n, frame.local_to_crs(c)) for n, c in sorted(centres.items()))))


def _facade_proxy(root: Path, refs: list[Path], seed: int) -> None:
    """The ``facade-proxy`` variant (see the module doc)."""
    import json

    from ..io.poses import read_poses, write_poses
    from ..pose import Pose

    rng = np.random.default_rng(seed)
    truth_f = Paths(root).truth_poses
    truth = read_poses(truth_f)
    ref_names = [n for n in sorted(truth) if n.startswith("reference/")]
    c0 = np.mean([truth[n].center for n in ref_names], axis=0)
    Q = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])   # 90 deg about east: up -> south, down -> north
    turned = {n: Pose.from_center(p.R @ Q.T, Q @ (p.center - c0) + c0) for n, p in truth.items()}
    write_poses(truth_f, turned)
    (root / "truth" / "facade_proxy.json").write_text(json.dumps(
        {"rotation_world": Q.tolist(), "about_point": [float(v) for v in c0],
         "what": "world turned 90 deg about east through about_point: the ground is a wall, the photos look level"}))
    for p in refs:
        strip_metadata(p, gps=True, focal=False)
    _write_geo(root, {n: turned[n].center + rng.normal(0, 0.003, 3) for n in ref_names}, 0.005)
    (root / "gcp_list.txt").unlink(missing_ok=True)


def _rtk_few(root: Path, refs: list[Path], seed: int, keep: int = 8) -> None:
    """The ``rtk-few`` variant (see the module doc)."""
    from ..io.poses import read_poses

    rng = np.random.default_rng(seed)
    truth = read_poses(Paths(root).truth_poses)
    names = [f"reference/{p.name}" for p in refs]
    idx = np.unique(np.round(np.linspace(0, len(refs) - 1, keep)).astype(int))
    kept = {names[i] for i in idx}
    for p, n in zip(refs, names):
        if n in kept:
            _drop_exif_gps(p)
        else:
            p.unlink()
    _write_geo(root, {n: truth[n].center + rng.normal(0, 0.02, 3) for n in sorted(kept)}, 0.02)
    (root / "gcp_list.txt").unlink(missing_ok=True)


def _nadir_heldout(root: Path, refs: list[Path], queries: list[Path], every: int = 5, first: int = 2) -> None:
    """The ``nadir-heldout`` variant (see the module doc)."""
    import shutil

    nadir = [p for p in refs if p.stem.upper().endswith("_N")]
    if not nadir:
        raise ValueError(f"{root}: no nadir reference photos (*_N.jpg) to make a nadir flight of")
    for p in refs:
        if p not in nadir:
            p.unlink()
    for d in sorted({p.parent for p in queries}):
        shutil.rmtree(d)
    held = nadir[first::every]
    out = root / "images" / "queries" / "heldout"
    out.mkdir(parents=True, exist_ok=True)
    moved = {}
    for p in held:
        p.rename(out / p.name)
        moved[f"reference/{p.name}"] = f"queries/heldout/{p.name}"
    for f in ("tiepoints.json", "cameras.txt"):
        (root / f).unlink(missing_ok=True)
    truth = Paths(root).truth_poses
    if truth.is_file():
        lines = truth.read_text().splitlines()
        extra = [moved[ln.split()[0]] + ln[len(ln.split()[0]):] for ln in lines
                 if ln.split() and ln.split()[0] in moved]
        truth.write_text("\n".join(lines + extra) + "\n")
    toml = root / "project.toml"
    text = toml.read_text()
    if "[sfm]" in text:
        text = text.replace("[sfm]", '[sfm]\nquery_pattern = "*"', 1)
    else:
        text = text.rstrip("\n") + '\n\n[sfm]\nquery_pattern = "*"\n'
    toml.write_text(text)


# --- a terrestrial block at the function level ------------------------------------------------

def level_block(seed: int = 0, n_photos: int = 8, distance_m: float = 6.0, arc_deg: float = 50.0,
                position_noise_m: float = 0.003, straight: bool = False, size: tuple[int, int] = (3072, 2048)):
    """A terrestrial facade capture as SfM hands it over, for georegistration tests against truth:
    ``n_photos`` level photos (pitch and roll within a few degrees) of a wall, taken along a short
    arc ``distance_m`` from it (``straight``: along a line parallel to it), their camera centres
    surveyed (``position_noise_m`` noise; the accuracy stated as 5 mm as in a ``geo.txt`` with
    accuracy columns), no attitude and no EXIF. The SfM model (pycolmap Reconstruction: cameras,
    wall points and their observations) is in an arbitrary frame: a random similarity of the world.

    Returns ``(rec, positions, accuracy, truth)``: {photo: surveyed centre (local metres)},
    {photo: 0.005}, {photo: true gtkit Pose (world)}. The wall is the plane y = 10 m, z up."""
    import pycolmap

    from ..pose import Pose

    def look_at(c, target):   # world-to-camera rows: x right (level), y down, z forward
        z = (target - c) / np.linalg.norm(target - c)
        x = np.cross(z, np.array([0.0, 0.0, 1.0]))
        x /= np.linalg.norm(x)
        return np.array([x, np.cross(z, x), z])

    rng = np.random.default_rng(seed)
    w, h = size
    f = 0.8 * w
    wall_y = 10.0
    if straight:
        xs = np.linspace(-0.4, 0.4, n_photos) * distance_m * np.radians(arc_deg)
        centres = np.c_[xs, np.full(n_photos, wall_y - distance_m), 1.6 + rng.normal(0, 0.02, n_photos)]
    else:
        a = np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, n_photos))
        centres = np.c_[distance_m * np.sin(a), wall_y - distance_m * np.cos(a), 1.6 + rng.normal(0, 0.02, n_photos)]
    truth = {}
    for k, c in enumerate(centres):
        target = np.array([c[0] * 0.5, wall_y, 1.6]) + np.r_[rng.normal(0, 0.3), 0.0, rng.normal(0, 0.3)]
        R = look_at(c, target)
        roll = np.radians(rng.normal(0, 1.0))
        Rr = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1.0]])
        truth[f"facade/IMG_{k:04d}.JPG"] = Pose.from_center(Rr @ R, c)
    gx, gz = np.meshgrid(np.linspace(-9, 9, 37), np.linspace(0.2, 9.0, 19))
    pts = np.c_[gx.ravel(), wall_y + rng.uniform(-0.3, 0.3, gx.size), gz.ravel()]
    # the SfM frame: an arbitrary similarity of the world
    q = rng.normal(size=4)
    Rm = pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix()
    s_m, t_m = float(rng.uniform(0.2, 3.0)), rng.normal(0, 5.0, 3)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=w, height=h, params=[f, f, w / 2, h / 2], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    obs: dict[int, list] = {}
    for iid, (name, p) in enumerate(sorted(truth.items()), start=1):
        xc = pts @ p.R.T + p.t
        uv = f * xc[:, :2] / xc[:, 2:3] + np.array([w / 2, h / 2])
        ok = (xc[:, 2] > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(ok)
        im = pycolmap.Image(name=name, keypoints=uv[idx] + rng.normal(0, 0.5, (len(idx), 2)), camera_id=1, image_id=iid)
        # world -> model: x' = s_m Rm x + t_m; the camera's rotation from the model frame is R Rm^T
        C = s_m * Rm @ p.center + t_m
        Rcm = p.R @ Rm.T
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(Rcm), -Rcm @ C))
        for j, pi in enumerate(idx):
            obs.setdefault(int(pi), []).append((iid, j))
    for pi, els in obs.items():
        if len(els) >= 2:
            rec.add_point3D(s_m * Rm @ pts[pi] + t_m, pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in els]))
    positions = {n: p.center + rng.normal(0, position_noise_m, 3) for n, p in truth.items()}
    return rec, positions, {n: 0.005 for n in truth}, truth


def level_block_gcps(truth: dict, n_gcps: int = 6, seed: int = 0, size: tuple[int, int] = (3072, 2048),
                     click_px: float = 1.0, scale: float = 1.0):
    """GCPs on the wall of :func:`level_block` (surveyed exactly, in the world frame) with their
    clicks in every photo that sees them (``click_px`` noise), the clicks' pixels times ``scale``
    (0.5: clicked on half-size copies of the photos). Returns a list of gtkit GCPs."""
    from ..io.odm import GCP, GCPClick

    rng = np.random.default_rng(seed + 1000)
    w, h = size
    f = 0.8 * w
    out = []
    for k in range(n_gcps):
        X = np.array([rng.uniform(-4, 4), 10.0, rng.uniform(0.3, 4.0)])
        clicks = []
        for name, p in sorted(truth.items()):
            xc = p.R @ X + p.t
            if xc[2] <= 0.5:
                continue
            uv = f * xc[:2] / xc[2] + np.array([w / 2, h / 2])
            if 0 <= uv[0] < w and 0 <= uv[1] < h:
                uv = (uv + rng.normal(0, click_px, 2)) * scale
                clicks.append(GCPClick(name, float(uv[0]), float(uv[1])))
        out.append(GCP(f"gcp{k:02d}", X, clicks))
    return out
