"""Georegistration by consumer-grade GPS: the block's tilt held by gravity, heading, scale and
horizontal position from the GPS positions, its height from the GPS altitudes with their drift.

A consumer drone or camera gives positions good to 2-20 m, an altitude that drifts by tens of metres
over a flight (barometric or GPS), often no attitude. A free Sim(3) fitted to such positions takes its
tilt from altitude errors (a drift along the flight lines tilts the block; with few inliers it may turn
it upside down). Here, instead:

1. the block is turned so that its own up (gtkit.sfm.gravity: gimbal attitude, else the aerial
   prior) is +z: its tilt is never taken from the positions;
2. heading, scale and horizontal offset: a 2D similarity fitted to the horizontal positions, least
   median of squares over pairs, then refitted on the inliers, the threshold from the positions'
   own scatter (3.03 sigma: 99 % of a 2D Gaussian), never under 3 x their stated accuracy;
3. height: the altitudes' offset from the block, with a linear drift over the flight's time where
   one is significant (Theil-Sen), inliers within 3 sigma of it; the block is placed at the
   drift's middle.

Everything is measured and returned: scatter horizontal and vertical, share kept, drift, and the
absolute accuracy the block can therefore claim.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from .geometry import RegistrationError
from .gravity import Up, rotation_to_z
from ..altitude_drift import altitude_drift_at  # noqa: F401  (a photo's drift from this fit's record)

RAYLEIGH_MEDIAN = 1.1774   # median of a 2D Gaussian's distance, in sigmas per axis
RAYLEIGH_99 = 3.035        # its 99 % quantile


@dataclass
class GpsFit:
    sim: pycolmap.Sim3d
    inliers: np.ndarray            # bool: horizontally and vertically consistent
    residuals_h: np.ndarray        # m, after the fit
    residuals_v: np.ndarray        # m, after the fit and the drift
    record: dict


def _fit2d(zs: np.ndarray, zt: np.ndarray, w: np.ndarray | None = None) -> tuple[complex, complex]:
    """Least-squares 2D similarity zt ~ a zs + b (complex numbers: a = scale x e^(i heading))."""
    w = np.ones(len(zs)) if w is None else w
    ms, mt = (w @ zs) / w.sum(), (w @ zt) / w.sum()
    ds, dt = zs - ms, zt - mt
    a = (w * np.conj(ds)) @ dt / max(float((w * np.abs(ds) ** 2).sum()), 1e-300)
    return a, mt - a * ms


def _lmeds2d(zs: np.ndarray, zt: np.ndarray, max_pairs: int, rng) -> tuple[complex, complex]:
    n = len(zs)
    if n * (n - 1) // 2 <= max_pairs:
        i, j = np.triu_indices(n, 1)
    else:
        i, j = rng.integers(0, n, max_pairs), rng.integers(0, n, max_pairs)
        ok = i != j
        i, j = i[ok], j[ok]
    dzs = zs[j] - zs[i]
    good = np.abs(dzs) > 1e-9
    i, j = i[good], j[good]
    a = (zt[j] - zt[i]) / (zs[j] - zs[i])
    b = zt[i] - a * zs[i]
    best, best_med = None, np.inf
    for k in range(0, len(a), 2048):  # residual medians of each hypothesis, in chunks
        r = np.abs(a[k:k + 2048, None] * zs[None] + b[k:k + 2048, None] - zt[None])
        med = np.median(r, axis=1)
        m = int(np.argmin(med))
        if med[m] < best_med:
            best_med, best = med[m], (a[k + m], b[k + m])
    if best is None:
        raise RegistrationError("the GPS positions coincide: heading and scale are undetermined")
    return best


def _theil_sen(t: np.ndarray, y: np.ndarray, rng, max_pairs: int = 20000) -> tuple[float, float]:
    n = len(t)
    if n * (n - 1) // 2 <= max_pairs:
        i, j = np.triu_indices(n, 1)
    else:
        i, j = rng.integers(0, n, max_pairs), rng.integers(0, n, max_pairs)
    dt = t[j] - t[i]
    ok = np.abs(dt) > 1e-9
    if ok.sum() < 3:
        return 0.0, float(np.median(y))
    slope = float(np.median((y[j] - y[i])[ok] / dt[ok]))
    return slope, float(np.median(y - slope * t))


# a common bias of positions without a stated accuracy does not show in their residuals; consumer
# GPS is biased by metres (horizontal) and more in height, so no less than this is claimed for it
UNSTATED_BIAS_H_M = 2.0
UNSTATED_BIAS_V_M = 5.0


def claimed_accuracy(scatter_h: float, scatter_v: float, stated: float | None) -> dict:
    """The absolute accuracy (1 sigma) a block placed by GPS alone can claim: its positions' scatter
    combined with a common bias that no residual shows (the stated accuracy, else as large as the
    scatter and never under UNSTATED_BIAS_H_M / _V_M)."""
    bias_h = stated if stated else max(scatter_h, UNSTATED_BIAS_H_M)
    bias_v = stated if stated else max(scatter_v, UNSTATED_BIAS_V_M)
    return {"scatter_h_m": round(float(scatter_h), 3), "scatter_v_m": round(float(scatter_v), 3),
            "absolute_accuracy_h_m": round(float(np.hypot(scatter_h, bias_h)), 3),
            "absolute_accuracy_v_m": round(float(np.hypot(scatter_v, bias_v)), 3),
            "bias_assumed": not stated}


def _effective_count(times: np.ndarray, res: np.ndarray, inl: np.ndarray) -> float:
    """How many independent positions the inliers are worth: n (1 - rho) / (1 + rho), rho the lag-one
    correlation of their residuals in capture order (>= 0)."""
    order = np.argsort(np.asarray(times, float)[inl], kind="stable")
    r = np.asarray(res)[inl][order]
    n = len(r)
    if n < 4:
        return float(n)
    x = np.concatenate([r.real - r.real.mean(), r.imag - r.imag.mean()])
    lag = np.concatenate([(r.real[1:] - r.real.mean()) * (r.real[:-1] - r.real.mean()),
                          (r.imag[1:] - r.imag.mean()) * (r.imag[:-1] - r.imag.mean())])
    rho = float(np.clip(lag.sum() / max(float((x ** 2).sum()), 1e-300), 0.0, 0.95))
    return max(2.0, n * (1 - rho) / (1 + rho))


def _mad(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else 0.0


def gravity_held_fit(names: list[str], src: np.ndarray, tgt: np.ndarray, times: np.ndarray, up: Up,
                     accuracy: np.ndarray | None = None, seed: int = 0, max_pairs: int = 4000,
                     min_scale_precision: float = 0.2) -> GpsFit:
    """The block (camera centres ``src`` in its frame) onto GPS positions ``tgt`` (local metres)
    with its tilt held by ``up``; ``times``: each photo's capture time (any unit, or its order);
    ``accuracy``: stated 1-sigma per position (0 = not stated). See the module docstring."""
    src, tgt = np.asarray(src, float), np.asarray(tgt, float)
    n = len(src)
    if n < 3:
        raise RegistrationError(f"only {n} photos with a GPS position (3 or more needed)")
    acc = np.zeros(n) if accuracy is None else np.asarray(accuracy, float)
    floor_h = max(0.01, 3.0 * float(np.median(acc)))
    rng = np.random.default_rng(seed)
    R0 = rotation_to_z(up.vector)
    s_up = src @ R0.T
    zs = s_up[:, 0] + 1j * s_up[:, 1]
    zt = tgt[:, 0] + 1j * tgt[:, 1]
    a, b = _lmeds2d(zs, zt, max_pairs, rng)
    inl_h = np.ones(n, bool)
    for _ in range(10):
        r = np.abs(a * zs + b - zt)
        sigma_h = max(float(np.median(r[inl_h] if inl_h.sum() >= 3 else r)) / RAYLEIGH_MEDIAN, floor_h / 3.0)
        new = r <= max(floor_h, RAYLEIGH_99 * sigma_h * 1.5)
        if new.sum() < 3:
            break
        a, b = _fit2d(zs[new], zt[new])
        if np.array_equal(new, inl_h):
            break
        inl_h = new
    r_h = np.abs(a * zs + b - zt)
    n_h = int(inl_h.sum())
    if n_h < 3:
        raise RegistrationError(f"only {n_h} of {n} GPS positions agree on one placement of the block "
                                "(3 or more needed): the positions are inconsistent")
    scale, heading = float(np.abs(a)), float(np.angle(a))
    if not np.isfinite(scale) or scale <= 0:
        raise RegistrationError("the GPS positions give no usable scale")
    # heading and scale precision from the spread of the positions against their scatter
    sigma_h = float(np.sqrt(np.sum(r_h[inl_h] ** 2) / max(1, 2 * (n_h - 2))))
    extent = float(np.sqrt(np.mean(np.abs(zt[inl_h] - zt[inl_h].mean()) ** 2)))
    # consumer GPS errors wander slowly: neighbours in time share theirs, so fewer positions count
    n_eff = _effective_count(times, (a * zs + b - zt), inl_h)
    rel_scale = sigma_h / max(extent, 1e-9) / np.sqrt(n_eff)
    if extent < 1e-6 or rel_scale > min_scale_precision:
        raise RegistrationError(
            f"the {n_h} consistent GPS positions spread over {extent:.1f} m with a scatter of {sigma_h:.1f} m: "
            f"too close together to fix the block's scale and heading (+/- {100 * rel_scale:.0f} %)")
    # height: offset and drift of the altitudes against the block, over the flight's time
    t = np.asarray(times, float)
    span = float(t.max() - t.min()) if len(t) else 0.0
    tau = (t - t.min()) / span if span > 0 else np.zeros(n)
    dz = tgt[:, 2] - scale * s_up[:, 2]
    sel = inl_h
    slope, icpt = _theil_sen(tau[sel], dz[sel], rng)
    res_drift = dz - (icpt + slope * tau)
    res_const = dz - float(np.median(dz[sel]))
    s_drift, s_const = _mad(res_drift[sel]), _mad(res_const[sel])
    n_v = int(sel.sum())
    slope_se = s_drift * np.sqrt(12.0 / max(n_v, 1))
    use_drift = span > 0 and abs(slope) > max(4.0 * slope_se, 1.0) and s_drift < 0.8 * s_const
    if not use_drift:
        slope, icpt = 0.0, float(np.median(dz[sel]))
    floor_v = max(0.01, floor_h)
    res_v = dz - (icpt + slope * tau)
    sigma_v = max(_mad(res_v[sel]), floor_v / 3.0)
    inl_v = np.abs(res_v) <= max(floor_v, 3.0 * sigma_v)
    inl = inl_h & inl_v
    if inl.sum() < max(3, 0.5 * n_h):
        raise RegistrationError(
            f"inconsistent altitudes: only {int(inl.sum())} of the {n_h} horizontally consistent GPS positions agree "
            f"with one altitude offset{' and drift' if use_drift else ''} (scatter {sigma_v:.1f} m)")
    tau_mid = float(np.median(tau[inl])) if inl.any() else 0.5
    tz = float(np.median((dz - slope * (tau - tau_mid))[inl])) if inl.any() else icpt + slope * tau_mid
    # the whole transform: world = scale * Rz(heading) R0 src + (Re b, Im b, tz)
    c, s = np.cos(heading), np.sin(heading)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = Rz @ R0
    sim = pycolmap.Sim3d(scale, pycolmap.Rotation3d(R), np.array([b.real, b.imag, tz]))
    world = scale * src @ R.T + np.array([b.real, b.imag, tz])
    res_v_final = tgt[:, 2] - world[:, 2] - slope * (tau - tau_mid)
    drift_m = float(slope)
    sigma_h_axis = sigma_h
    record = {
        "mode": "gravity-held", "tilt_from": up.source, "up": up.record(),
        "n_positions": n, "n_inliers": int(inl.sum()), "share_kept": round(float(inl.mean()), 3),
        "n_horizontal_inliers": n_h, "n_vertical_inliers": int((inl_v & inl_h).sum()),
        "horizontal_residual_median_m": float(np.median(r_h[inl])) if inl.any() else None,
        "vertical_residual_median_m": float(np.median(np.abs(res_v_final[inl]))) if inl.any() else None,
        "sigma_h_m": sigma_h_axis, "sigma_v_m": sigma_v,
        "altitude_drift_m": drift_m if use_drift else 0.0,
        # when the drift is zero (capture time, seconds) and how it runs: see altitude_drift_at
        "drift_time_start_s": float(t.min()) if span > 0 else None, "drift_tau_mid": tau_mid,
        "altitude_offset_m": float(tz),
        "flight_seconds": span if span > 0 else None,
        "scale_precision": float(rel_scale),
        "heading_precision_deg": float(np.degrees(rel_scale)),
        # what the site can claim in absolute terms: a common GPS bias would not show in the
        # residuals, so the single-position scatter bounds it; heights also carry the drift's unknown zero
        "n_effective": round(float(n_eff), 1),
        **claimed_accuracy(sigma_h_axis, float(sigma_v + abs(drift_m if use_drift else 0.0) / 2.0),  # heights: + half the drift
                           float(np.median(acc)) if np.any(acc > 0) else None),
    }
    return GpsFit(sim, inl, r_h, res_v_final, record)
