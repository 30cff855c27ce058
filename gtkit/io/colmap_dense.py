"""COLMAP's dense array files (depth and normal maps: ``W&H&C&`` then float32 little-endian planes).

numpy only, so a machine that runs COLMAP without gtkit's other dependencies can read them too
(``benchmarks/bench_patchmatch.py gpu``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def read_colmap_array(path: Path) -> np.ndarray:
    """A COLMAP dense array file (``W&H&C&`` then float32 little-endian, rows of W, channel planes):
    (H, W) or (H, W, C)."""
    raw = Path(path).read_bytes()
    head, pos = [], 0
    for _ in range(3):
        end = raw.index(b"&", pos)
        head.append(int(raw[pos:end]))
        pos = end + 1
    w, h, c = head
    data = np.frombuffer(raw, "<f4", count=w * h * c, offset=pos)
    a = data.reshape(c, h, w)
    return a[0].copy() if c == 1 else np.moveaxis(a, 0, -1).copy()


def write_colmap_array(path: Path, a: np.ndarray) -> None:
    """The inverse of :func:`read_colmap_array` (COLMAP reads it as a depth or normal map)."""
    a = np.asarray(a, np.float32)
    planes = a[None] if a.ndim == 2 else np.moveaxis(a, -1, 0)
    c, h, w = planes.shape
    Path(path).write_bytes(f"{w}&{h}&{c}&".encode() + np.ascontiguousarray(planes).astype("<f4").tobytes())
