"""A smoothed track for a sequence of ground points: constant-velocity Kalman filter + RTS
smoother in 3D, each measurement weighted by its propagated covariance.

Process model: white-noise acceleration with spectral density ``accel_sigma**2`` per axis
(m/s^2; a car cornering ~2, a walking person ~0.5). Measurements whose innovation exceeds the
``gate_chi2`` (3 degrees of freedom) are flagged as outliers and left out of the update (never
two in a row, so a turn the model did not expect cannot make the filter drop the track).
On the small sample (shots 2 s apart, a car at 8 m/s turning at street corners) smoothing
changes the median error little (car 0.97 -> 1.02 m, person 0.80 -> 0.77 m with noisy poses):
the errors of one shot are mostly systematic (its pose), not frame-to-frame jitter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SmoothingSettings:
    accel_sigma: float = 3.0       # m/s^2, process noise (white acceleration) per axis
    meas_sigma_m: float = 2.0      # per-axis sigma of a point without a propagated covariance
    gate_chi2: float = 16.27       # 3-dof chi-square at p = 0.001; innovations above it are outliers
    init_speed_sigma: float = 20.0  # m/s, prior on the first velocity


def smooth_track(times, points, covs=None, s: SmoothingSettings = SmoothingSettings()) -> dict:
    """RTS-smoothed positions (N, 3), their covariances (N, 3, 3), velocities, and an outlier
    mask, for measurements sorted or not (the output follows the input order)."""
    t = np.asarray(times, float)
    z = np.asarray(points, float)
    n = len(t)
    order = np.argsort(t, kind="stable")
    t, z = t[order], z[order]
    Rm = np.empty((n, 3, 3))
    for k, i in enumerate(order):
        c = None if covs is None else covs[i]
        Rm[k] = np.eye(3) * s.meas_sigma_m ** 2 if c is None else np.asarray(c) + np.eye(3) * 1e-4
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    xf = np.zeros((n, 6))
    Pf = np.zeros((n, 6, 6))
    xp_all = np.zeros((n, 6))
    Pp_all = np.zeros((n, 6, 6))
    F_all = np.zeros((n, 6, 6))
    outlier = np.zeros(n, bool)
    x = np.concatenate([z[0], np.zeros(3)])
    P = np.diag([*np.diag(Rm[0]), *(np.full(3, s.init_speed_sigma ** 2))])
    q = s.accel_sigma ** 2
    for k in range(n):
        dt = 0.0 if k == 0 else t[k] - t[k - 1]
        F = np.eye(6)
        F[:3, 3:] = np.eye(3) * dt
        Q = np.zeros((6, 6))
        Q[:3, :3] = np.eye(3) * q * dt ** 3 / 3
        Q[:3, 3:] = Q[3:, :3] = np.eye(3) * q * dt ** 2 / 2
        Q[3:, 3:] = np.eye(3) * q * dt
        if k > 0:
            x = F @ x
            P = F @ P @ F.T + Q
        xp_all[k], Pp_all[k], F_all[k] = x, P, F
        y = z[k] - H @ x
        S = H @ P @ H.T + Rm[k]
        # gate, but never two in a row: a manoeuvre the model did not expect must not lose the track
        if k > 0 and not outlier[k - 1] and float(y @ np.linalg.solve(S, y)) > s.gate_chi2:
            outlier[k] = True
        else:
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ y
            P = (np.eye(6) - K @ H) @ P
        xf[k], Pf[k] = x, P
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(n - 2, -1, -1):
        Pp = Pp_all[k + 1]
        C = Pf[k] @ F_all[k + 1].T @ np.linalg.pinv(Pp)
        xs[k] = xf[k] + C @ (xs[k + 1] - xp_all[k + 1])
        Ps[k] = Pf[k] + C @ (Ps[k + 1] - Pp) @ C.T
    inv = np.empty(n, int)
    inv[order] = np.arange(n)
    return {"points": xs[inv, :3], "velocity": xs[inv, 3:], "cov": Ps[inv, :3, :3], "outlier": outlier[inv]}
