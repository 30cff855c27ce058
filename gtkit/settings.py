"""Settings resolve in one place: command-line flag > ``project.toml`` section > default.

A stage's settings are a dataclass with documented defaults (nested dataclasses for sub-steps).
``project.toml`` holds the overrides a site needs, one section per stage, nested tables for the
sub-steps, e.g.::

    [sfm]
    refine_intrinsics = "auto"
    [sfm.features]
    max_num_features = 6000
    [sfm.georegister]
    gps_inlier_m = 5.0
    gcp_accuracy_m = 0.03
    checkpoints = ["gcp07", "gcp11"]

:func:`resolve` applies them, then the flags given on the command line (dotted names, None =
not given), checks every key and type, and returns a new settings object. The stage records the
resolved settings in its ``stage.json`` (a changed setting recomputes the stage).
"""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

from .errors import GtkitError


def _coerce(value, current, where: str, source):
    """``value`` checked against the type of the default ``current``."""
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise GtkitError(f"{where} must be true or false, not {value!r}", source)
        return value
    if isinstance(current, int) and not isinstance(current, bool):
        if isinstance(value, bool) or not isinstance(value, int):
            raise GtkitError(f"{where} must be an integer, not {value!r}", source)
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise GtkitError(f"{where} must be a number, not {value!r}", source)
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise GtkitError(f"{where} must be a string, not {value!r}", source)
        return value
    if isinstance(current, (list, tuple)):
        if not isinstance(value, (list, tuple)):
            raise GtkitError(f"{where} must be a list, not {value!r}", source)
        return type(current)(value)
    return value  # None defaults (optional numbers etc.) take the given value


def apply_overrides(settings, overrides: dict, where: str, source=None):
    """A copy of ``settings`` with ``overrides`` (nested dicts for nested dataclasses) applied."""
    out = copy.deepcopy(settings)
    names = {f.name for f in dataclasses.fields(out)}
    changes = {}
    for key, value in (overrides or {}).items():
        if key not in names:
            raise GtkitError(f"unknown setting {where}.{key} (known: {', '.join(sorted(names))})", source)
        cur = getattr(out, key)
        if dataclasses.is_dataclass(cur):
            if not isinstance(value, dict):
                raise GtkitError(f"{where}.{key} must be a table ([{where}.{key}])", source)
            changes[key] = apply_overrides(cur, value, f"{where}.{key}", source)
        else:
            changes[key] = _coerce(value, cur, f"{where}.{key}", source)
    return dataclasses.replace(out, **changes) if changes else out   # frozen settings too


def _nest(flat: dict) -> dict:
    out: dict = {}
    for k, v in flat.items():
        if v is None:
            continue
        d = out
        *parents, leaf = k.split(".")
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = v
    return out


def resolve(defaults, section: str, project=None, cli: dict | None = None):
    """Settings for one stage: ``defaults`` < ``project.toml [section]`` < ``cli`` ({'a.b': value},
    None values ignored). ``project``: a :class:`gtkit.project.Project` or None."""
    s = defaults
    if project is not None:
        table = project.config.get(section, {})
        s = apply_overrides(s, table, section, Path(project.paths.project_toml))
    return apply_overrides(s, _nest(cli or {}), section, "command line")
