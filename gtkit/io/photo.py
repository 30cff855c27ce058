"""Photos read from disk: one reader for every stage that needs a photo's pixels (RGB, uint8)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import GtkitError


def read_photo(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """An RGB uint8 photo, optionally resized to ``size`` = (w, h); JPEGs are decoded at a
    reduced size directly when that is enough (fast for 20-megapixel photos)."""
    import cv2

    path = Path(path)
    flag = cv2.IMREAD_COLOR
    if size is not None:
        try:
            from PIL import Image

            with Image.open(path) as im:
                w0, _ = im.size
        except OSError:
            w0 = None
        if w0:
            r = w0 / max(1, size[0])
            flag = {8: cv2.IMREAD_REDUCED_COLOR_8, 4: cv2.IMREAD_REDUCED_COLOR_4,
                    2: cv2.IMREAD_REDUCED_COLOR_2}.get(next((k for k in (8, 4, 2) if r >= k), 1), cv2.IMREAD_COLOR)
    img = cv2.imread(str(path), flag)
    if img is None:
        raise GtkitError("not a readable image", path)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA)
    return img
