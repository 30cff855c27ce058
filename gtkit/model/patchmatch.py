"""Depth maps from COLMAP's PatchMatch stereo on an NVIDIA GPU: the optional fast path of the depth step.

pycolmap's CUDA build (``pycolmap-cuda12``, the same API as ``pycolmap``; ``scripts/setup.sh`` installs
it in place of the CPU build when ``nvidia-smi`` finds a GPU) runs ``patch_match_stereo``; the CPU build
cannot. ``depth_method`` (:class:`ModelSettings`) says which path makes the depth maps: ``"auto"``
(PatchMatch where ``pycolmap.has_cuda``, else SGBM), ``"sgbm"`` or ``"patchmatch"``.

The workspace COLMAP reads is written from gtkit's own views, so its depth maps fall on the same
pixels as the CPU path's and everything after the depth step (fusion, surface, texture) is shared:

- ``images/<photo>.png``: the photo undistorted to the view's pinhole camera at the working size
  (grey, lossless; :func:`gtkit.model.views.load_image`);
- ``sparse/{cameras,images,points3D}.txt``: one PINHOLE camera per view with the view's ``K``
  (COLMAP's dense code takes pixel (col, row) at coordinate (col, row), the convention of ``View.K``),
  the view's pose, and the reference block's sparse points with their tracks (COLMAP sets each
  photo's depth range from them);
- ``stereo/patch-match.cfg``: each photo and its stereo neighbours (:func:`choose_neighbours`, the
  same as the CPU path's).

COLMAP computes the photometric maps of every photo, then the geometric ones (each checked against
its neighbours' maps), and skips a photo whose output files exist, so a killed run resumes. Its
``stereo/depth_maps/<photo>.png.geometric.bin`` (camera z, metres; 0 where unknown) become gtkit's
``work/model/depth/<key>/<photo>.npz``.
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_bytes, write_text
from ..io.colmap_dense import read_colmap_array
from .settings import ModelSettings
from .views import View, load_image

log = logging.getLogger(__name__)
METHODS = ("auto", "sgbm", "patchmatch")


def cuda_available() -> bool:
    """True when the installed pycolmap is a CUDA build and sees a GPU."""
    try:
        import pycolmap
    except ImportError:
        return False
    return bool(getattr(pycolmap, "has_cuda", False))


def resolve_method(setting: str) -> str:
    """``"sgbm"`` or ``"patchmatch"`` for the ``depth_method`` setting (``"auto"``: PatchMatch when CUDA
    is there)."""
    if setting not in METHODS:
        raise GtkitError(f"depth method {setting!r} is not one of {', '.join(METHODS)}")
    if setting == "auto":
        return "patchmatch" if cuda_available() else "sgbm"
    if setting == "patchmatch" and not cuda_available():
        raise GtkitError("depth method 'patchmatch' needs pycolmap's CUDA build and an NVIDIA GPU "
                         "(pip install pycolmap-cuda12 in place of pycolmap); this pycolmap has no CUDA")
    return setting


def workspace_name(name: str) -> str:
    """A photo's image name inside the workspace (a lossless PNG beside the photo's own name)."""
    return name + ".png"


def _points_and_tracks(block: Path, views: dict[str, View]):
    """The reference block's sparse points seen by the views: {point id: xyz}, {view name: [point ids]}."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(block / "model"))
    xyz = {pid: np.asarray(p.xyz, float) for pid, p in rec.points3D.items()}
    seen = {}
    for im in rec.images.values():
        if im.name in views:
            seen[im.name] = sorted({p.point3D_id for p in im.points2D if p.has_point3D()})
    return xyz, seen


def _f(x) -> str:
    """A number as text that reads back to the same float64."""
    return repr(float(x))


def write_workspace(project, views: dict[str, View], neighbours: dict[str, list[str]], block: Path, ws: Path) -> None:
    """The COLMAP dense workspace of the views (see the module docstring); images already there are kept."""
    import cv2

    names = list(views)
    ids = {n: i + 1 for i, n in enumerate(names)}
    for n in names:                      # COLMAP writes <photo>.<type>.bin beside the photo's sub-folders
        for sub in ("images", "stereo/depth_maps", "stereo/normal_maps", "stereo/consistency_graphs"):
            (ws / sub / workspace_name(n)).parent.mkdir(parents=True, exist_ok=True)
        out = ws / "images" / workspace_name(n)
        if not out.is_file():
            ok, buf = cv2.imencode(".png", load_image(project, views[n], gray=True))
            if not ok:
                raise GtkitError("could not encode the working image", out)
            write_bytes(out, buf.tobytes())
    xyz, seen = _points_and_tracks(block, views)
    cams, imgs, tracks = [], [], {}
    for n in names:
        v, i = views[n], ids[n]
        K = v.K
        cams.append(f"{i} PINHOLE {v.width} {v.height} {_f(K[0, 0])} {_f(K[1, 1])} {_f(K[0, 2])} {_f(K[1, 2])}")
        q = v.pose.q
        t = v.pose.t
        imgs.append(f"{i} {_f(q[0])} {_f(q[1])} {_f(q[2])} {_f(q[3])} {_f(t[0])} {_f(t[1])} {_f(t[2])} {i} {workspace_name(n)}")
        obs = []
        for pid in seen.get(n, []):
            pc = v.pose.transform(xyz[pid][None])[0]
            if pc[2] <= 0:
                continue
            u, w = K[0, 0] * pc[0] / pc[2] + K[0, 2], K[1, 1] * pc[1] / pc[2] + K[1, 2]
            tracks.setdefault(pid, []).append((i, len(obs)))
            obs.append(f"{_f(u)} {_f(w)} {pid}")
        imgs.append(" ".join(obs))
    pts = [f"{pid} {_f(xyz[pid][0])} {_f(xyz[pid][1])} {_f(xyz[pid][2])} 128 128 128 0.5 "
           + " ".join(f"{i} {k}" for i, k in tr) for pid, tr in tracks.items()]
    sparse = ws / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    write_text(sparse / "cameras.txt", "# gtkit views: pinhole at the working size\n" + "\n".join(cams) + "\n")
    write_text(sparse / "images.txt", "# gtkit views\n" + "\n".join(imgs) + "\n")
    write_text(sparse / "points3D.txt", "# the reference block's sparse points\n" + "\n".join(pts) + "\n")
    cfg = []
    for n, nb in neighbours.items():
        cfg += [workspace_name(n), ", ".join(workspace_name(m) for m in nb)]
    write_text(ws / "stereo" / "patch-match.cfg", "\n".join(cfg) + "\n")


def patchmatch_options(settings: ModelSettings):
    """COLMAP's PatchMatch options for gtkit's working images (already at the working size)."""
    import pycolmap

    o = pycolmap.PatchMatchOptions()
    o.max_image_size = -1                # the workspace images are the working size already
    o.geom_consistency = True
    o.filter = True
    o.gpu_index = "-1"                   # every GPU there is
    return o


def collect(ws: Path, views: dict[str, View], todo: dict[str, list[str]], folder: Path) -> dict[str, str]:
    """COLMAP's geometric depth maps of the workspace ``ws`` as gtkit's depth maps in ``folder`` (camera
    z, metres, NaN where unknown); returns {photo: reason} of the photos in ``todo`` that have none."""
    from . import depth as D

    failed = {}
    for n, nb in todo.items():
        f = ws / "stereo" / "depth_maps" / (workspace_name(n) + ".geometric.bin")
        if not f.is_file():
            failed[n] = "PatchMatch wrote no depth map"
            continue
        d = read_colmap_array(f)
        v = views[n]
        if d.shape != (v.height, v.width):
            raise GtkitError(f"PatchMatch depth map is {d.shape[1]}x{d.shape[0]}, the view {v.width}x{v.height}", f)
        d = np.where(d > 0, d, np.nan).astype(np.float32)
        D.write_depth(D.depth_file(folder, n), d, {"neighbours": nb, "method": "patchmatch"})
    return failed


def depth_maps(project, views: dict[str, View], neighbours: dict[str, list[str]], settings: ModelSettings,
               folder: Path, block: Path, show: bool = True) -> dict[str, str]:
    """The missing depth maps of ``folder`` by PatchMatch on the GPU; returns {photo: reason} of photos
    without one."""
    import pycolmap

    from . import depth as D

    todo = {n: nb for n, nb in neighbours.items() if not D.depth_file(folder, n).is_file()}
    if not todo:
        return {}
    ws = folder.parent / (folder.name + ".patchmatch")
    log.info("depth maps: PatchMatch on the GPU for %d photos (workspace %s)", len(todo), ws)
    write_workspace(project, views, neighbours, block, ws)
    pycolmap.patch_match_stereo(str(ws), options=patchmatch_options(settings))
    failed = collect(ws, views, todo, folder)
    # the workspace holds every photo's photometric and geometric depth and normal maps (~40 MB a photo
    # at 1024 px): gone once gtkit has its depth maps (a killed run keeps it and COLMAP resumes in it)
    shutil.rmtree(ws, ignore_errors=True)
    return failed
