"""Photo-over-render overlays for checking a pose by eye, and the alignment measure.

The reference model is rendered at an image's pose (:mod:`gtkit.render.renderer`) and laid
over the photo in one of four modes, used alike by the annotator GUI and ``gtkit overlay``:

``blend``    photo and render mixed with weight ``alpha`` (0 = photo, 1 = render)
``swipe``    render left of a vertical divider at ``swipe`` (fraction of the width), photo right
``edges``    the photo in grey with its own edges in green and the render's edges in magenta
``checker``  a checkerboard of ``checker_px`` tiles alternating photo and render

Alignment measures (:func:`alignment`), both in full-resolution photo pixels, computed at a
working resolution whose long side is at most 768 px (``MEASURE_SIDE``), only where the model was
rendered (eroded by a few pixels so the model's outline against empty background does not count):

``misalignment_px`` (the headline figure)
    The working image is cut into half-overlapping 96-px tiles; in each tile the shift that
    moves the render's gradient-magnitude image onto the photo's is found by phase
    correlation (tiles without texture or without a confident peak are skipped; 48-px tiles
    when fewer than 5 large ones fit where the model was drawn). The
    measure is the median length of these shifts: how far, typically, the render must move
    to sit on the photo. 0 = aligned; it grows linearly with the error up to half a tile.
``edge_distance_px``
    A symmetric median chamfer distance between Canny edges (Gaussian sigma 1.5 px; thresholds
    adapted to each image so that its strongest 10 % of gradients count) of the photo and of
    the rendered RGB: for every edge pixel of one image, the distance to the
    nearest edge pixel of the other with a similar gradient orientation (within 22.5 deg);
    the mean of the two medians. 0 = edges on top of each other; robust to edges only one
    image has (texture differences) because it uses medians, but it saturates at the
    typical spacing of edges (a few pixels in busy scenes), so it separates "aligned" from
    "not aligned" rather than measuring large errors.

Everything here is numpy/OpenCV; :func:`write_overlays` (the batch stage behind
``gtkit overlay``) additionally loads the model and renders.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.photo import read_photo
from ..io.poses import INTRINSICS, POSES

log = logging.getLogger(__name__)

MODES = ("blend", "swipe", "edges", "checker")


# --- compositing ------------------------------------------------------------------------


def _check(photo: np.ndarray, render: np.ndarray):
    if photo.shape[:2] != render.shape[:2]:
        raise GtkitError(f"overlay: photo {photo.shape[:2]} and render {render.shape[:2]} differ in size")


def _valid(render: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    return np.ones(render.shape[:2], bool) if valid is None else valid.astype(bool)


def blend(photo: np.ndarray, render: np.ndarray, alpha: float = 0.5, valid: np.ndarray | None = None) -> np.ndarray:
    """``(1 - alpha) * photo + alpha * render`` where the model was drawn; the photo elsewhere."""
    _check(photo, render)
    a = float(np.clip(alpha, 0.0, 1.0))
    out = photo.astype(np.float32) * (1 - a) + render.astype(np.float32) * a
    out = np.where(_valid(render, valid)[..., None], out, photo.astype(np.float32))
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def swipe(photo: np.ndarray, render: np.ndarray, position: float = 0.5, valid: np.ndarray | None = None,
          line_color=(255, 220, 0)) -> np.ndarray:
    """The render left of a vertical divider at ``position`` (0..1 of the width), the photo right."""
    _check(photo, render)
    h, w = photo.shape[:2]
    x = int(round(np.clip(position, 0.0, 1.0) * w))
    out = photo.copy()
    left = _valid(render, valid)[:, :x]
    out[:, :x][left] = render[:, :x][left]
    if 0 < x < w:
        out[:, max(0, x - 1):x + 1] = line_color
    return out


def checkerboard(photo: np.ndarray, render: np.ndarray, tile: int = 64, valid: np.ndarray | None = None) -> np.ndarray:
    """Alternating ``tile``-pixel squares of render and photo."""
    _check(photo, render)
    h, w = photo.shape[:2]
    tile = max(1, int(tile))
    ii, jj = np.meshgrid(np.arange(h) // tile, np.arange(w) // tile, indexing="ij")
    use = ((ii + jj) % 2 == 0) & _valid(render, valid)
    out = photo.copy()
    out[use] = render[use]
    return out


def edge_map(rgb: np.ndarray, sigma: float = 1.5, mask: np.ndarray | None = None) -> np.ndarray:
    """Boolean Canny edge map (Gaussian smoothing, thresholds adapted to the image; see
    :func:`edge_distance`)."""
    return _oriented_edges(rgb, sigma, 1, mask)[0]


def edges(photo: np.ndarray, render: np.ndarray, valid: np.ndarray | None = None, sigma: float = 1.5) -> np.ndarray:
    """The photo in dimmed grey, its edges in green, the render's edges in magenta (white where both)."""
    import cv2

    _check(photo, render)
    grey = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    out = np.repeat((grey.astype(np.float32) * 0.45)[..., None], 3, axis=2).astype(np.uint8)
    inner = _inner(_valid(render, valid))
    pe = edge_map(photo, sigma, inner)
    re = edge_map(render, sigma, inner) & inner
    out[pe] = (40, 230, 40)
    out[re] = (255, 40, 255)
    out[pe & re] = (255, 255, 255)
    return out


def compose(mode: str, photo: np.ndarray, render: np.ndarray, valid: np.ndarray | None = None, *,
            alpha: float = 0.5, position: float = 0.5, tile: int = 64, sigma: float = 1.5) -> np.ndarray:
    """One of :data:`MODES` (plus ``photo`` and ``render`` for the plain images)."""
    if mode == "blend":
        return blend(photo, render, alpha, valid)
    if mode == "swipe":
        return swipe(photo, render, position, valid)
    if mode == "edges":
        return edges(photo, render, valid, sigma)
    if mode == "checker":
        return checkerboard(photo, render, tile, valid)
    if mode == "photo":
        return photo.copy()
    if mode == "render":
        return render.copy()
    raise GtkitError(f"unknown overlay mode {mode!r} (one of {', '.join(MODES)}, photo, render)")


# --- the alignment measure ----------------------------------------------------------------


def _inner(valid: np.ndarray, margin: int = 4) -> np.ndarray:
    """The rendered region shrunk by ``margin`` px (drops the outline against empty background)."""
    import cv2

    if valid.all():
        return valid
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    return cv2.erode(valid.astype(np.uint8), k) > 0


@dataclass
class Alignment:
    """How well a render lines up with its photo (see the module docstring); full-resolution pixels."""

    misalignment_px: float         # median local shift between photo and render (tiles); NaN if no tile
    edge_distance_px: float        # symmetric median oriented-edge distance; NaN if too few edges
    render_to_photo_px: float      # median distance from render edges to the nearest photo edge
    photo_to_render_px: float      # median distance from photo edges to the nearest render edge
    n_tiles: int                   # tiles that gave a confident shift
    n_render_edges: int
    n_photo_edges: int
    coverage: float                # share of the image where the model was drawn
    scale: float                   # working resolution / full resolution

    def as_dict(self) -> dict:
        """JSON-ready: floats rounded, NaN (nothing to measure) as None."""
        return {k: ((round(v, 4) if np.isfinite(v) else None) if isinstance(v, float) else v)
                for k, v in dataclasses.asdict(self).items()}


def _gray(rgb: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    return cv2.GaussianBlur(g, (0, 0), sigma) if sigma > 0 else g


def _oriented_edges(rgb: np.ndarray, sigma: float, n_bins: int, mask: np.ndarray | None = None):
    """Canny edges and each pixel's gradient-orientation bin (orientation modulo 180 deg).

    The Canny thresholds adapt to the image: the strongest ``EDGE_SHARE`` of gradients (inside
    ``mask``) are edges, so a dim, soft photo and a crisp render yield comparable edge sets."""
    import cv2

    g = _gray(rgb, sigma)
    f = g.astype(np.float32)
    gx, gy = cv2.Sobel(f, cv2.CV_32F, 1, 0), cv2.Sobel(f, cv2.CV_32F, 0, 1)
    mag = cv2.magnitude(gx, gy)
    sel = mag[mask] if mask is not None and mask.any() else mag.ravel()
    high = max(float(np.percentile(sel, 100 * (1 - EDGE_SHARE))), 8.0)
    e = cv2.Canny(g, 0.4 * high, high, L2gradient=True) > 0
    ang = np.mod(np.arctan2(gy, gx), np.pi)
    return e, np.minimum((ang / np.pi * n_bins).astype(np.int32), n_bins - 1)


EDGE_SHARE = 0.1  # share of pixels whose gradient counts as strong (adaptive Canny high threshold)


def edge_distance(photo: np.ndarray, render: np.ndarray, mask: np.ndarray, sigma: float = 1.5,
                  n_bins: int = 8, min_edges: int = 50) -> tuple[float, float, int, int]:
    """Symmetric median chamfer distance between oriented Canny edges, in working pixels.

    An edge pixel's distance is to the nearest edge pixel of the other image whose gradient
    orientation is within one bin (180/``n_bins`` deg) of its own. Returns (render->photo,
    photo->render, n render edges, n photo edges); NaN distances when there are too few edges."""
    import cv2

    ep, bp = _oriented_edges(photo, sigma, n_bins, mask)
    er, br = _oriented_edges(render, sigma, n_bins, mask)
    ep &= mask
    er &= mask
    n_p, n_r = int(ep.sum()), int(er.sum())
    if n_p < min_edges or n_r < min_edges:
        return float("nan"), float("nan"), n_r, n_p

    def one_way(src, src_bins, dst, dst_bins):
        dts = np.stack([cv2.distanceTransform((~(dst & (dst_bins == k))).astype(np.uint8), cv2.DIST_L2, 5)
                        for k in range(n_bins)])
        ii, jj = np.nonzero(src)
        b = src_bins[ii, jj]
        d = np.min(np.stack([dts[(b + o) % n_bins, ii, jj] for o in (-1, 0, 1)]), axis=0)
        return float(np.median(d))

    return one_way(er, br, ep, bp), one_way(ep, bp, er, br), n_r, n_p


def local_shifts(photo: np.ndarray, render: np.ndarray, mask: np.ndarray, tile: int = 96,
                 sigma: float = 2.0, min_response: float = 0.1) -> np.ndarray:
    """(N, 2) shifts (working px) that move the render onto the photo, one per half-overlapping
    ``tile``-pixel square fully inside ``mask``: phase correlation of gradient magnitudes."""
    import cv2

    def grad(img):
        f = _gray(img, sigma).astype(np.float32)
        return cv2.magnitude(cv2.Sobel(f, cv2.CV_32F, 1, 0), cv2.Sobel(f, cv2.CV_32F, 0, 1))

    a, b = grad(photo), grad(render)
    h, w = a.shape
    if min(h, w) < tile:
        return np.zeros((0, 2))
    win = cv2.createHanningWindow((tile, tile), cv2.CV_32F)
    out = []
    for y in range(0, h - tile + 1, tile // 2):
        for x in range(0, w - tile + 1, tile // 2):
            if mask[y:y + tile, x:x + tile].mean() < 0.9:
                continue
            pa, pb = a[y:y + tile, x:x + tile], b[y:y + tile, x:x + tile]
            if pa.std() < 1.0 or pb.std() < 1.0:
                continue  # no texture: no shift to measure
            (dx, dy), r = cv2.phaseCorrelate(pb, pa, win)
            if r >= min_response:
                out.append((dx, dy))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


MEASURE_SIDE = 768  # the measures are computed at most this size (long side): same figure at any display size


def alignment(photo: np.ndarray, render: np.ndarray, valid: np.ndarray | None = None, *, scale: float = 1.0,
              sigma: float = 1.5, tile: int = 96, max_side: int = MEASURE_SIDE) -> Alignment:
    """Both alignment measures for a photo and a render of the same size (module docstring).

    ``scale`` is the size of these arrays relative to the full-resolution photo, so the
    results are in full-resolution pixels. Larger arrays are first reduced to ``max_side``."""
    import cv2

    _check(photo, render)
    v = _valid(render, valid)
    h, w = photo.shape[:2]
    if max(h, w) > max_side:
        k = max_side / max(h, w)
        size = (max(1, round(w * k)), max(1, round(h * k)))
        photo = cv2.resize(photo, size, interpolation=cv2.INTER_AREA)
        render = cv2.resize(render, size, interpolation=cv2.INTER_AREA)
        v = cv2.resize(v.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        scale *= size[0] / w
    inner = _inner(v)
    r2p, p2r, n_r, n_p = edge_distance(photo, render, inner, sigma)
    sh = local_shifts(photo, render, _inner(v, 8), tile)
    if len(sh) < 5:  # the model covers little of the photo: smaller tiles fit inside it
        sh = local_shifts(photo, render, _inner(v, 8), tile // 2)
    mis = float(np.median(np.hypot(sh[:, 0], sh[:, 1]))) / scale if len(sh) else float("nan")
    return Alignment(mis, 0.5 * (r2p + p2r) / scale, r2p / scale, p2r / scale, len(sh), n_r, n_p,
                     float(v.mean()), scale)


# --- images at a working resolution --------------------------------------------------------


def working_scale(width: int, height: int, max_side: int) -> float:
    return min(1.0, float(max_side) / max(width, height))


# --- batch: the `gtkit overlay` stage -------------------------------------------------------


@dataclass
class OverlaySettings:
    # Working resolution: photo and render at max_side (long side), measured at MEASURE_SIDE, figures in
    # full-resolution pixels. Kept for full-size photos (issue 48): at the true poses of the full-size
    # sample (seed 0, 8 reference + 4 wide photos, loaded) 1024 / 768 measures 1.12 px = 0.39 mrad at
    # 0.32 CPU s a photo, 2048 / 1536 0.74 px = 0.22 mrad at 1.41 CPU s (4.4 x); small's photos at
    # 1024 / 768: 0.48 mrad. At the true poses the figure is the floor a pose error must pass to show:
    # 768 keeps it below the small sample's, so full-size photos are reviewed no worse than small ones;
    # a finer floor (MEASURE_SIDE 1536 with max_side 2048) costs 4.4 x.
    max_side: int = 1024          # long side of the overlay PNGs (the measures use at most MEASURE_SIDE)
    modes: tuple[str, ...] = MODES  # which overlay PNGs to write per image
    alpha: float = 0.5            # blend weight of the render
    position: float = 0.5         # swipe divider, fraction of the width
    tile: int = 64                # checkerboard square, pixels at the working resolution
    sigma: float = 1.5            # Gaussian smoothing before Canny, working pixels


def pose_file_candidates(paths) -> list[Path]:
    """Where the register stage may have written pseudo-GT poses, most likely first."""
    reg = paths.stage("register")
    return [paths.pseudo_gt_poses, reg / "pseudo_gt_poses.txt", paths.exports / POSES]


def default_pose_file(paths) -> Path | None:
    """The pseudo-GT pose file of the register stage, if it exists (never the truth)."""
    return next((p for p in pose_file_candidates(paths) if p.is_file()), None)


def reference_block_pose_file(paths) -> Path | None:
    """The reference block's SfM poses (``work/sfm_reference/poses.txt``), if they exist."""
    p = paths.reference_poses
    return p if p.is_file() else None


def intrinsics_for(paths, pose_file: Path | None) -> dict:
    """Intrinsics that go with a pose file: ``intrinsics.txt`` beside it, else ``cameras.txt``."""
    from ..io.poses import read_intrinsics

    cams = {}
    if paths.cameras.is_file():
        cams.update(read_intrinsics(paths.cameras))
    if pose_file is not None:
        side = Path(pose_file).parent / INTRINSICS
        if side.is_file():
            cams.update(read_intrinsics(side))
    return cams


class OverlayScene:
    """The reference model uploaded once, the poses and intrinsics: renders overlays on demand.
    Used by both the GUI (one renderer, reused) and :func:`write_overlays`."""

    def __init__(self, project, pose_file: str | Path | None = None, model_path: str | Path | None = None,
                 tile_budget_mb: float = 1024.0):
        from ..io.poses import read_poses
        from .tiles import open_renderer

        P = self.paths = project.paths
        self.project = project
        self.pose_file = Path(pose_file) if pose_file else default_pose_file(P)
        if self.pose_file is None:
            raise GtkitError("no poses to overlay: run `gtkit register` first or pass --poses FILE",
                             P.stage("register"))
        self.poses, self.cameras = {}, {}
        if pose_file is None and reference_block_pose_file(P) is not None:
            # the register stage poses the queries; the reference photos come from their own block
            ref = reference_block_pose_file(P)
            self.poses.update(read_poses(ref))
            self.cameras.update(intrinsics_for(P, ref))
        self.poses.update(read_poses(self.pose_file))
        self.cameras.update(intrinsics_for(P, self.pose_file))
        from ..model_files import reference_model

        model_path = Path(model_path) if model_path else reference_model(project.paths)
        self.model_path = model_path
        # a tiled model is streamed (only the tiles in each photo's frustum, under the budget), so a site
        # whose textures alone pass the memory budget can still be overlaid
        self.renderer = open_renderer(model_path, project.frame, tile_budget_mb)

    def images(self) -> list[str]:
        return sorted(n for n in self.poses if n in self.cameras)

    def render(self, name: str, max_side: int = 1024, pose=None):
        """(photo, render rgb, valid mask, scale) at the working resolution."""
        if name not in self.cameras:
            raise GtkitError(f"no intrinsics for {name}", self.project.paths.cameras)
        cam = self.cameras[name]
        pose = pose if pose is not None else self.poses.get(name)
        if pose is None:
            raise GtkitError(f"no pose for {name}", self.pose_file)
        s = working_scale(cam.width, cam.height, max_side)
        c = cam.scaled(s) if s < 1.0 else cam
        photo = read_photo(self.project.paths.images / name, (c.width, c.height))
        res = self.renderer.render(c, pose)
        return photo, res.rgb, res.valid, c.width / cam.width


def overlay_file_name(image: str, mode: str) -> str:
    return image.replace("/", "__").rsplit(".", 1)[0] + f"_{mode}.png"


PARTIAL = "alignment.partial.jsonl"   # one line an overlaid image, appended as the stage goes


def _image_key(scene: OverlayScene, name: str, model_fp: str, settings: OverlaySettings) -> str:
    """What an image's overlays depend on: model, settings, its camera and pose, the photo file."""
    import hashlib
    import json

    pose, photo = scene.poses[name], scene.paths.images / name
    st = photo.stat() if photo.is_file() else None
    blob = json.dumps([model_fp, dataclasses.asdict(settings), scene.cameras[name].to_line(),
                       np.round(pose.R, 12).tolist(), np.round(pose.t, 9).tolist(),
                       [st.st_size, st.st_mtime_ns] if st else None])
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _done_images(out: Path) -> dict[str, tuple[str, dict]]:
    """name -> (key, alignment) of the images a previous run overlaid: its finished summary, then the
    lines it appended before stopping (a torn last line is ignored)."""
    import json

    done = {}
    try:
        prev = json.loads((out / "alignment.json").read_text())
        keys = prev.get("keys") or {}
        done.update({n: (keys[n], a) for n, a in (prev.get("images") or {}).items() if n in keys})
    except (OSError, ValueError, AttributeError):
        pass
    try:
        for line in (out / PARTIAL).read_text().splitlines():
            try:
                rec = json.loads(line)
                done[rec["name"]] = (rec["key"], rec["alignment"])
            except (ValueError, KeyError, TypeError):
                continue
    except OSError:
        pass
    return done


@contextlib.contextmanager
def _released(renderer):
    try:
        yield renderer
    finally:
        renderer.release()


def write_overlays(project_dir: str | Path, pose_file: str | Path | None, out_dir: str | Path | None,
                   settings: OverlaySettings, images: list[str] | None = None,
                   progress=None, model_path: str | Path | None = None) -> dict:
    """Write overlay PNGs for every posed image and ``alignment.json`` with the edge distance
    of each; returns that summary. Default output: ``reports/overlays/``.

    Resumes image by image: an image whose PNGs exist and whose model, settings, camera, pose and
    photo file are those of the run that wrote them is not rendered again (its measure is reused)."""
    import json

    import cv2

    from ..io.atomic import atomic_path, write_json
    from ..model_files import model_fingerprint
    from ..project import Project, StageClock

    clock = StageClock()  # what the overlays cost (wall, CPU, peak memory, disk): the scale table reads it
    st = settings
    for m in st.modes:
        if m not in MODES:
            raise GtkitError(f"unknown overlay mode {m!r} (one of {', '.join(MODES)})")
    proj = Project.load(project_dir)
    scene = OverlayScene(proj, pose_file, model_path)
    out = Path(out_dir) if out_dir else proj.paths.reports / "overlays"
    names = images or scene.images()
    missing = [n for n in names if n not in scene.poses or n not in scene.cameras]
    if missing:
        raise GtkitError(f"{len(missing)} images have no pose or intrinsics, e.g. {missing[0]}", scene.pose_file)
    mp = scene.model_path.resolve()
    model_fp = f"{model_fingerprint(proj.paths.root, str(mp))}-{mp.stat().st_mtime_ns}"  # a rewritten model counts
    done = _done_images(out)
    per, keys, n_reused = {}, {}, 0
    out.mkdir(parents=True, exist_ok=True)
    # the model's buffers and textures are freed when done: on a software GL they are this
    # process's memory (3.6 GB at the large preset), which the main job would carry into render-db
    with open(out / PARTIAL, "a") as partial, _released(scene.renderer):
        for k, name in enumerate(names):
            key = keys[name] = _image_key(scene, name, model_fp, st)
            prev = done.get(name)
            if prev and prev[0] == key and all((out / overlay_file_name(name, m)).is_file() for m in st.modes):
                per[name] = prev[1]
                n_reused += 1
                if progress:
                    progress(k + 1, len(names), name, Alignment(**{f: (np.nan if v is None else v)
                                                                    for f, v in prev[1].items()}))
                continue
            photo, rgb, valid, s = scene.render(name, st.max_side)
            for mode in st.modes:
                img = compose(mode, photo, rgb, valid, alpha=st.alpha, position=st.position, tile=st.tile,
                              sigma=st.sigma)
                with atomic_path(out / overlay_file_name(name, mode)) as tmp:
                    cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            a = alignment(photo, rgb, valid, scale=s, sigma=st.sigma)
            per[name] = a.as_dict()
            partial.write(json.dumps({"name": name, "key": key, "alignment": per[name]}) + "\n")
            partial.flush()
            if progress:
                progress(k + 1, len(names), name, a)
    if n_reused:
        log.info("overlays: %d of %d images up to date, %d rendered", n_reused, len(names), len(names) - n_reused)

    def med(key):
        v = np.array([np.nan if d[key] is None else d[key] for d in per.values()], dtype=float)
        return float(np.nanmedian(v)) if np.isfinite(v).any() else None

    summary = {"pose_file": str(scene.pose_file), "model": str(scene.model_path),
               "settings": dataclasses.asdict(st),
               "measures": "misalignment_px: median local shift (phase correlation, 96-px tiles); "
                           "edge_distance_px: symmetric median oriented Canny-edge distance; "
                           "both in full-resolution pixels (see gtkit.render.overlay)",
               "working_resolution": {"png_max_side": st.max_side, "measure_side": MEASURE_SIDE,
                                      "note": "photos are decoded and rendered at png_max_side (long side), "
                                              "measured at measure_side; figures in full-resolution pixels"},
               "median_misalignment_px": med("misalignment_px"),
               "median_edge_distance_px": med("edge_distance_px"),
               "n_rendered": len(names) - n_reused,
               "cost": clock.cost([out]),
               "images": per,
               "keys": keys}
    from ..project import relative_paths

    write_json(out / "alignment.json", relative_paths(summary, proj.paths.root))  # paths relative to the project
    (out / PARTIAL).unlink(missing_ok=True)
    return summary
