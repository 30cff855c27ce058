"""The layout the photo pages share: a side panel of lists and details on the left (between a
minimum and a maximum width), the photo's title over its view on the right, taking the rest."""
from __future__ import annotations

from PySide6.QtWidgets import QHBoxLayout, QVBoxLayout, QWidget


def side_and_photo(page: QWidget, side, title: QWidget, view: QWidget, widths: tuple[int, int]) -> None:
    """Lay ``page`` out: the ``side`` layout left (``widths`` = min, max pixels), ``title`` over
    ``view`` right."""
    left = QWidget()
    left.setLayout(side)
    left.setMinimumWidth(widths[0])
    left.setMaximumWidth(widths[1])
    right = QWidget()
    rl = QVBoxLayout(right)
    rl.setContentsMargins(0, 0, 0, 0)
    rl.addWidget(title)
    rl.addWidget(view, 1)
    lay = QHBoxLayout(page)
    lay.addWidget(left)
    lay.addWidget(right, 1)
