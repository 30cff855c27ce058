"""A zoomable, pannable photo with tie-point markers and a magnifier loupe.

Scene coordinates are the photo's full-resolution pixel coordinates in gtkit's (COLMAP)
convention: the pixmap covers [0, W] x [0, H], so the top-left pixel's centre is (0.5, 0.5)
and a click at scene (x, y) is stored as x, y unchanged. A preview is shown first; the full
resolution replaces it when the user zooms in past the preview's detail.

Mouse: wheel = zoom at the cursor, right or middle drag = pan, left click on empty photo =
place, left drag on a marker = move it.
"""
from __future__ import annotations

from PySide6.QtCore import QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QBrush, QColor, QFont, QImage, QPainter, QPen, QPixmap
from PySide6.QtWidgets import QGraphicsItem, QGraphicsPixmapItem, QGraphicsScene, QGraphicsView, QLabel

COLORS = {"normal": QColor(0, 220, 255), "active": QColor(255, 230, 0), "suggestion": QColor(255, 140, 0),
          "suggestion_current": QColor(255, 60, 200), "bad": QColor(255, 50, 50)}


class Marker(QGraphicsItem):
    """One observation: a ring with a centre dot and its tie-point id, constant size on screen."""

    R = 8.0

    def __init__(self, view, key: str, x: float, y: float, kind: str = "normal", label: str = "",
                 movable: bool = True):
        super().__init__()
        self.view, self.key, self.kind, self.label = view, key, kind, label
        self.setPos(x, y)
        self.setFlag(QGraphicsItem.GraphicsItemFlag.ItemIgnoresTransformations)
        self.setFlag(QGraphicsItem.GraphicsItemFlag.ItemIsMovable, movable)
        self.setFlag(QGraphicsItem.GraphicsItemFlag.ItemIsSelectable, True)
        self.setZValue(10 if kind == "active" or kind == "suggestion_current" else 5)
        self.setCursor(Qt.CursorShape.SizeAllCursor if movable else Qt.CursorShape.PointingHandCursor)
        self._press = None

    def boundingRect(self) -> QRectF:
        return QRectF(-self.R - 2, -self.R - 2, 2 * self.R + 90, 2 * self.R + 4)

    def paint(self, p: QPainter, option, widget=None):
        c = COLORS.get(self.kind, COLORS["normal"])
        p.setRenderHint(QPainter.RenderHint.Antialiasing)
        p.setPen(QPen(QColor(0, 0, 0, 200), 3.5))
        p.drawEllipse(QPointF(0, 0), self.R, self.R)
        pen = QPen(c, 1.8, Qt.PenStyle.DashLine if self.kind.startswith("suggestion") else Qt.PenStyle.SolidLine)
        p.setPen(pen)
        p.drawEllipse(QPointF(0, 0), self.R, self.R)
        p.drawLine(QPointF(-self.R - 1, 0), QPointF(-3, 0))
        p.drawLine(QPointF(3, 0), QPointF(self.R + 1, 0))
        p.drawLine(QPointF(0, -self.R - 1), QPointF(0, -3))
        p.drawLine(QPointF(0, 3), QPointF(0, self.R + 1))
        if self.label:
            p.setFont(QFont("Sans", 8))
            p.setPen(QColor(0, 0, 0))
            p.drawText(QPointF(self.R + 3, 4), self.label)
            p.setPen(c)
            p.drawText(QPointF(self.R + 2, 3), self.label)

    def mousePressEvent(self, e):
        self._press = QPointF(self.pos())
        self.view.marker_pressed.emit(self.key)
        super().mousePressEvent(e)

    def mouseReleaseEvent(self, e):
        super().mouseReleaseEvent(e)
        if self._press is not None and self.pos() != self._press:
            old, new = self._press, self.pos()
            self.view.marker_moved.emit(self.key, old.x(), old.y(), new.x(), new.y())
        self._press = None


class ImageView(QGraphicsView):
    clicked = Signal(float, float)                         # left click on the photo (scene = pixels)
    marker_pressed = Signal(str)                           # marker key
    marker_moved = Signal(str, float, float, float, float)  # key, old x, y, new x, y
    view_changed = Signal()

    def __init__(self, cache=None, parent=None, title: str = ""):
        super().__init__(parent)
        self.cache = cache
        self.title = title
        self.setScene(QGraphicsScene(self))
        self.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform)
        self.setTransformationAnchor(QGraphicsView.ViewportAnchor.AnchorUnderMouse)
        self.setResizeAnchor(QGraphicsView.ViewportAnchor.AnchorViewCenter)
        self.setBackgroundBrush(QBrush(QColor(40, 40, 40)))
        self.setMouseTracking(True)
        self.setViewportUpdateMode(QGraphicsView.ViewportUpdateMode.SmartViewportUpdate)
        self.pixmap_item = QGraphicsPixmapItem()
        self.pixmap_item.setTransformationMode(Qt.TransformationMode.SmoothTransformation)
        self.pixmap_item.setZValue(0)
        self.scene().addItem(self.pixmap_item)
        self.path: str | None = None
        self.full_size = (0, 0)
        self._source: QImage | None = None   # the image shown (preview or full)
        self._is_full = False
        self.markers: dict[str, Marker] = {}
        self._pan = None
        self.loupe = QLabel(self.viewport())
        self.loupe.setFixedSize(180, 180)
        self.loupe.setStyleSheet("border: 2px solid #ffd000; background: black;")
        self.loupe.hide()
        self.loupe_enabled = True
        self.loupe_zoom = 4.0
        if cache is not None:
            cache.full_ready.connect(self._on_full_ready)

    # --- the photo ---------------------------------------------------------------------
    def show_image(self, path: str | None, image: QImage | None = None, full_size=None):
        """Show a photo by path (through the cache) or an in-memory image (``full_size`` = its
        size in scene pixels, default its own size)."""
        self.path = str(path) if path else None
        if image is None and path is not None:
            image, size = self.cache.preview(self.path)
            full_size = (size.width(), size.height())
        if image is None:
            self.pixmap_item.setPixmap(QPixmap())
            self._source, self.full_size = None, (0, 0)
            return
        full_size = full_size or (image.width(), image.height())
        same_size = tuple(full_size) == tuple(self.full_size)
        self.full_size = tuple(full_size)
        self._set_source(image)
        self.setSceneRect(QRectF(0, 0, *self.full_size))
        if not same_size:
            self.fit()
        self._maybe_full()

    def _set_source(self, image: QImage):
        self._source = image
        self._is_full = image.width() >= self.full_size[0]
        self.pixmap_item.setPixmap(QPixmap.fromImage(image))
        self.pixmap_item.setScale(self.full_size[0] / max(1, image.width()))

    def _on_full_ready(self, path: str, img: QImage):
        if path == self.path and not self._is_full:
            self._set_source(img)

    def _maybe_full(self):
        """Load the full resolution once the preview is magnified on screen."""
        if self.path is None or self._is_full or self._source is None or self.cache is None:
            return
        shown = self.transform().m11() * self.full_size[0] / max(1, self._source.width())
        if shown > 1.2:
            img = self.cache.full(self.path)
            if img is not None:
                self._set_source(img)

    # --- view state ----------------------------------------------------------------------
    def zoom(self) -> float:
        return self.transform().m11()

    def fit(self):
        if self.full_size[0]:
            self.fitInView(QRectF(0, 0, *self.full_size), Qt.AspectRatioMode.KeepAspectRatio)
            self.view_changed.emit()

    def zoom_by(self, factor: float):
        z = self.zoom() * factor
        if 0.005 < z < 64:
            self.scale(factor, factor)
            self._maybe_full()
            self.view_changed.emit()

    def center_on(self, x: float, y: float, zoom: float | None = None):
        if zoom:
            self.resetTransform()
            self.scale(zoom, zoom)
        self.centerOn(x, y)
        self._maybe_full()
        self.view_changed.emit()

    def view_state(self) -> dict:
        c = self.mapToScene(self.viewport().rect().center())
        return {"center": [round(c.x(), 2), round(c.y(), 2)], "zoom": round(self.zoom(), 6)}

    def set_view_state(self, st: dict | None):
        if st and "center" in st and "zoom" in st:
            self.center_on(*st["center"], zoom=float(st["zoom"]))

    # --- markers ---------------------------------------------------------------------------
    def clear_markers(self):
        for m in self.markers.values():
            self.scene().removeItem(m)
        self.markers = {}

    def set_marker(self, key: str, x: float, y: float, kind: str = "normal", label: str = "",
                   movable: bool = True) -> Marker:
        m = self.markers.get(key)
        if m is None:
            m = Marker(self, key, x, y, kind, label, movable)
            self.scene().addItem(m)
            self.markers[key] = m
        elif (m.x(), m.y(), m.kind, m.label) != (x, y, kind, label):  # untouched markers cost nothing
            if (m.x(), m.y()) != (x, y):
                m.setPos(x, y)
            m.kind, m.label = kind, label
            m.setZValue(10 if kind in ("active", "suggestion_current") else 5)
            m.update()
        return m

    def remove_marker(self, key: str):
        m = self.markers.pop(key, None)
        if m is not None:
            self.scene().removeItem(m)

    def scene_to_widget(self, x: float, y: float):
        """Widget (viewport) position of a scene point, e.g. for driving clicks in tests."""
        return self.mapFromScene(QPointF(x, y))

    # --- mouse -------------------------------------------------------------------------------
    def wheelEvent(self, e):
        d = e.angleDelta().y()
        if not d:
            return
        pos = e.position()
        before = self.viewportTransform().inverted()[0].map(pos)  # the photo point under the cursor
        anchor = self.transformationAnchor()
        self.setTransformationAnchor(QGraphicsView.ViewportAnchor.NoAnchor)
        self.zoom_by(1.0015 ** d)
        self.setTransformationAnchor(anchor)
        after = self.viewportTransform().map(before)  # keep it under the cursor (as far as the scroll range allows)
        self.horizontalScrollBar().setValue(self.horizontalScrollBar().value() + round(after.x() - pos.x()))
        self.verticalScrollBar().setValue(self.verticalScrollBar().value() + round(after.y() - pos.y()))
        self._maybe_full()
        self.view_changed.emit()

    def mousePressEvent(self, e):
        if e.button() in (Qt.MouseButton.RightButton, Qt.MouseButton.MiddleButton):
            self._pan = e.position()
            self.setCursor(Qt.CursorShape.ClosedHandCursor)
            return
        if e.button() == Qt.MouseButton.LeftButton:
            item = self.itemAt(e.position().toPoint())
            if not isinstance(item, Marker):
                p = self.mapToScene(e.position().toPoint())
                if self.full_size[0] and 0 <= p.x() <= self.full_size[0] and 0 <= p.y() <= self.full_size[1]:
                    pf = self.viewportTransform().inverted()[0].map(e.position())  # sub-pixel position
                    self.clicked.emit(pf.x(), pf.y())
                return
        super().mousePressEvent(e)

    def mouseMoveEvent(self, e):
        if self._pan is not None:
            d = e.position() - self._pan
            self._pan = e.position()
            self.horizontalScrollBar().setValue(self.horizontalScrollBar().value() - int(d.x()))
            self.verticalScrollBar().setValue(self.verticalScrollBar().value() - int(d.y()))
            self.view_changed.emit()
            return
        self._update_loupe(e.position().toPoint())
        super().mouseMoveEvent(e)

    def mouseReleaseEvent(self, e):
        if self._pan is not None:
            self._pan = None
            self.unsetCursor()
            return
        super().mouseReleaseEvent(e)

    def leaveEvent(self, e):
        self.loupe.hide()
        super().leaveEvent(e)

    def _update_loupe(self, pos):
        if not self.loupe_enabled or self._source is None:
            self.loupe.hide()
            return
        p = self.mapToScene(pos)
        s = self._source.width() / max(1, self.full_size[0])  # source px per scene px
        screen_zoom = self.zoom() * self.loupe_zoom             # screen px per scene px in the loupe
        half = self.loupe.width() / 2.0 / screen_zoom           # scene px half-width shown
        src = QRectF((p.x() - half) * s, (p.y() - half) * s, 2 * half * s, 2 * half * s).toRect()
        if src.width() < 2:
            self.loupe.hide()
            return
        crop = self._source.copy(src).scaled(self.loupe.size(), Qt.AspectRatioMode.IgnoreAspectRatio,
                                             Qt.TransformationMode.FastTransformation)
        painter = QPainter(crop)
        k = crop.width() / (2 * half)  # loupe px per scene px
        x0, y0 = p.x() - half, p.y() - half
        for m in self.markers.values():  # the markers under the loupe, at their exact positions
            if x0 <= m.x() <= x0 + 2 * half and y0 <= m.y() <= y0 + 2 * half:
                painter.setPen(QPen(COLORS.get(m.kind, COLORS["normal"]), 1.5))
                painter.drawEllipse(QPointF((m.x() - x0) * k, (m.y() - y0) * k), 6.0, 6.0)
        painter.setPen(QPen(QColor(255, 230, 0), 1))
        c = crop.width() // 2
        painter.drawLine(c - 12, c, c - 3, c)
        painter.drawLine(c + 3, c, c + 12, c)
        painter.drawLine(c, c - 12, c, c - 3)
        painter.drawLine(c, c + 3, c, c + 12)
        painter.end()
        self.loupe.setPixmap(QPixmap.fromImage(crop))
        x = pos.x() + 24 if pos.x() + 24 + self.loupe.width() < self.viewport().width() else pos.x() - 24 - self.loupe.width()
        y = pos.y() + 24 if pos.y() + 24 + self.loupe.height() < self.viewport().height() else pos.y() - 24 - self.loupe.height()
        self.loupe.move(max(0, x), max(0, y))
        self.loupe.show()
        self.loupe.raise_()
