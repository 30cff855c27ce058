"""Local features and matchers, chosen by name from small registries.

Interface
    extractor ``extract(rgb uint8 HxWx3) -> Features`` (keypoints in gtkit pixel convention,
    i.e. COLMAP's: top-left pixel centre at (0.5, 0.5), in the *given* image's pixels);
    matcher ``match(Features, Features) -> (M, 2) int`` index pairs.

``sift``: OpenCV SIFT on a copy resized so its longer side is at most ``max_side`` (keypoints
are scaled back; with COLMAP's pixel convention a resize by s maps u to u * s exactly),
descriptors stored as uint8 like COLMAP, turned into RootSIFT for matching.
``nn-ratio``: mutual nearest neighbours that also pass Lowe's ratio test, in RootSIFT space for
SIFT (uint8) descriptors and on the unit vectors of float (learned) ones (:func:`unit_descriptors`).
``xfeat`` / ``lighterglue``: XFeat features and the LighterGlue matcher (:mod:`.learned`, optional
extra ``gtkit[learned]``; named in the registry, imported (with torch) only when one is built).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..conventions import index_to_pixel
from ..errors import GtkitError


@dataclass
class Features:
    kp: np.ndarray     # (N, 2) float64 pixels, gtkit convention
    desc: np.ndarray   # (N, D) descriptors as stored (uint8 SIFT; float16 XFeat)
    image_size: tuple[int, int] | None = None  # (width, height) of the image; learned matchers need it

    def __len__(self):
        return len(self.kp)


def rootsift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelovic & Zisserman 2012): L1-normalise, then square root (unit L2)."""
    d = np.asarray(desc, dtype=np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-9)
    return np.sqrt(d)


def unit_descriptors(desc: np.ndarray) -> np.ndarray:
    """Descriptors as unit float32 vectors for matching and VLAD: RootSIFT for uint8 (SIFT)
    descriptors, L2-normalised for float (learned, signed) ones."""
    if np.asarray(desc).dtype == np.uint8:
        return rootsift(desc)
    d = np.asarray(desc, dtype=np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


# Bumped whenever an extractor's output changes for the same settings: database feature caches
# and finished localization runs are keyed on it, so they are recomputed, never mixed.
CODE_VERSION = {"sift": 2, "xfeat": 1}

# OpenCV's SIFT reports keypoints +0.25 px off in x and y (its first octave is the image doubled
# by linear interpolation, whose sample grid is shifted by a quarter pixel). Measured exactly with
# an image and its 180-degree rotated copy, which needs no resampling: detections p + b and
# W - p + b give b = +0.250 / +0.249 px (tests/test_localize_units.py). Subtracted in the pixels
# SIFT ran on, before scaling back.
OPENCV_SIFT_OFFSET_PX = 0.25


class SiftExtractor:
    name = "sift"

    def __init__(self, max_keypoints: int = 4000, max_side: int = 1024, contrast_threshold: float = 0.02):
        import cv2

        self.max_side = max_side
        self.sift = cv2.SIFT_create(nfeatures=max_keypoints, contrastThreshold=contrast_threshold)

    def extract(self, rgb: np.ndarray) -> Features:
        import cv2

        gray = cv2.cvtColor(np.asarray(rgb), cv2.COLOR_RGB2GRAY)
        h, w = gray.shape
        s = min(1.0, self.max_side / max(h, w))
        if s < 1.0:
            gray = cv2.resize(gray, (int(round(w * s)), int(round(h * s))), interpolation=cv2.INTER_AREA)
        kps, desc = self.sift.detectAndCompute(gray, None)
        if desc is None or not kps:
            return Features(np.zeros((0, 2)), np.zeros((0, 128), np.uint8))
        pts = index_to_pixel(np.array([k.pt for k in kps], dtype=np.float64)) - OPENCV_SIFT_OFFSET_PX
        sx, sy = w / gray.shape[1], h / gray.shape[0]
        pts *= (sx, sy)
        return Features(pts, np.clip(np.round(desc), 0, 255).astype(np.uint8))


class MutualNNRatioMatcher:
    name = "nn-ratio"

    def __init__(self, ratio: float = 0.85):
        self.ratio = ratio

    def match(self, a: Features, b: Features) -> np.ndarray:
        """One dense similarity matrix (BLAS) instead of a k-d tree or OpenCV's brute force:
        the vectors are unit length, so squared distance = 2 - 2 * similarity."""
        if len(a) < 2 or len(b) < 2:
            return np.zeros((0, 2), int)
        S = unit_descriptors(a.desc) @ unit_descriptors(b.desc).T
        back = S.argmax(axis=0)                  # best a for every b (mutual check)
        rows = np.arange(len(a))
        j1 = S.argmax(axis=1)
        s1 = S[rows, j1].copy()
        S[rows, j1] = -np.inf
        s2 = S.max(axis=1)
        d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1, 0.0))
        d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2, 0.0))
        keep = (d1 < self.ratio * d2) & (back[j1] == rows)
        return np.stack([rows[keep], j1[keep]], axis=1).astype(int)


# The registry names each part by "module:class"; a module is imported only when its part is built,
# so this module never imports the learned one (which imports Features from here) and torch loads
# only for a learned part.
EXTRACTORS = {"sift": "gtkit.localize.features:SiftExtractor", "xfeat": "gtkit.localize.learned:XFeatExtractor"}
MATCHERS = {"nn-ratio": "gtkit.localize.features:MutualNNRatioMatcher",
            "lighterglue": "gtkit.localize.learned:LighterGlueMatcher"}


def _load(spec: str):
    import importlib

    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def make_extractor(name: str, **kw):
    if name not in EXTRACTORS:
        raise GtkitError(f"unknown feature extractor {name!r} (available: {', '.join(EXTRACTORS)})")
    return _load(EXTRACTORS[name])(**kw)


def make_matcher(name: str, **kw):
    if name not in MATCHERS:
        raise GtkitError(f"unknown matcher {name!r} (available: {', '.join(MATCHERS)})")
    return _load(MATCHERS[name])(**kw)


# --- on-disk feature store (one HDF5 group per image, like hloc) ---------------------------------

def write_features(h5, name: str, f: Features) -> None:
    if name in h5:
        del h5[name]
    g = h5.create_group(name)
    g.create_dataset("kp", data=f.kp.astype(np.float32))
    g.create_dataset("desc", data=f.desc)
    if f.image_size is not None:
        g.attrs["image_size"] = np.asarray(f.image_size, dtype=np.int64)


def read_features(h5, name: str) -> Features:
    g = h5[name]
    size = g.attrs.get("image_size")
    return Features(g["kp"][()].astype(np.float64), g["desc"][()],
                    None if size is None else (int(size[0]), int(size[1])))
