"""Fast image loading for big photos: a scaled preview decoded directly by QImageReader (JPEG
decoders scale while decoding, so a 20-megapixel photo's 2048-px preview costs a fraction of a
full decode) and the full resolution decoded in a worker thread only when the user zooms in."""
from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

from PySide6.QtCore import QObject, QRunnable, QSize, QThreadPool, Signal
from PySide6.QtGui import QImage, QImageReader

PREVIEW_SIDE = 2048   # a preview's long side is at most this ...
PREVIEW_MIN = 1024    # ... and, where the photo is larger, at least this


def preview_size(size: QSize, max_side: int = PREVIEW_SIDE, min_side: int = PREVIEW_MIN) -> QSize:
    """The photo's size divided by the power of two that brings its long side into
    [min_side, max_side]: JPEG decoders produce exactly these sizes while decoding (DCT
    scaling), with no resampling pass. 5472x3648 -> 1368x912."""
    w, h = size.width(), size.height()
    d = 1
    while max(w, h) / d > max_side and max(w, h) / (2 * d) >= min_side:
        d *= 2
    if max(w, h) / d > max_side:  # odd sizes: fall back to an exact fit
        s = max_side / max(w, h)
        return QSize(max(1, round(w * s)), max(1, round(h * s)))
    return QSize(-(-w // d), -(-h // d))


def image_size(path: str | Path) -> QSize:
    r = QImageReader(str(path))
    return r.size()


def read_image(path: str | Path, max_side: int | None = None) -> QImage:
    """The image, decoded as a preview of at most ``max_side`` px on its long side
    (:func:`preview_size`), or at full resolution when ``max_side`` is None."""
    r = QImageReader(str(path))
    r.setAutoTransform(False)  # pixel coordinates are those of the stored image
    size = r.size()
    if max_side and size.isValid() and max(size.width(), size.height()) > max_side:
        r.setScaledSize(preview_size(size, max_side, min(PREVIEW_MIN, max_side)))
    img = r.read()
    if img.isNull():
        raise OSError(f"{path}: cannot read image ({r.errorString()})")
    return img.convertToFormat(QImage.Format.Format_RGB32)


class _Signals(QObject):
    done = Signal(str, QImage)
    preview_done = Signal(str, QImage, QSize)


class _FullLoad(QRunnable):
    def __init__(self, path: str, signals: _Signals):
        super().__init__()
        self.path, self.signals = path, signals

    def run(self):
        try:
            img = read_image(self.path)
        except OSError:
            return
        try:
            self.signals.done.emit(self.path, img)
        except RuntimeError:  # the window closed meanwhile
            pass


class _PreviewLoad(QRunnable):
    def __init__(self, path: str, side: int, signals: _Signals):
        super().__init__()
        self.path, self.side, self.signals = path, side, signals

    def run(self):
        try:
            size = image_size(self.path)
            img = read_image(self.path, self.side)
        except OSError:
            return
        try:
            self.signals.preview_done.emit(self.path, img, size)
        except RuntimeError:  # the window closed meanwhile
            pass


class ImageCache(QObject):
    """Previews (kept for many images) and full-resolution images (a few), by path."""

    full_ready = Signal(str, QImage)

    def __init__(self, n_previews: int = 64, n_full: int = 3, preview_side: int = PREVIEW_SIDE):
        super().__init__()
        self.preview_side = preview_side
        self._previews: OrderedDict[str, tuple[QImage, QSize]] = OrderedDict()
        self._full: OrderedDict[str, QImage] = OrderedDict()
        self.n_previews, self.n_full = n_previews, n_full
        self._pending: set[str] = set()
        self._signals = _Signals()
        self._signals.done.connect(self._on_full)
        self._signals.preview_done.connect(self._on_preview)
        self._prefetching: set[str] = set()
        self.pool = QThreadPool()
        self.pool.setMaxThreadCount(1)

    def preview(self, path: str) -> tuple[QImage, QSize]:
        """(preview image, full-resolution size)."""
        path = str(path)
        if path in self._previews:
            self._previews.move_to_end(path)
            return self._previews[path]
        full = image_size(path)
        img = self._full.get(path) or read_image(path, self.preview_side)
        if img.width() > self.preview_side or img.height() > self.preview_side:
            img = read_image(path, self.preview_side)
        self._previews[path] = (img, full)
        while len(self._previews) > self.n_previews:
            self._previews.popitem(last=False)
        return img, full

    def shutdown(self) -> None:
        """Drop queued loads and wait for the running one (call when the window closes)."""
        self.pool.clear()
        self.pool.waitForDone(5000)

    def prefetch(self, paths) -> None:
        """Decode previews of photos the user is likely to open next, in the background."""
        for p in map(str, paths):
            if p not in self._previews and p not in self._prefetching:
                self._prefetching.add(p)
                self.pool.start(_PreviewLoad(p, self.preview_side, self._signals), 0)

    def _on_preview(self, path: str, img: QImage, size: QSize):
        self._prefetching.discard(path)
        if path not in self._previews:
            self._previews[path] = (img, size)
            while len(self._previews) > self.n_previews:
                self._previews.popitem(last=False)

    def full(self, path: str) -> QImage | None:
        """The full-resolution image if loaded; otherwise start loading it and return None."""
        path = str(path)
        if path in self._full:
            self._full.move_to_end(path)
            return self._full[path]
        if path not in self._pending:
            self._pending.add(path)
            self.pool.start(_FullLoad(path, self._signals), 1)  # before any prefetch
        return None

    def _on_full(self, path: str, img: QImage):
        self._pending.discard(path)
        self._full[path] = img
        while len(self._full) > self.n_full:
            self._full.popitem(last=False)
        self.full_ready.emit(path, img)
