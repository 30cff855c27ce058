"""Tie-point residuals after registration, as the register stage reports them (if it has run).

Accepted shapes of ``work/register/tiepoint_residuals.json`` (the first that matches):
``{"tiepoints": [{"id", "residual_px", "inlier"?, "observations"?: [{"image", "residual_px"}]}]}``,
``{"tiepoints": {"tp1": {...} | 1.2}}`` or a plain ``{"tp1": 1.2}``. Missing file = no residuals.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

CANDIDATES = ("tiepoint_residuals.json", "tiepoints_residuals.json", "residuals.json")


@dataclass
class Residual:
    residual_px: float
    inlier: bool | None = None
    per_image: dict[str, float] = field(default_factory=dict)


def residual_file(paths) -> Path | None:
    d = paths.stage("register")
    return next((d / n for n in CANDIDATES if (d / n).is_file()), None)


def _num(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _one(rec) -> Residual | None:
    if isinstance(rec, (int, float)):
        return Residual(float(rec))
    if not isinstance(rec, dict):
        return None
    per = {}
    for o in rec.get("observations", []) or []:
        if isinstance(o, dict) and "image" in o:
            r = _num(o.get("residual_px", o.get("residual", o.get("error_px"))))
            if r is not None:
                per[str(o["image"])] = r
    r = _num(rec.get("residual_px", rec.get("residual", rec.get("error_px", rec.get("reproj_px")))))
    if r is None and per:
        r = max(per.values())
    if r is None:
        return None
    inl = rec.get("inlier")
    return Residual(r, None if inl is None else bool(inl), per)


def read_residuals(paths) -> dict[str, Residual]:
    """tie-point id -> residual; empty when the register stage has not written any."""
    f = residual_file(paths)
    if f is None:
        return {}
    try:
        d = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        log.warning("%s: unreadable tie-point residuals (%s)", f, e)
        return {}
    body = d.get("tiepoints", d) if isinstance(d, dict) else d
    out = {}
    if isinstance(body, list):
        for rec in body:
            if isinstance(rec, dict) and "id" in rec:
                r = _one(rec)
                if r is not None:
                    out[str(rec["id"])] = r
    elif isinstance(body, dict):
        for k, rec in body.items():
            r = _one(rec)
            if r is not None:
                out[str(k)] = r
    return out
