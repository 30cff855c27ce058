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
"""
from __future__ import annotations

import io
import struct
from pathlib import Path

from PIL import Image

VARIANTS = ("no-gps", "no-focal", "flat-gcps", "checkpoints", "survey-geo")
_FOCAL_TAGS = (0x920A, 0xA405)  # FocalLength, FocalLengthIn35mmFilm (Exif sub-IFD)
_GPS_IFD = 0x8825


def _segments(data: bytes):
    """(marker, payload) of every JPEG segment before the scan, then (None, rest)."""
    assert data[:2] == b"\xff\xd8", "not a JPEG"
    i = 2
    while i < len(data):
        marker = data[i + 1]
        if marker == 0xDA:  # start of scan: the rest is image data
            yield None, data[i:]
            return
        n = struct.unpack(">H", data[i + 2:i + 4])[0]
        yield marker, data[i + 4:i + 2 + n]
        i += 2 + n


def strip_metadata(path: Path, gps: bool, focal: bool) -> None:
    """Rewrite ``path`` without EXIF GPS + XMP (``gps``) and/or EXIF focal (``focal``); pixels untouched."""
    path = Path(path)
    data = path.read_bytes()
    exif = Image.open(io.BytesIO(data)).getexif()
    if gps:
        exif.get_ifd(_GPS_IFD).clear()
        exif.pop(_GPS_IFD, None)
    if focal:
        sub = exif.get_ifd(0x8769)
        for t in _FOCAL_TAGS:
            sub.pop(t, None)
    out = bytearray(b"\xff\xd8")
    for marker, payload in _segments(data):
        if marker is None:
            out += payload
            break
        if marker == 0xE1 and payload.startswith(b"Exif\x00\x00"):
            payload = b"Exif\x00\x00" + exif.tobytes()[6:] if exif.tobytes().startswith(b"Exif") else b"Exif\x00\x00" + exif.tobytes()
        elif marker == 0xE1 and gps and payload.startswith(b"http://ns.adobe.com/xap/1.0/"):
            continue
        out += bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(bytes(out))
    tmp.replace(path)


def apply_variant(root: str | Path, name: str) -> None:
    """Turn the sample project at ``root`` into the variant ``name`` (see the module doc)."""
    root = Path(root)
    refs = sorted((root / "images" / "reference").glob("*.jpg"))
    if name == "no-gps":
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
        truth = read_poses(root / "truth" / "poses.txt")
        rows = [proj.frame.local_to_crs(p.center) for n, p in sorted(truth.items()) if n.startswith("reference/")]
        names = [n for n in sorted(truth) if n.startswith("reference/")]
        (root / "geo.txt").write_text(proj.frame.crs_spec + "\n" + "".join(
            f"{n} {x:.4f} {y:.4f} {z:.4f} 0 0 0 0.005 0.005\n" for n, (x, y, z) in zip(names, rows)))
    else:
        raise ValueError(f"unknown sample variant {name!r} (known: {', '.join(VARIANTS)})")
