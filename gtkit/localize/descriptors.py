"""Global image descriptors for retrieval, chosen by name.

``vlad``: VLAD (Jegou et al. 2010) on RootSIFT (or on unit learned descriptors, e.g. XFeat's) with a k-means codebook trained on the database's
own descriptors (nothing downloaded): residuals summed per visual word, intra-normalised
(Arandjelovic & Zisserman 2013), signed square root, L2. Similarity = dot product.
"""
from __future__ import annotations

import numpy as np

from ..errors import GtkitError
from .features import unit_descriptors


class Vlad:
    name = "vlad"

    def __init__(self, centers: np.ndarray):
        self.centers = np.asarray(centers, dtype=np.float32)

    @classmethod
    def train(cls, descriptors: np.ndarray, k: int = 64, seed: int = 0, iterations: int = 20) -> "Vlad":
        """k-means codebook on (uint8 SIFT or float learned) descriptors."""
        import cv2

        x = unit_descriptors(descriptors)
        if len(x) < k:
            raise GtkitError(f"too few descriptors ({len(x)}) to train a {k}-word VLAD codebook")
        cv2.setRNGSeed(seed)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, iterations, 1e-4)
        _, _, centers = cv2.kmeans(x, k, None, crit, 1, cv2.KMEANS_PP_CENTERS)
        return cls(centers)

    @property
    def dim(self) -> int:
        return self.centers.size

    def describe(self, descriptors: np.ndarray) -> np.ndarray:
        """Descriptors of one image (uint8 SIFT or float learned) -> unit VLAD vector (float32)."""
        k, d = self.centers.shape
        v = np.zeros((k, d), np.float32)
        if len(descriptors):
            x = unit_descriptors(descriptors)
            d2 = (x * x).sum(1)[:, None] - 2 * x @ self.centers.T + (self.centers ** 2).sum(1)[None]
            a = d2.argmin(1)
            np.add.at(v, a, x - self.centers[a])
        n = np.linalg.norm(v, axis=1, keepdims=True)
        v = np.where(n > 0, v / np.maximum(n, 1e-12), 0)
        v = np.sign(v) * np.sqrt(np.abs(v))
        v = v.ravel()
        return v / max(float(np.linalg.norm(v)), 1e-12)

    def save(self, path) -> None:
        from ..io.atomic import atomic_path

        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.save(f, self.centers)

    @classmethod
    def load(cls, path) -> "Vlad":
        return cls(np.load(path))


DESCRIPTORS = {"vlad": Vlad}
