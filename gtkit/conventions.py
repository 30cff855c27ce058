"""The conventions of gtkit, written once.

Every other module imports these; none restates them.

World frame
    Metres in the project's projected CRS (see :mod:`gtkit.geo`) minus a float64 local
    origin stored in ``project.toml``: x = easting, y = northing, z = height (up).
    Heights are whatever the input gave (GPS ellipsoidal heights for DJI photos); gtkit
    never changes the vertical datum silently.

Pose
    A pose is *world-to-camera*: ``x_cam = R @ x_world + t``. The camera centre is
    ``C = -R.T @ t``. Camera axes are OpenCV's: x right, y down, z forward (optical axis).
    Quaternions are ordered ``(qw, qx, qy, qz)`` (COLMAP, hloc, UAVD4L).

Pixels
    COLMAP's convention: the *centre* of the top-left pixel is at (0.5, 0.5); the image
    spans [0, W] x [0, H]. A numpy array index (row i, column j) is the pixel whose centre
    is (j + 0.5, i + 0.5). Use :func:`pixel_to_index` / :func:`index_to_pixel`.

DJI attitude
    Gimbal (and flight) angles in degrees: yaw clockwise from true north, pitch from the
    horizon (0 = horizon, -90 = nadir, positive = up), roll about the optical axis
    (positive = right side down, as seen from behind the camera). They are the intrinsic
    Z-Y-X (yaw, pitch, roll) Euler angles of the camera body in a north-east-down frame,
    the body axes being x forward (optical axis), y right, z down.
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "UP", "GRAVITY_WORLD", "pixel_to_index", "index_to_pixel", "quat_to_rotmat", "rotmat_to_quat",
    "camera_center", "translation_from_center", "dji_to_rotation", "rotation_to_dji",
    "gravity_in_camera", "rotation_angle_deg", "wrap_deg", "angle_between_deg",
]

UP = np.array([0.0, 0.0, 1.0])
GRAVITY_WORLD = -UP  # the direction gravity pulls, in world coordinates

# --- pixels -----------------------------------------------------------------------------


def pixel_to_index(xy: np.ndarray) -> np.ndarray:
    """Pixel coordinates (COLMAP convention) -> continuous array coordinates (col, row),
    where integer values are pixel centres (OpenCV's convention, e.g. for cv2.remap)."""
    return np.asarray(xy, dtype=np.float64) - 0.5


def index_to_pixel(ij: np.ndarray) -> np.ndarray:
    """Continuous array coordinates (col, row) with integer pixel centres -> COLMAP pixels."""
    return np.asarray(ij, dtype=np.float64) + 0.5


# --- rotations and poses ----------------------------------------------------------------


def quat_to_rotmat(q_wxyz) -> np.ndarray:
    q = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (qw, qx, qy, qz) with qw >= 0."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -np.asarray(R).T @ np.asarray(t, dtype=np.float64)


def translation_from_center(R: np.ndarray, C: np.ndarray) -> np.ndarray:
    return -np.asarray(R) @ np.asarray(C, dtype=np.float64)


# World (x east, y north, z up) from north-east-down.
_WORLD_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# Body (x forward, y right, z down) from OpenCV camera (x right, y down, z forward).
_BODY_FROM_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def dji_to_rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """DJI gimbal angles (degrees) -> world-to-camera rotation R (OpenCV camera axes)."""
    ned_from_body = Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    world_from_cam = _WORLD_FROM_NED @ ned_from_body @ _BODY_FROM_CAM
    return world_from_cam.T


def rotation_to_dji(R: np.ndarray) -> tuple[float, float, float]:
    """World-to-camera rotation -> DJI (yaw, pitch, roll) in degrees, yaw in (-180, 180].

    At pitch = -90 (exact nadir) yaw and roll are not separable; the roll is then set to 0.
    """
    ned_from_body = _WORLD_FROM_NED.T @ np.asarray(R).T @ _BODY_FROM_CAM.T
    with warnings.catch_warnings():  # exact nadir is gimbal lock by design; documented above
        warnings.simplefilter("ignore", UserWarning)
        yaw, pitch, roll = Rotation.from_matrix(ned_from_body).as_euler("ZYX", degrees=True)
    return float(wrap_deg(yaw)), float(pitch), float(wrap_deg(roll))


def gravity_in_camera(R: np.ndarray) -> np.ndarray:
    """Unit gravity direction expressed in camera coordinates for world-to-camera R."""
    return np.asarray(R) @ GRAVITY_WORLD


def wrap_deg(a):
    """Wrap angles (degrees) into (-180, 180]."""
    w = np.mod(np.asarray(a, dtype=np.float64) + 180.0, 360.0) - 180.0
    w = np.where(w == -180.0, 180.0, w)
    return w if w.ndim else float(w)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, in degrees."""
    # via the quaternion of the relative rotation: precise for tiny angles, unlike arccos(trace)
    rel = Rotation.from_matrix(np.asarray(R_a).T @ np.asarray(R_b))
    return float(np.degrees(rel.magnitude()))


def angle_between_deg(u: np.ndarray, v: np.ndarray) -> float:
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    c = u @ v / (np.linalg.norm(u) * np.linalg.norm(v))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
