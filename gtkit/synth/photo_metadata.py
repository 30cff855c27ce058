"""Rewriting a sample photo's metadata without touching its pixels: EXIF GPS, EXIF focal length,
the DJI XMP packet (the sample variants of :mod:`gtkit.synth.variants` and
:mod:`gtkit.synth.gcp_points_variant` build on it). Only the JPEG's metadata segments are rewritten,
atomically."""
from __future__ import annotations

import io
import struct
from fractions import Fraction
from pathlib import Path

from PIL import Image

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
    _write_segments(path, data, exif, "drop" if gps else "keep")


def _rewrite(path: Path, gps: tuple[float, float, float] | None = None, xmp: str = "keep") -> None:
    """Rewrite a JPEG's EXIF GPS (``gps`` = lat, lon, altitude) and its XMP packet (``xmp``: keep |
    drop | a new packet's text); pixels untouched, written atomically."""
    from ..io.exif import _to_dms

    data = path.read_bytes()
    exif = Image.open(io.BytesIO(data)).getexif()
    if gps is not None:
        lat, lon, alt = gps
        g = exif.get_ifd(_GPS_IFD)
        g[1], g[2] = ("N" if lat >= 0 else "S"), _to_dms(lat)
        g[3], g[4] = ("E" if lon >= 0 else "W"), _to_dms(lon)
        g[5], g[6] = (b"\x00" if alt >= 0 else b"\x01"), Fraction(abs(alt)).limit_denominator(1000)
    _write_segments(path, data, exif, xmp)


def _write_segments(path: Path, data: bytes, exif, xmp: str) -> None:
    """``path`` rewritten from the JPEG bytes ``data`` with the EXIF segment ``exif`` and its XMP
    packet kept, dropped or replaced (``xmp``: keep | drop | the new packet's text); atomically."""
    out = bytearray(b"\xff\xd8")
    for marker, payload in _segments(data):
        if marker is None:
            out += payload
            break
        if marker == 0xE1 and payload.startswith(b"Exif\x00\x00"):
            raw = exif.tobytes()
            payload = raw if raw.startswith(b"Exif") else b"Exif\x00\x00" + raw
        elif marker == 0xE1 and payload.startswith(b"http://ns.adobe.com/xap/1.0/"):
            if xmp == "drop":
                continue
            if xmp != "keep":
                payload = b"http://ns.adobe.com/xap/1.0/\x00" + xmp.encode("utf-8")
        out += bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(bytes(out))
    tmp.replace(path)
