"""A typed world-to-camera pose (see :mod:`gtkit.conventions`), validated on construction."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .conventions import (camera_center, dji_to_rotation, quat_to_rotmat, rotation_angle_deg,
                          rotmat_to_quat, translation_from_center)
from .errors import GtkitError


def skew(v) -> np.ndarray:
    """The cross-product matrix: ``skew(a) @ b == np.cross(a, b)``."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=np.float64)


@dataclass(frozen=True, eq=False)
class Pose:
    """World-to-camera rigid transform ``x_cam = R @ x_world + t``.

    ``covariance`` (optional) is 6x6 over (rotation vector [rad], translation [m]) of the
    world-to-camera pose for the left perturbation ``R' = exp(dr) R, t' = t + dt``
    (:meth:`from_pycolmap` converts pycolmap's to this).
    """

    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray | None = None

    def __post_init__(self):
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise GtkitError(f"pose needs R 3x3 and t 3, got {R.shape} and {t.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise GtkitError("pose has NaN or infinite values")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
            raise GtkitError("pose rotation is not orthonormal with det +1")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        if self.covariance is not None:
            c = np.asarray(self.covariance, dtype=np.float64)
            if c.shape != (6, 6):
                raise GtkitError(f"pose covariance must be 6x6, got {c.shape}")
            object.__setattr__(self, "covariance", c)

    @classmethod
    def identity(cls) -> "Pose":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_qt(cls, q_wxyz, t) -> "Pose":
        q = np.asarray(q_wxyz, dtype=np.float64)
        n = np.linalg.norm(q)
        if not np.isfinite(n) or abs(n - 1.0) > 1e-3:
            raise GtkitError(f"quaternion is not unit length (|q| = {n:.6g})")
        return cls(quat_to_rotmat(q / n), t)

    @classmethod
    def from_center(cls, R, C) -> "Pose":
        return cls(R, translation_from_center(R, C))

    @classmethod
    def from_dji(cls, yaw_deg, pitch_deg, roll_deg, C) -> "Pose":
        R = dji_to_rotation(yaw_deg, pitch_deg, roll_deg)
        return cls.from_center(R, C)

    @classmethod
    def from_pycolmap(cls, rigid, covariance=None) -> "Pose":
        """From a pycolmap ``Rigid3d`` (cam_from_world), with optionally the 6x6 covariance that
        pycolmap's ``BACovariance.get_cam_cov_from_world`` gives. That one is in Ceres' quaternion
        tangent space, whose rotation part is *half* the rotation vector (``q = [cos|d|, sin|d| d/|d|]``
        turns by 2|d|; measured: its rotation block is 1/4 of the rotation-vector covariance of the
        same problem), so rotation rows and columns are scaled by 2 here."""
        if covariance is not None:
            J = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])
            covariance = J @ np.asarray(covariance, dtype=np.float64) @ J
        return cls(rigid.rotation.matrix(), rigid.translation, covariance)

    def to_pycolmap(self):
        import pycolmap

        return pycolmap.Rigid3d(pycolmap.Rotation3d(self.R), self.t)

    @property
    def q(self) -> np.ndarray:
        return rotmat_to_quat(self.R)

    @property
    def center(self) -> np.ndarray:
        return camera_center(self.R, self.t)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 world-to-camera."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    def inverse_matrix(self) -> np.ndarray:
        """4x4 camera-to-world."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R.T, self.center
        return m

    def transform(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> camera frame."""
        return np.asarray(points_world, dtype=np.float64) @ self.R.T + self.t

    def center_covariance(self) -> np.ndarray | None:
        """3x3 covariance of the camera centre C = -R^T t under the covariance's left perturbation
        (``R' = exp(dr) R``, ``t' = t + dt``): C' = -R^T exp(-dr) (t + dt), so
        dC = R^T (-[t]_x dr - dt). None without a covariance."""
        if self.covariance is None:
            return None
        J = self.center_jacobian()
        return J @ self.covariance @ J.T

    def center_jacobian(self) -> np.ndarray:
        """3x6 derivative of the camera centre with respect to the covariance's (dr, dt):
        R^T [-[t]_x, -I] (see :meth:`center_covariance`)."""
        return self.R.T @ np.concatenate([-skew(self.t), -np.eye(3)], axis=1)

    def point_jacobian(self, X: np.ndarray) -> np.ndarray:
        """3x6 derivative of a world point's camera-frame position ``R X + t`` with respect to the
        covariance's (dr, dt) (left perturbation, as in :meth:`center_covariance`): [-[R X]_x, I]."""
        return np.concatenate([-skew(self.R @ np.asarray(X, np.float64)), np.eye(3)], axis=1)

    def error_to(self, other: "Pose") -> tuple[float, float]:
        """(camera-centre distance in metres, rotation geodesic error in degrees)."""
        return float(np.linalg.norm(self.center - other.center)), rotation_angle_deg(self.R, other.R)

    def __repr__(self):
        c = self.center
        return f"Pose(center=[{c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}], q={np.round(self.q, 6).tolist()})"
