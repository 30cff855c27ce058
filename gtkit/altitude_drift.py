"""A photo's GPS altitude drift: the part of a consumer GPS altitude that drifted over the
reference flight, as the reference block's gravity-held GPS fit (``gtkit.sfm.gps_fit``) measured it,
for the stages that use query photos' GPS altitudes (the localization database's heights, the
localization priors). Below both: it reads the fit's record, a plain dict."""
from __future__ import annotations


def altitude_drift_at(fit: dict | None, t: float | None, margin: float = 0.1) -> float | None:
    """How far the GPS altitude of a photo taken at ``t`` (EXIF capture time, seconds) is off by the
    drift that the reference flight's gravity-held fit (``fit``, its record) found: subtract it from
    the photo's GPS altitude. None where no drift was fitted or ``t`` lies outside the flight (by more
    than ``margin`` of its length): another flight's altitudes drift their own way."""
    if not fit or t is None or not fit.get("altitude_drift_m") or not fit.get("flight_seconds") \
            or fit.get("drift_time_start_s") is None:
        return None
    span = float(fit["flight_seconds"])
    tau = (float(t) - float(fit["drift_time_start_s"])) / span
    if not -margin <= tau <= 1.0 + margin:
        return None
    return float(fit["altitude_drift_m"]) * (tau - float(fit.get("drift_tau_mid", 0.5)))
