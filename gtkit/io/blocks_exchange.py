"""ContextCapture BlocksExchange XML: photos with pose, intrinsics and distortion (read and write).

What the format says and what gtkit assumes (Bentley's published BlocksExchange spec, v2.1/3.x,
and exports seen in the wild):

* ``<SpatialReferenceSystems><SRS><Id>/<Definition>``: ``EPSG:n``, WKT, PROJ string or
  ``ENU:lat,lon``; ``<Block><SRSId>`` names the block's SRS (absent: a local Cartesian frame,
  which gtkit reads as the project's world frame itself).
* ``<Pose><Rotation><M_00>..<M_22>`` is the rotation **from the SRS to the camera** (rows are
  the camera axes written in SRS coordinates), ``<Center>`` the camera centre in the SRS. With
  ``<CameraOrientation>XRightYDown</CameraOrientation>`` (the default and what ContextCapture
  writes) the camera axes are OpenCV's, so ``M`` is gtkit's world-to-camera ``R`` directly. This
  was checked on a published ContextCapture export: the third row (optical axis) of a DJI oblique
  photo points below the horizon in the gimbal's heading, and the first row (image right) is
  horizontal and to the right of it. The other seven orientations are turned into XRightYDown
  by a fixed axis permutation (``_ORIENTATION``).
* Intrinsics are per ``<Photogroup>``: ``<ImageDimensions>``; focal length from
  ``<FocalLengthPixels>``, else ``<FocalLength>`` (mm) x max(W, H) / ``<SensorSize>`` (mm, the
  sensor's largest side); ``<AspectRatio>`` = fy / fx; ``<Skew>`` must be 0 (no COLMAP model has skew).
* ``<PrincipalPoint>`` is in pixels with the image origin at the **top-left corner of the
  top-left pixel**, the convention COLMAP and gtkit use (top-left pixel centre at (0.5, 0.5)), so
  it is copied unchanged (``PIXEL_SHIFT`` = 0 says so in one place; change it there if a delivery
  proves otherwise).
* ``<Distortion>`` K1 K2 K3 P1 P2 is the Brown model on normalised coordinates with OpenCV's
  tangential order; it maps to COLMAP ``OPENCV`` (k1 k2 p1 p2). A non-zero K3 has no gtkit camera
  model: it is an error unless ``drop_k3=True``.
* Photos without a ``<Rotation>`` + ``<Center>`` (not oriented) are skipped and counted; a rotation
  given as Omega/Phi/Kappa is refused with a clear error (only M_ij is read).

Image names come back relative to ``image_root`` when the XML's paths lie under it (otherwise
the path as written, with ``/``).
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..pose import Pose
from .atomic import write_text
from .srs import SrsToWorld

PIXEL_SHIFT = 0.0  # gtkit pixel = BlocksExchange pixel + PIXEL_SHIFT (both: top-left corner is 0)

# camera axes of each CameraOrientation, written in OpenCV camera axes (x right, y down, z forward):
# M_opencv = A @ M_given
_ORIENTATION = {
    "XRightYDown": np.diag([1.0, 1.0, 1.0]),
    "XLeftYDown": np.diag([-1.0, 1.0, -1.0]),
    "XLeftYUp": np.diag([-1.0, -1.0, 1.0]),
    "XRightYUp": np.diag([1.0, -1.0, -1.0]),
    "XDownYRight": np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]),
    "XDownYLeft": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),
    "XUpYLeft": np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]]),
    "XUpYRight": np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
}


@dataclass
class Block:
    poses: dict[str, Pose]
    cameras: dict[str, Camera]
    srs: str | None = None
    skipped: list[str] = field(default_factory=list)   # photos without a usable pose


def _f(el, tag, path, default=None, required=False):
    t = el.findtext(tag)
    if t is None or not t.strip():
        if required:
            raise GtkitError(f"<{el.tag}> lacks <{tag}>", path)
        return default
    try:
        return float(t)
    except ValueError:
        raise GtkitError(f"<{tag}> is not a number: {t.strip()!r}", path) from None


def _image_name(image_path: str, image_root: Path | None, base: Path) -> str:
    """A photo's name relative to ``image_root`` when it lies below it, else its path as written
    (only the file name for an absolute path elsewhere, e.g. ``D:/survey/DJI_0001.jpg``)."""
    raw = image_path.strip().replace("\\", "/")
    drive = len(raw) > 1 and raw[1] == ":"
    p = Path(raw)
    if image_root is not None and not drive:
        full = p if p.is_absolute() else Path(base) / p
        rel = os.path.relpath(os.path.abspath(full), os.path.abspath(image_root))
        if not rel.startswith(".."):
            return Path(rel).as_posix()
    return PurePosixPath(raw).name if (drive or p.is_absolute()) else raw


def _camera(pg, path: Path, drop_k3: bool) -> Camera:
    name = pg.findtext("Name", "photogroup")
    dims = pg.find("ImageDimensions")
    if dims is None:
        raise GtkitError(f"photogroup {name!r} lacks <ImageDimensions>", path)
    W, H = int(_f(dims, "Width", path, required=True)), int(_f(dims, "Height", path, required=True))
    model_type = (pg.findtext("CameraModelType") or "Perspective").strip()
    if model_type != "Perspective":
        raise GtkitError(f"photogroup {name!r}: camera model {model_type!r} is not supported (Perspective only)", path)
    f = _f(pg, "FocalLengthPixels", path)
    if f is None:
        f_mm, sensor = _f(pg, "FocalLength", path), _f(pg, "SensorSize", path)
        if f_mm is None or not sensor:
            raise GtkitError(f"photogroup {name!r} gives neither <FocalLengthPixels> nor <FocalLength> with "
                             "<SensorSize>", path)
        f = f_mm * max(W, H) / sensor
    aspect = _f(pg, "AspectRatio", path, 1.0)
    skew = _f(pg, "Skew", path, 0.0)
    if abs(skew) > 1e-9:
        raise GtkitError(f"photogroup {name!r}: skew {skew} is not supported", path)
    pp = pg.find("PrincipalPoint")
    cx = _f(pp, "x", path, W / 2.0) if pp is not None else W / 2.0
    cy = _f(pp, "y", path, H / 2.0) if pp is not None else H / 2.0
    cx, cy = cx + PIXEL_SHIFT, cy + PIXEL_SHIFT
    d = pg.find("Distortion")
    k1 = k2 = k3 = p1 = p2 = 0.0
    if d is not None:
        k1, k2, k3 = (_f(d, t, path, 0.0) for t in ("K1", "K2", "K3"))
        p1, p2 = (_f(d, t, path, 0.0) for t in ("P1", "P2"))
    if k3 != 0.0 and not drop_k3:
        raise GtkitError(f"photogroup {name!r}: distortion K3 = {k3} has no COLMAP/gtkit camera model "
                         "(import with drop_k3 to ignore it)", path)
    fx, fy = f, f * aspect
    if any(v != 0.0 for v in (k1, k2, p1, p2)):
        return Camera("OPENCV", W, H, (fx, fy, cx, cy, k1, k2, p1, p2))
    return Camera("PINHOLE", W, H, (fx, fy, cx, cy))


def read_blocks_exchange(path: str | Path, frame, image_root: str | Path | None = None,
                         drop_k3: bool = False) -> Block:
    """Poses (world-to-camera, project frame) and intrinsics of every oriented photo."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("file not found", path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise GtkitError(f"not valid XML ({e})", path) from None
    if root.tag != "BlocksExchange":
        raise GtkitError(f"not a BlocksExchange file (root element <{root.tag}>)", path)
    srs_defs = {}
    for s in root.iter("SRS"):
        sid, d = (s.findtext("Id") or "").strip(), (s.findtext("Definition") or "").strip()
        if sid:
            srs_defs[sid] = d
    base = Path(root.findtext("BaseImagePath") or path.parent)
    blocks = root.findall("Block")
    if not blocks:
        raise GtkitError("no <Block>", path)
    out = Block({}, {})
    for block in blocks:
        sid = (block.findtext("SRSId") or "").strip()
        if sid and sid not in srs_defs:
            raise GtkitError(f"block SRSId {sid} is not defined in <SpatialReferenceSystems>", path)
        srs = srs_defs.get(sid) if sid else None
        if srs is not None and out.srs is not None and srs != out.srs:
            raise GtkitError(f"blocks use different SRSs ({out.srs!r}, {srs!r})", path)
        out.srs = srs
        to_world = SrsToWorld(srs, frame, source=path) if srs else None
        for pg in block.iter("Photogroup"):
            cam = _camera(pg, path, drop_k3)
            orient = (pg.findtext("CameraOrientation") or "XRightYDown").strip()
            if orient not in _ORIENTATION:
                raise GtkitError(f"unknown CameraOrientation {orient!r}", path)
            A = _ORIENTATION[orient]
            for ph in pg.findall("Photo"):
                ip = ph.findtext("ImagePath")
                pid = (ph.findtext("Id") or "?").strip()
                if not ip:
                    raise GtkitError(f"photo {pid} has no <ImagePath>", path)
                name = _image_name(ip, Path(image_root) if image_root else None, base)
                pose_el = ph.find("Pose")
                rot = pose_el.find("Rotation") if pose_el is not None else None
                cen = pose_el.find("Center") if pose_el is not None else None
                if rot is None or cen is None:
                    if pose_el is not None and pose_el.find("Omega") is not None:
                        raise GtkitError(f"photo {pid} ({name}): Omega/Phi/Kappa rotations are not supported; "
                                         "export the block with rotation matrices", path)
                    out.skipped.append(name)
                    continue
                M = np.array([[_f(rot, f"M_{i}{j}", path, required=True) for j in range(3)] for i in range(3)])
                C = np.array([_f(cen, t, path, required=True) for t in ("x", "y", "z")])
                if not (np.all(np.isfinite(M)) and np.all(np.isfinite(C))):
                    raise GtkitError(f"photo {pid} ({name}): pose has NaN or infinite values", path)
                err = np.abs(M @ M.T - np.eye(3)).max()
                if err > 1e-5 or np.linalg.det(M) < 0:
                    raise GtkitError(f"photo {pid} ({name}): rotation is not orthonormal with det +1 "
                                     f"(|M M^T - I| = {err:.2g}, det = {np.linalg.det(M):.6g})", path)
                R = A @ M
                if to_world is not None:
                    Cw = to_world.points(C)
                    R = R @ to_world.rotation_at(C).T
                else:
                    Cw = C
                try:
                    out.poses[name] = Pose.from_center(R, Cw)
                except GtkitError as e:
                    raise GtkitError(f"photo {pid} ({name}): {e}", path) from None
                out.cameras[name] = cam
    if not out.poses:
        raise GtkitError(f"no oriented photos (skipped {len(out.skipped)} without a pose)", path)
    return out


def _x(v: float) -> str:
    return repr(float(v))


def write_blocks_exchange(path: str | Path, poses: dict[str, Pose], cameras: dict[str, Camera], frame,
                          image_root: str | Path | None = None, block_name: str = "gtkit") -> Path:
    """Write poses + intrinsics as a BlocksExchange XML in the project's CRS (centres = world + origin).

    Photos sharing a camera go in one photogroup. ``ImagePath`` is ``image_root/name`` when an
    image root is given, else the name itself (relative to the XML's folder)."""
    missing = sorted(set(poses) - set(cameras))
    if missing:
        raise GtkitError(f"no intrinsics for {len(missing)} posed images (e.g. {missing[0]})", path)
    groups: dict[Camera, list[str]] = {}
    for name in sorted(poses):
        groups.setdefault(cameras[name], []).append(name)
    esc = _xml_escape
    L = ['<?xml version="1.0" encoding="utf-8"?>', '<BlocksExchange version="2.1">',
         "\t<SpatialReferenceSystems>", "\t\t<SRS>", "\t\t\t<Id>0</Id>",
         f"\t\t\t<Name>{esc(frame.crs_spec)}</Name>", f"\t\t\t<Definition>{esc(frame.crs_spec)}</Definition>",
         "\t\t</SRS>", "\t</SpatialReferenceSystems>", "\t<Block>", f"\t\t<Name>{esc(block_name)}</Name>",
         "\t\t<Description>written by gtkit; Rotation = world-to-camera (XRightYDown), Center in SRS</Description>",
         "\t\t<SRSId>0</SRSId>", "\t\t<Photogroups>"]
    photo_id = 0
    origin = np.asarray(frame.origin, dtype=np.float64)
    for g, (cam, names) in enumerate(groups.items()):
        if cam.model not in ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL"):
            raise GtkitError(f"camera model {cam.model} cannot be written to BlocksExchange", path)
        k1, k2, p1, p2 = cam.distortion
        L += ["\t\t\t<Photogroup>", f"\t\t\t\t<Name>camera_{g}</Name>",
              f"\t\t\t\t<ImageDimensions><Width>{cam.width}</Width><Height>{cam.height}</Height></ImageDimensions>",
              "\t\t\t\t<CameraModelType>Perspective</CameraModelType>",
              f"\t\t\t\t<FocalLengthPixels>{_x(cam.fx)}</FocalLengthPixels>",
              "\t\t\t\t<CameraOrientation>XRightYDown</CameraOrientation>",
              f"\t\t\t\t<PrincipalPoint><x>{_x(cam.cx - PIXEL_SHIFT)}</x><y>{_x(cam.cy - PIXEL_SHIFT)}</y></PrincipalPoint>",
              f"\t\t\t\t<AspectRatio>{_x(cam.fy / cam.fx)}</AspectRatio>", "\t\t\t\t<Skew>0</Skew>",
              f"\t\t\t\t<Distortion><K1>{_x(k1)}</K1><K2>{_x(k2)}</K2><K3>0</K3><P1>{_x(p1)}</P1><P2>{_x(p2)}</P2></Distortion>"]
        for name in names:
            p = poses[name]
            C = p.center + origin
            ip = (Path(image_root) / name).as_posix() if image_root else name
            L += ["\t\t\t\t<Photo>", f"\t\t\t\t\t<Id>{photo_id}</Id>", f"\t\t\t\t\t<ImagePath>{esc(ip)}</ImagePath>",
                  "\t\t\t\t\t<Pose>", "\t\t\t\t\t\t<Rotation>"]
            L += [f"\t\t\t\t\t\t\t<M_{i}{j}>{_x(p.R[i, j])}</M_{i}{j}>" for i in range(3) for j in range(3)]
            L += ["\t\t\t\t\t\t</Rotation>",
                  f"\t\t\t\t\t\t<Center><x>{_x(C[0])}</x><y>{_x(C[1])}</y><z>{_x(C[2])}</z></Center>",
                  "\t\t\t\t\t</Pose>", "\t\t\t\t</Photo>"]
            photo_id += 1
        L.append("\t\t\t</Photogroup>")
    L += ["\t\t</Photogroups>", "\t</Block>", "</BlocksExchange>"]
    return write_text(path, "\n".join(L) + "\n")


def _xml_escape(s: str) -> str:
    return str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
