"""Where "up" is in an SfM block's own frame, from what the photos say about gravity.

Two sources, best first:
- **gimbal attitude** (DJI XMP gimbal yaw/pitch/roll): each photo's camera-frame gravity, carried
  into the block's frame by its SfM rotation; the robust mean over photos (a wrong tag is dropped);
- **the aerial prior** (no attitude: consumer cameras): photos look down (the mean optical axis
  points down: its sign is never in doubt for aerial photos 15-90 deg below the horizon), and a
  camera held level has its image x axis horizontal (true of nadir and oblique photos alike), so up
  is the direction most nearly perpendicular to every photo's x axis, taken on the downward side.

A third, **the level prior** (``up_from_level_prior``: photos taken level and upright, as of a
facade from the ground), is used by the georegistration only where the positions or GCPs show a
level capture, and only for what they cannot hold.

``block_up(rec, metas)`` returns the unit vector and how it was found, with a spread (degrees) that
says how well the photos agree. The georegistration holds the block's tilt by it where the GPS
positions cannot (gtkit.sfm.gps_fit), and checks every fit against it (gtkit.sfm.plausibility).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from ..conventions import dji_to_rotation


@dataclass
class Up:
    vector: np.ndarray     # unit, in the block's frame
    source: str            # "gimbal" | "aerial prior" | "level prior"
    n_photos: int
    spread_deg: float      # how far single photos' estimates lie from it (robust), degrees
    sigma_deg: float       # the estimate's own uncertainty, degrees

    def record(self) -> dict:
        return {"source": self.source, "n_photos": int(self.n_photos), "spread_deg": round(float(self.spread_deg), 3),
                "sigma_deg": round(float(self.sigma_deg), 3)}


def _axes(rec: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    """{photo: its rotation cam_from_world (rows = camera x, y, z axes in the block's frame)}."""
    return {im.name: im.cam_from_world().rotation.matrix() for im in rec.images.values() if im.has_pose}


def _angles_deg(u: np.ndarray, vs: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(vs @ u, -1.0, 1.0)))


def _robust_mean(vs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised mean of unit vectors, twice with those > 3 robust spreads (>= 2 deg) off dropped."""
    keep = np.ones(len(vs), bool)
    u = vs.mean(0)
    for _ in range(3):
        u = vs[keep].mean(0)
        u /= np.linalg.norm(u)
        a = _angles_deg(u, vs)
        lim = max(2.0, 3.0 * 1.4826 * float(np.median(a[keep])))
        new = a <= lim
        if new.sum() < max(2, len(vs) // 2) or np.array_equal(new, keep):
            break
        keep = new
    return u, keep


def up_from_gimbal(rec: pycolmap.Reconstruction, metas: dict) -> Up | None:
    """Up from the photos' gimbal attitude (at least 3 photos with gimbal tags)."""
    R = _axes(rec)
    vs = []
    for n, Rcw in R.items():
        m = metas.get(n)
        if m is None or not m.has_gimbal:
            continue
        g_cam = dji_to_rotation(m.gimbal_yaw, m.gimbal_pitch, m.gimbal_roll) @ np.array([0.0, 0.0, 1.0])
        vs.append(Rcw.T @ g_cam)   # world up seen from the camera, in the block's frame
    if len(vs) < 3:
        return None
    vs = np.array(vs)
    u, keep = _robust_mean(vs)
    a = _angles_deg(u, vs[keep])
    spread = float(1.4826 * np.median(a)) if len(a) else 0.0
    return Up(u, "gimbal", int(keep.sum()), spread, spread / np.sqrt(max(1, keep.sum())))


def up_from_aerial_prior(rec: pycolmap.Reconstruction, min_eig_ratio: float = 4.0) -> Up | None:
    """Up from photos that look down with their image x axis level (see the module docstring)."""
    R = _axes(rec)
    if len(R) < 3:
        return None
    Rs = np.array(list(R.values()))
    xs, zs = Rs[:, 0, :], Rs[:, 2, :]
    down = zs.mean(0)
    if np.linalg.norm(down) < 0.2:   # the photos look every way: no aerial block
        return None
    u0 = -down / np.linalg.norm(down)
    w, V = np.linalg.eigh(xs.T @ xs / len(xs))
    if w[1] >= min_eig_ratio * max(w[0], 1e-12):
        u = V[:, 0] * np.sign(V[:, 0] @ u0)          # level x axes in several directions: the common normal
    else:                                            # x axes all alike (one flight direction): tilt about them from the axes
        x = V[:, 2]
        u = u0 - (u0 @ x) * x
        u /= np.linalg.norm(u)
    if np.degrees(np.arccos(np.clip(u @ u0, -1, 1))) > 45.0:
        u = u0      # the level-x-axis estimate disagrees with "photos look down": keep the safer one
    # single photos' disagreement: how far each x axis is from level
    tilt = np.degrees(np.abs(np.arcsin(np.clip(xs @ u, -1, 1))))
    spread = float(1.4826 * np.median(tilt))
    return Up(u, "aerial prior", len(Rs), spread, spread / np.sqrt(len(Rs)))


def up_from_level_prior(rec: pycolmap.Reconstruction, min_sigma_deg: float = 2.0) -> Up | None:
    """Up from photos taken level and upright (a terrestrial or facade capture): every image x axis
    horizontal and the image y axis pointing down on average. A prior for level photos only: the
    mean pitch of hand-held photos is not zero, so its uncertainty is never under ``min_sigma_deg``
    (it holds only what the positions or GCPs cannot, e.g. the roll about a single strip's line)."""
    R = _axes(rec)
    if len(R) < 3:
        return None
    Rs = np.array(list(R.values()))
    xs, ys = Rs[:, 0, :], Rs[:, 1, :]
    u = -ys.mean(0)
    if np.linalg.norm(u) < 0.5:
        return None
    u /= np.linalg.norm(u)
    w, V = np.linalg.eigh(xs.T @ xs / len(xs))
    if w[1] >= 4.0 * max(w[0], 1e-12):   # x axes in several directions: their common normal
        v = V[:, 0] * np.sign(V[:, 0] @ u)
        if np.degrees(np.arccos(np.clip(v @ u, -1, 1))) < 30.0:
            u = v
    a = _angles_deg(u, -ys)
    spread = float(1.4826 * np.median(a))
    return Up(u, "level prior", len(Rs), spread, max(spread / np.sqrt(len(Rs)), min_sigma_deg))


def block_up(rec: pycolmap.Reconstruction, metas: dict) -> Up | None:
    """Up in ``rec``'s frame: from gimbal attitude where photos carry it, else the aerial prior."""
    return up_from_gimbal(rec, metas) or up_from_aerial_prior(rec)


def rotation_to_z(u: np.ndarray) -> np.ndarray:
    """A rotation taking the unit vector ``u`` to +z (the smallest one)."""
    u = np.asarray(u, float) / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(u, z)
    s, c = np.linalg.norm(v), float(u @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
