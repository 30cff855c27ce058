"""Every bad input at once: photos checked all together, each problem named with its true cause.

``gtkit init`` and the stages that read photos (the SfM of the reference block and of the query
sequences, localization) look at every photo before using any, and a project whose photos or files
have problems is refused with one report listing them all (a count, each name with its cause)
instead of stopping at the first. What a photo can be: missing, unreadable (permissions), empty,
not an image at all (a text or HTML file named ``.jpg``), a format gtkit does not read, or a
truncated JPEG (no end-of-image marker: a copy or download cut short). The line-by-line files
(``gcp_list.txt``, ``geo.txt``, ``cameras.txt``) collect every bad line in their readers
(:class:`gtkit.errors.Problems`).

Cost: a photo is opened for its header and its last bytes, not decoded: about 1 ms a photo.
"""
from __future__ import annotations

import os
from pathlib import Path

from .errors import GtkitError
from .io.exif import jpeg_truncation
from .project import IMAGE_EXT

SHOWN = 20              # problems named in the one-line message; past that, all are in a file it names

_MAGIC = ((b"\xff\xd8\xff", "JPEG"), (b"\x89PNG\r\n\x1a\n", "PNG"), (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"),
          (b"II+\x00", "TIFF"), (b"MM\x00+", "TIFF"))
_OTHER = ((b"GIF8", "a GIF image"), (b"BM", "a BMP image"), (b"%PDF", "a PDF document"), (b"PK\x03\x04", "a ZIP archive"),
          (b"RIFF", "a RIFF file (WebP, AVI ...)"))


class BadInputs(GtkitError):
    """Inputs with problems, all of them: ``problems`` maps each name to its cause."""

    def __init__(self, message: str, path=None, problems: dict | None = None):
        super().__init__(message, path)
        self.problems = dict(problems or {})


def _kind_of(head: bytes) -> str | None:
    for magic, kind in _MAGIC:
        if head.startswith(magic):
            return kind
    return None


def _looks_like_text(head: bytes) -> bool:
    if not head:
        return False
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return sum(c.isprintable() or c in "\r\n\t" for c in text) >= 0.95 * len(text)


def photo_problem(path: str | Path) -> str | None:
    """Why ``path`` cannot be used as a photo, in a few words (None: it can)."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        return f"a broken link (to {os.readlink(path)})"
    if not path.exists():
        return "missing"
    if not path.is_file():
        return "not a file"
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(64)
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError as e:
        return f"cannot be read ({e.strerror or e})"
    if size == 0:
        return "empty file (0 bytes)"
    kind = _kind_of(head)
    if kind is None:
        if _looks_like_text(head):
            first = head.decode("utf-8").strip().splitlines()[0][:30] if head.strip() else ""
            return f"not an image: a text file ({size} bytes, starts {first!r})"
        other = next((k for m, k in _OTHER if head.startswith(m)), None)
        if head[4:8] == b"ftyp":
            other = "an ISO media file (HEIC, MP4 ...)"
        return f"not an image gtkit reads: {other}" if other else f"not an image ({size} bytes of unknown data)"
    if kind == "JPEG" and (cut := jpeg_truncation(tail, size)):
        return cut
    try:
        from PIL import Image

        with Image.open(path) as im:
            w, h = im.size
    except Exception as e:  # noqa: BLE001 - whatever Pillow says is the cause
        return f"not a readable {kind} ({str(e).splitlines()[0] if str(e) else type(e).__name__})"
    if not (w > 0 and h > 0):
        return f"{kind} of size {w}x{h}"
    return None


def photo_problems(paths, name=lambda p: Path(p).name) -> dict[str, str]:
    """{name: cause} for every photo of ``paths`` that cannot be used (in their order)."""
    out = {}
    for p in paths:
        why = photo_problem(p)
        if why:
            out[name(p)] = why
    return out


def listing(problems: dict[str, str], shown: int = SHOWN) -> str:
    """``a.jpg: cause; b.jpg: cause; ... and N more`` for a one-line message."""
    items = [f"{n}: {why}" for n, why in problems.items()]
    more = len(items) - shown
    return "; ".join(items[:shown]) + (f"; ... and {more} more" if more > 0 else "")


def bad_photos_error(problems: dict[str, str], where, what_to_do: str, report: Path | None = None) -> BadInputs:
    """One error counting and naming the bad photos; past :data:`SHOWN` of them every one is also
    written, a line each, to ``report`` (default: a file in the temporary folder), which it names."""
    n = len(problems)
    full = ""
    if n > SHOWN:
        import tempfile

        from .io.atomic import write_text

        report = Path(report) if report else Path(tempfile.gettempdir()) / f"gtkit-bad-photos-{os.getpid()}.txt"
        write_text(report, "".join(f"{k}\t{v}\n" for k, v in problems.items()))
        full = f" (all {n} in {report})"
    return BadInputs(f"{n} bad photo{'s' if n != 1 else ''}{full}: {listing(problems)}; {what_to_do}", where, problems)


def require_good_photos(project, folders=("reference",)) -> None:
    """A stage about to read the project's photos: every photo under ``images/<folder>/`` checked,
    all bad ones named in one error (names relative to ``images/``)."""
    P = project.paths
    photos = []
    for folder in folders:
        d = P.images / folder
        if d.is_dir():
            photos += sorted(f for f in d.rglob("*") if f.suffix.lower() in IMAGE_EXT and (f.is_file() or f.is_symlink()))
    bad = photo_problems(photos, lambda p: str(Path(p).relative_to(P.images)))
    if bad:
        raise bad_photos_error(bad, P.images, "replace them, or move them out of images/ (a photo left out is "
                               "not used), then run again", P.work / "errors" / "bad_photos.txt")
