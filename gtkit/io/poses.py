"""Pose and intrinsics text files, in the formats hloc and the UAVD4L tools use.

Pose file: one image a line, ``name qw qx qy qz tx ty tz`` (world-to-camera, see
:mod:`gtkit.conventions`). Optional 6x6 covariances go in a sibling file with one line
``name c00 c01 ... c55`` (row-major), since the pose format has no room for them.
Intrinsics file: ``name MODEL W H params...`` (COLMAP camera models).
Lines starting with ``#`` and blank lines are ignored. Image names may not contain spaces.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import GtkitError, Problems
from ..pose import Pose
from .atomic import write_text

# The file names of a pose set: every stage that places photos writes these into its folder
# (work/<stage>/), the sample writes them into truth/; gtkit.project.Paths names the folders.
POSES = "poses.txt"
INTRINSICS = "intrinsics.txt"
COVARIANCES = "covariances.txt"


def _lines(path: Path):
    path = Path(path)
    if not path.is_file():
        raise GtkitError("file not found", path)
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield n, s.split()


def read_poses(path: str | Path) -> dict[str, Pose]:
    poses: dict[str, Pose] = {}
    for n, f in _lines(Path(path)):
        if len(f) != 8:
            raise GtkitError(f"line {n}: expected 'name qw qx qy qz tx ty tz', got {len(f)} fields", path)
        try:
            vals = np.array([float(v) for v in f[1:]])
            poses[f[0]] = Pose.from_qt(vals[:4], vals[4:])
        except (ValueError, GtkitError) as e:
            raise GtkitError(f"line {n} ({f[0]}): {e}", path) from None
    return poses


def write_poses(path: str | Path, poses: dict[str, Pose], header: str | None = None) -> Path:
    out = [f"# {h}" for h in (header or "").splitlines()]
    out.append("# name qw qx qy qz tx ty tz (world-to-camera, OpenCV axes)")
    for name in sorted(poses):
        p = poses[name]
        out.append(name + " " + " ".join(repr(float(v)) for v in (*p.q, *p.t)))
    return write_text(path, "\n".join(out) + "\n")


def read_covariances(path: str | Path) -> dict[str, np.ndarray]:
    cov = {}
    for n, f in _lines(Path(path)):
        if len(f) != 37:
            raise GtkitError(f"line {n}: expected a name and 36 covariance values", path)
        cov[f[0]] = np.array([float(v) for v in f[1:]]).reshape(6, 6)
    return cov


def write_covariances(path: str | Path, cov: dict[str, np.ndarray]) -> Path:
    out = ["# name, 6x6 row-major covariance of (rotation vector [rad], translation [m]), world-to-camera"]
    for name in sorted(cov):
        out.append(name + " " + " ".join(repr(float(v)) for v in np.asarray(cov[name]).reshape(-1)))
    return write_text(path, "\n".join(out) + "\n")


def read_intrinsics(path: str | Path) -> dict[str, Camera]:
    """Every bad line is named in one error (:class:`gtkit.errors.Problems`)."""
    cams: dict[str, Camera] = {}
    problems = Problems(path)
    for n, f in _lines(Path(path)):
        if len(f) < 5:
            problems.add(f"line {n}", f"expected 'name MODEL W H params...', got {len(f)} field{'s' if len(f) != 1 else ''}")
            continue
        try:
            w, h = int(f[2]), int(f[3])
        except ValueError:
            problems.add(f"line {n} ({f[0]})", f"width and height must be whole numbers, got {f[2]!r} {f[3]!r}")
            continue
        try:
            params = tuple(float(v) for v in f[4:])
        except ValueError:
            bad = next(v for v in f[4:] if not _is_number(v))
            problems.add(f"line {n} ({f[0]})", f"parameter {bad!r} is not a number")
            continue
        try:
            cams[f[0]] = Camera(f[1], w, h, params)
        except GtkitError as e:
            problems.add(f"line {n} ({f[0]})", e)
    problems.raise_if_any()
    return cams


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def write_intrinsics(path: str | Path, cams: dict[str, Camera]) -> Path:
    out = ["# name MODEL W H params... (COLMAP models; top-left pixel centre at (0.5, 0.5))"]
    out += [f"{name} {cams[name].to_line()}" for name in sorted(cams)]
    return write_text(path, "\n".join(out) + "\n")
