"""EXIF GPS and DJI XMP metadata of photos: read (real DJI files) and write (sample sites).

Angles are DJI's (see :mod:`gtkit.conventions`). Altitudes: ``gps_alt`` is EXIF GPSAltitude,
``abs_alt`` DJI AbsoluteAltitude, ``rel_alt`` RelativeAltitude (above take-off), all metres.
"""
from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from ..errors import GtkitError

DJI_TAGS = ("GimbalYawDegree", "GimbalPitchDegree", "GimbalRollDegree", "FlightYawDegree",
            "FlightPitchDegree", "FlightRollDegree", "AbsoluteAltitude", "RelativeAltitude")
_GPS_IFD = 0x8825


@dataclass
class PhotoMeta:
    width: int
    height: int
    lat: float | None = None
    lon: float | None = None
    gps_alt: float | None = None
    abs_alt: float | None = None
    rel_alt: float | None = None
    gimbal_yaw: float | None = None
    gimbal_pitch: float | None = None
    gimbal_roll: float | None = None
    flight_yaw: float | None = None
    flight_pitch: float | None = None
    flight_roll: float | None = None
    timestamp: str | None = None
    make: str | None = None
    model: str | None = None
    focal_mm: float | None = None
    focal_35mm: float | None = None

    @property
    def has_gps(self) -> bool:
        return self.lat is not None and self.lon is not None

    @property
    def has_gimbal(self) -> bool:
        return None not in (self.gimbal_yaw, self.gimbal_pitch, self.gimbal_roll)

    @property
    def altitude(self) -> float | None:
        """Best available absolute altitude: DJI AbsoluteAltitude, else EXIF GPSAltitude."""
        return self.abs_alt if self.abs_alt is not None else self.gps_alt

    def as_dict(self) -> dict:
        return asdict(self)


def camera_key(meta) -> tuple:
    """What makes two photos 'the same camera': EXIF make, model, image size and focal length."""
    f = None if meta.focal_mm is None else round(float(meta.focal_mm), 2)
    return (meta.make or "", meta.model or "", meta.width, meta.height, f)


def _dms(v, ref) -> float:
    d, m, s = (float(x) for x in v)
    val = d + m / 60.0 + s / 3600.0
    return -val if ref in ("S", "W", b"S", b"W") else val


_XMP_ATTR = re.compile(r'(?:drone-dji|crs|tiff|exif):(\w+)\s*=\s*"([^"]*)"')
_XMP_ELEM = re.compile(r"<(?:drone-dji):(\w+)>([^<]*)</(?:drone-dji):\w+>")


def _xmp_packet(raw: bytes) -> str:
    start = raw.find(b"<x:xmpmeta")
    end = raw.find(b"</x:xmpmeta>", start)
    return raw[start:end + 12].decode("utf-8", "replace") if start >= 0 and end > 0 else ""


def read_xmp_dji(raw: bytes) -> dict[str, float]:
    pkt = _xmp_packet(raw)
    out = {}
    for k, v in _XMP_ATTR.findall(pkt) + _XMP_ELEM.findall(pkt):
        if k in DJI_TAGS:
            try:
                out[k] = float(v)
            except ValueError:
                pass
    return out


def jpeg_truncation(tail: bytes, size: int) -> str | None:
    """Why a JPEG whose last bytes are ``tail`` (of ``size`` bytes in all) is cut short, or None when
    it ends with the end-of-image marker (zero padding after it allowed). The one rule: the photo
    pre-check (:mod:`gtkit.input_check`) and the metadata reader both use it."""
    if tail.rstrip(b"\0").endswith(b"\xff\xd9"):
        return None
    return f"truncated JPEG (no end-of-image marker after {size} bytes: a copy or download cut short?)"


def read_photo_meta(path: str | Path, require: tuple[str, ...] = ()) -> PhotoMeta:
    """Read size, EXIF GPS and DJI XMP angles of a photo.

    ``require`` may name 'gps' and/or 'gimbal'; a photo lacking them is a clear error.
    """
    path = Path(path)
    if not path.is_file():
        raise GtkitError("image not found", path)
    try:
        if path.suffix.lower() not in (".jpg", ".jpeg"):   # (a JPEG's end is checked below)
            with Image.open(path) as im:
                im.verify()
        with Image.open(path) as im:
            w, h = im.size
            exif = im.getexif()
            gps = exif.get_ifd(_GPS_IFD)
            sub = exif.get_ifd(0x8769)
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise GtkitError(f"not a readable image ({e})", path) from None
    raw = path.read_bytes()   # the XMP packet may sit anywhere in the header segments
    cut = jpeg_truncation(raw[-64:], len(raw)) if path.suffix.lower() in (".jpg", ".jpeg") else None
    if cut:
        raise GtkitError(cut, path)
    m = PhotoMeta(width=w, height=h, make=_s(exif.get(0x010F)), model=_s(exif.get(0x0110)))
    m.timestamp = _s(sub.get(0x9003) or exif.get(0x0132))
    if sub.get(0x920A):
        m.focal_mm = float(sub[0x920A])
    if sub.get(0xA405):
        m.focal_35mm = float(sub[0xA405])
    try:
        if 2 in gps and 4 in gps:
            m.lat = _dms(gps[2], gps.get(1, "N"))
            m.lon = _dms(gps[4], gps.get(3, "E"))
        if 6 in gps:
            m.gps_alt = float(gps[6]) * (-1.0 if gps.get(5) in (1, b"\x01") else 1.0)
    except (TypeError, ValueError, ZeroDivisionError) as e:
        raise GtkitError(f"unreadable EXIF GPS tags ({e})", path) from None
    dji = read_xmp_dji(raw)
    m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll = (dji.get(k) for k in DJI_TAGS[:3])
    m.flight_yaw, m.flight_pitch, m.flight_roll = (dji.get(k) for k in DJI_TAGS[3:6])
    m.abs_alt, m.rel_alt = dji.get("AbsoluteAltitude"), dji.get("RelativeAltitude")
    if "gps" in require and not m.has_gps:
        raise GtkitError("no EXIF GPS position (GPSLatitude/GPSLongitude missing)", path)
    if "gimbal" in require and not m.has_gimbal:
        raise GtkitError("no DJI XMP gimbal angles (drone-dji:GimbalYaw/Pitch/RollDegree missing)", path)
    return m


def _s(v):
    if v is None:
        return None
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    return str(v).strip("\0 ").strip() or None


def _to_dms(value: float):
    value = abs(value)
    d = int(value)
    m = int((value - d) * 60)
    s = (value - d - m / 60.0) * 3600.0
    return (Fraction(d, 1), Fraction(m, 1), Fraction(s).limit_denominator(1000000))


def dji_xmp_packet(tags: dict[str, float], extra: dict[str, str] | None = None) -> bytes:
    """An XMP packet with drone-dji attributes, as DJI cameras write it."""
    attrs = "".join(f'\n   drone-dji:{k}="{v:+.2f}"' if k in DJI_TAGS else f'\n   drone-dji:{k}="{v}"'
                    for k, v in {**tags, **(extra or {})}.items())
    return ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
            '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            '  <rdf:Description rdf:about="DJI Meta Data" xmlns:tiff="http://ns.adobe.com/tiff/1.0/"'
            ' xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"'
            f'{attrs}>\n  </rdf:Description>\n </rdf:RDF>\n</x:xmpmeta>\n'
            '<?xpacket end="w"?>').encode("utf-8")


def write_jpeg_with_meta(path: str | Path, rgb, *, lat: float | None = None, lon: float | None = None,
                         alt: float | None = None, dji: dict[str, float] | None = None,
                         timestamp: str | None = None, make: str = "DJI", model: str | None = None,
                         focal_mm: float | None = None, quality: int = 92,
                         focal_35mm: float | None = None) -> Path:
    """Write an RGB uint8 array as a JPEG with EXIF GPS and DJI XMP tags, atomically."""
    from PIL.TiffImagePlugin import IFDRational

    from .atomic import atomic_path

    im = Image.fromarray(rgb)
    exif = Image.Exif()
    exif[0x010F] = make
    if model:
        exif[0x0110] = model
    if timestamp:
        exif[0x0132] = timestamp
        exif.get_ifd(0x8769)[0x9003] = timestamp
    if focal_mm:
        # a bare Fraction in the Exif sub-IFD makes Pillow fail on save; IFDRational works
        exif.get_ifd(0x8769)[0x920A] = IFDRational(Fraction(focal_mm).limit_denominator(1000))
    if focal_35mm:
        exif.get_ifd(0x8769)[0xA405] = int(round(focal_35mm))
    if lat is not None and lon is not None:
        g = exif.get_ifd(_GPS_IFD)
        g[0] = b"\x02\x03\x00\x00"
        g[1], g[2] = ("N" if lat >= 0 else "S"), _to_dms(lat)
        g[3], g[4] = ("E" if lon >= 0 else "W"), _to_dms(lon)
        if alt is not None:
            g[5], g[6] = (b"\x00" if alt >= 0 else b"\x01"), Fraction(abs(alt)).limit_denominator(1000)
    kw = {"xmp": dji_xmp_packet(dji)} if dji else {}
    with atomic_path(path) as tmp:
        im.save(tmp, format="JPEG", quality=quality, exif=exif, **kw)
    return Path(path)


def capture_seconds(stamp: str | None) -> float | None:
    """An EXIF date-time ("YYYY:MM:DD HH:MM:SS", as :class:`PhotoMeta.timestamp`) in seconds, or None."""
    import datetime as dt

    if not stamp:
        return None
    try:
        return dt.datetime.strptime(stamp.strip()[:19], "%Y:%m:%d %H:%M:%S").timestamp()
    except ValueError:
        return None
