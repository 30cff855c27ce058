"""Fast image loading for big photos: a scaled preview decoded directly by QImageReader (JPEG
decoders scale while decoding, so a 20-megapixel photo's 2048-px preview costs a fraction of a
full decode) and the full resolution decoded in a worker thread only when the user zooms in."""
from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

from PySide6.QtCore import QObject, QRunnable, QSize, QThreadPool, Signal
from PySide6.QtGui import QImage, QImageReader

PREVIEW_SIDE = 2048


def image_size(path: str | Path) -> QSize:
    r = QImageReader(str(path))
    return r.size()


def read_image(path: str | Path, max_side: int | None = None) -> QImage:
    """The image, decoded at most ``max_side`` px on its long side (None: full resolution)."""
    r = QImageReader(str(path))
    r.setAutoTransform(False)  # pixel coordinates are those of the stored image
    size = r.size()
    if max_side and size.isValid() and max(size.width(), size.height()) > max_side:
        s = max_side / max(size.width(), size.height())
        r.setScaledSize(QSize(max(1, round(size.width() * s)), max(1, round(size.height() * s))))
    img = r.read()
    if img.isNull():
        raise OSError(f"{path}: cannot read image ({r.errorString()})")
    return img.convertToFormat(QImage.Format.Format_RGB32)


class _Signals(QObject):
    done = Signal(str, QImage)


class _FullLoad(QRunnable):
    def __init__(self, path: str, signals: _Signals):
        super().__init__()
        self.path, self.signals = path, signals

    def run(self):
        try:
            img = read_image(self.path)
        except OSError:
            return
        self.signals.done.emit(self.path, img)


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

    def full(self, path: str) -> QImage | None:
        """The full-resolution image if loaded; otherwise start loading it and return None."""
        path = str(path)
        if path in self._full:
            self._full.move_to_end(path)
            return self._full[path]
        if path not in self._pending:
            self._pending.add(path)
            self.pool.start(_FullLoad(path, self._signals))
        return None

    def _on_full(self, path: str, img: QImage):
        self._pending.discard(path)
        self._full[path] = img
        while len(self._full) > self.n_full:
            self._full.popitem(last=False)
        self.full_ready.emit(path, img)
