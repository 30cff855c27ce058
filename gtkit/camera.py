"""Camera intrinsics in COLMAP's camera models, with projection in numpy.

Pixel coordinates follow :mod:`gtkit.conventions` (top-left pixel centre at (0.5, 0.5)),
which is also COLMAP's, so params are COLMAP's unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import GtkitError

# model name -> parameter names (COLMAP order)
MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


def distort(xn: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Normalised coordinates (..., 2) -> distorted, OpenCV (k1, k2, p1, p2) ``d`` (4,) or one per point (..., 4)."""
    k1, k2, p1, p2 = (d[..., i] for i in range(4))
    x, y = xn[..., 0], xn[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


@dataclass(frozen=True)
class Camera:
    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self):
        if self.model not in MODELS:
            raise GtkitError(f"unsupported camera model {self.model!r} (supported: {', '.join(MODELS)})")
        if len(self.params) != len(MODELS[self.model]):
            raise GtkitError(f"camera model {self.model} needs {len(MODELS[self.model])} params "
                             f"({' '.join(MODELS[self.model])}), got {len(self.params)}")
        if self.width <= 0 or self.height <= 0 or not np.all(np.isfinite(self.params)):
            raise GtkitError(f"invalid camera {self.model} {self.width}x{self.height} {self.params}")
        object.__setattr__(self, "params", tuple(float(p) for p in self.params))

    # --- construction --------------------------------------------------------------
    @classmethod
    def pinhole(cls, width: int, height: int, fx: float, fy: float | None = None,
                cx: float | None = None, cy: float | None = None) -> "Camera":
        cx = width / 2.0 if cx is None else cx
        cy = height / 2.0 if cy is None else cy
        return cls("PINHOLE", int(width), int(height), (fx, fx if fy is None else fy, cx, cy))

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> "Camera":
        f = width / 2.0 / np.tan(np.radians(hfov_deg) / 2.0)
        return cls.pinhole(width, height, f)

    @classmethod
    def from_pycolmap(cls, cam) -> "Camera":
        return cls(cam.model.name, int(cam.width), int(cam.height), tuple(cam.params))

    def to_pycolmap(self):
        import pycolmap

        return pycolmap.Camera(model=self.model, width=self.width, height=self.height, params=list(self.params))

    # --- parameters ----------------------------------------------------------------
    def _p(self) -> dict:
        return dict(zip(MODELS[self.model], self.params))

    @property
    def fx(self) -> float:
        p = self._p()
        return p.get("fx", p.get("f"))

    @property
    def fy(self) -> float:
        p = self._p()
        return p.get("fy", p.get("f"))

    @property
    def cx(self) -> float:
        return self._p()["cx"]

    @property
    def cy(self) -> float:
        return self._p()["cy"]

    @property
    def distortion(self) -> np.ndarray:
        """OpenCV-ordered (k1, k2, p1, p2); zeros for undistorted models."""
        p = self._p()
        return np.array([p.get("k1", p.get("k", 0.0)), p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0)])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    def K(self) -> np.ndarray:
        """3x3 calibration matrix in COLMAP pixel convention."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def pinhole_part(self) -> "Camera":
        """The same camera without distortion."""
        return Camera.pinhole(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    def scaled(self, s: float) -> "Camera":
        """The camera for the image resized by factor ``s`` (pixel convention kept)."""
        w, h = int(round(self.width * s)), int(round(self.height * s))
        sx, sy = w / self.width, h / self.height
        p = self._p()
        new = []
        for name, v in p.items():
            if name in ("fx", "cx"):
                new.append(v * sx)
            elif name in ("fy", "cy"):
                new.append(v * sy)
            elif name == "f":
                new.append(v * (sx + sy) / 2)
            else:
                new.append(v)
        return Camera(self.model, w, h, tuple(new))

    def hfov_deg(self) -> float:
        return float(np.degrees(2 * np.arctan(self.width / 2.0 / self.fx)))

    # --- projection ----------------------------------------------------------------
    def _distort(self, xn: np.ndarray) -> np.ndarray:
        return distort(xn, self.distortion)

    def world_to_image(self, xn: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (x/z, y/z) -> pixels, distortion applied."""
        xn = np.asarray(xn, dtype=np.float64)
        xd = self._distort(xn) if self.has_distortion else xn
        return np.stack([self.fx * xd[..., 0] + self.cx, self.fy * xd[..., 1] + self.cy], axis=-1)

    def image_to_world(self, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels -> normalised image coordinates (x/z, y/z), distortion removed."""
        uv = np.asarray(uv, dtype=np.float64)
        xd = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        if not self.has_distortion:
            return xd
        x = xd.copy()
        for _ in range(iterations):  # fixed-point iteration, converges for mild distortion
            x = x - (self._distort(x) - xd)
        return x

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Pixels of this camera -> the same rays' pixels in :meth:`pinhole_part` (distortion removed)."""
        return self.pinhole_part().world_to_image(self.image_to_world(uv))

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (N, 3) -> (pixels (N, 2), in_front mask)."""
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        front = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = p[..., :2] / z[..., None]
        return self.world_to_image(xn), front

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Pixels -> unit viewing rays in camera coordinates."""
        xn = self.image_to_world(uv)
        d = np.concatenate([xn, np.ones(xn.shape[:-1] + (1,))], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv)
        return ((uv[..., 0] >= margin) & (uv[..., 0] <= self.width - margin)
                & (uv[..., 1] >= margin) & (uv[..., 1] <= self.height - margin))

    def to_line(self) -> str:
        return f"{self.model} {self.width} {self.height} " + " ".join(repr(p) for p in self.params)
