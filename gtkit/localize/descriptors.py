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
        return self.describe_many([descriptors])[0]

    def describe_many(self, images: list[np.ndarray], batch_rows: int = 100_000) -> np.ndarray:
        """:meth:`describe` of many images, (N, dim) float32. The nearest words of several images'
        descriptors come from one matrix product (up to ``batch_rows`` rows): one small product a
        view cost ~8 ms of CPU in OpenBLAS's threads on the loaded 2-core machine, ~0.5 ms on one
        thread; residuals are summed per word with one ``reduceat`` (``np.add.at`` took ~4 ms a view)."""
        out = np.zeros((len(images), self.dim), np.float32)
        c2 = (self.centers ** 2).sum(1)[None]
        i = 0
        while i < len(images):
            j, rows = i, 0
            while j < len(images) and (j == i or rows + len(images[j]) <= batch_rows):
                rows += len(images[j])
                j += 1
            xs = [unit_descriptors(d) if len(d) else np.zeros((0, self.centers.shape[1]), np.float32)
                  for d in images[i:j]]
            x = np.concatenate(xs)
            words = (c2 - 2 * x @ self.centers.T).argmin(1) if len(x) else np.zeros(0, int)
            bounds = np.cumsum([0] + [len(a) for a in xs])
            for m in range(j - i):
                out[i + m] = self._vlad(xs[m], words[bounds[m]:bounds[m + 1]])
            i = j
        return out

    def _vlad(self, x: np.ndarray, a: np.ndarray) -> np.ndarray:
        k, d = self.centers.shape
        v = np.zeros((k, d), np.float32)
        if len(x):
            order = np.argsort(a, kind="stable")   # sum_i [a_i = j] (x_i - c_j), word by word
            sw = a[order]
            starts = np.flatnonzero(np.r_[True, sw[1:] != sw[:-1]])
            w = sw[starts]
            v[w] = np.add.reduceat(x[order], starts, axis=0) - np.diff(np.r_[starts, len(a)])[:, None] * self.centers[w]
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
