"""Sensor priors: the rotation prior filter for retrieval (UAVD4L eq. 3.1) and the GPS radius.

A database view survives when each of its DJI angles (yaw, pitch, roll) differs from the
query's IMU/gimbal prior by at most ``gamma_o`` degrees, angles wrapped into (-180, 180].
The database's own angles are the exact ones it was rendered with (see
:mod:`gtkit.localize.grid`); the query's come from its DJI XMP gimbal tags.

At nadir (pitch -90) yaw and roll describe the same in-plane rotation; both the database and
DJI photos write roll 0 there, so comparing the angles as given stays meaningful.
"""
from __future__ import annotations

import numpy as np

from ..conventions import wrap_deg


def angle_differences(prior_ypr, views_ypr: np.ndarray) -> np.ndarray:
    """(N, 3) absolute wrapped differences (deg) between a prior (yaw, pitch, roll) and views."""
    d = np.asarray(views_ypr, dtype=np.float64) - np.asarray(prior_ypr, dtype=np.float64)[None]
    return np.abs(wrap_deg(d))


def rotation_filter(prior_ypr, views_ypr: np.ndarray, gamma_o: float = 30.0) -> np.ndarray:
    """Boolean mask of the views within ``gamma_o`` degrees of the prior on every angle."""
    if len(views_ypr) == 0:
        return np.zeros(0, bool)
    return (angle_differences(prior_ypr, views_ypr) <= gamma_o).all(axis=1)


def gps_filter(prior_xy, view_centers: np.ndarray, radius_m: float) -> np.ndarray:
    """Boolean mask of the views whose camera centre lies within ``radius_m`` (horizontal)."""
    c = np.asarray(view_centers, dtype=np.float64)[:, :2]
    return np.linalg.norm(c - np.asarray(prior_xy, dtype=np.float64)[None, :2], axis=1) <= radius_m
