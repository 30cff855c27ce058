"""``gtkit model build DIR``: the reference model from the reference photos (the stage).

    run(project, ModelSettings())   # work/sfm_reference -> work/model/... -> model/reference.obj

Steps and their outputs (``work/model/``): ``depth/<key>/<photo>.npz`` (one a photo, kept when a
run is killed), ``fused/<key>/<cell>.npy`` (the fused cloud, one file per 100 m cell, ``index.json``
last) + ``points.laz`` (in the project CRS), ``surface/<key>/tile_<k>.npz`` (each surface tile,
trimmed and simplified, saved when done), then the textured OBJ + offset sidecar. A killed build
resumes: finished depth maps, a finished fusion and finished surface tiles with the same settings
are read back (``force`` keeps only the depth maps). Memory is bounded by a photo (depth, fusion), a
cell (fusion's averaging) and a surface tile, not by the site. Where the project has no model the
OBJ is ``model/reference.obj``; where a delivered model is there already, it is
``model/built/reference.obj`` and the delivered one stays the project's model unless ``use=True``
(the delivered files then move to ``model/delivered/``). ``project.toml [model]`` records which.
"""
from __future__ import annotations

import logging
import resource
import shutil
import time
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.poses import INTRINSICS, POSES
from ..io.mesh import Mesh, write_obj, write_offset_sidecar
from ..project import (Project, file_fingerprint, mark_stage_done, reset_peak_rss, settings_dict, settings_key,
                       read_stage_record, stage_done, start_stage_clock)
from . import depth as D
from . import fusion, patchmatch, surface, texture
from .settings import ModelSettings
from .views import block_dir, choose_neighbours, fusion_neighbours, load_image, load_views, region

log = logging.getLogger(__name__)


class NoStereo(GtkitError):
    """The reference block's photos cannot make a model (too few, none with stereo neighbours, or depth
    maps that agree nowhere, as on an 8-photo facade set whose neighbours are 30+ deg apart): the
    project goes on without one where it can (``gtkit run``: the pseudo-GT's automatic ties stay on
    the reference SfM's own points; the stages that draw a model say they cannot run)."""
STAGE = "model"
MODEL_FILE = "reference.obj"
TILES_DIR = "tiles"          # the tiled copy of a large site's model, beside the OBJ
DEPTH_VERSION = 2   # bump when the depth maps' method changes (finished maps of another version are not reused)


def _peak_gb() -> float:
    """Peak resident memory of this process (GB) since the start or the last :func:`_reset_peak`."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def _reset_peak() -> None:
    """Start a new peak-memory window (Linux: writing 5 to clear_refs resets VmHWM; elsewhere the
    peaks are cumulative). The stage's own clock (its record's ``cost``) keeps the peak so far."""
    reset_peak_rss()


def _cpu_s() -> float:
    """CPU seconds of this process and its reaped children (an executor's local workers)."""
    r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime


def _children_peak_gb() -> float:
    """The largest peak resident memory of a reaped child process (GB; 0 without any)."""
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1e9


def _mark(step: str, t: dict, mem: dict, cpu: dict) -> None:
    """End of a step: its time, CPU seconds and peak memory (the step's own where the OS can reset
    the peak, else the process's so far)."""
    t[step], mem[step], cpu[step] = time.time(), _peak_gb(), _cpu_s()
    _reset_peak()


def _step_done(step: str, t: dict, mem: dict, what: str) -> None:
    prev = max(v for k, v in t.items() if k != step and v <= t[step])
    log.info("model build: %s done in %.0f s (%s); peak memory in the step %.2f GB", step, t[step] - prev, what, mem[step])


def _bar(total: int, desc: str, show: bool):
    from ..progress import progress_bar

    return progress_bar(total, desc, unit="photo", show=show)


def depth_maps(project: Project, views, neighbours, settings: ModelSettings, folder: Path, show: bool = True,
               executor=None) -> dict:
    """Compute the missing depth maps (one file a photo); returns {name: reason} of failed photos.
    ``executor``: None computes them here, one after the other; an
    :class:`~gtkit.localize.executors.ExecutorSettings` runs runs of :data:`DEPTH_CHUNK` photos as tasks
    there (local processes or a Dask cluster, :func:`_depth_chunk`): the same maps, written by the
    workers, each as soon as it is done (a killed run keeps them)."""
    for f in folder.glob(".*.tmp*"):      # a map being written when a run was killed
        f.unlink(missing_ok=True)
    todo = [(n, nb) for n, nb in neighbours.items() if not D.depth_file(folder, n).is_file()]
    if executor is not None and todo:
        return _depth_maps_on(executor, project, views, neighbours, todo, settings, folder, show)
    img = _grey_pictures(project, views)
    failed = {}
    t0 = time.time()
    with _bar(len(neighbours), "depth maps", show) as bar:
        bar.update(len(neighbours) - len(todo))
        for done, (n, nb) in enumerate(todo):
            if done and done % 25 == 0:
                log.info("depth maps: %d of %d there, %d computed in this run (%.1f s a photo)",
                         len(neighbours) - len(todo) + done, len(neighbours), done, (time.time() - t0) / done)
            why = _depth_map(n, nb, views, img, settings, folder)
            if why:
                failed[n] = why
            bar.update(1)
    return failed


def _grey_pictures(project: Project, views):
    """``img(name)``: the photo's grey picture at the working size, read once and kept (a photo is the
    stereo neighbour of several others)."""
    gray: dict[str, np.ndarray] = {}

    def img(n):
        if n not in gray:
            gray[n] = load_image(project, views[n], gray=True)
        return gray[n]

    return img


def _depth_map(n: str, nb: list[str], views, img, settings: ModelSettings, folder: Path) -> str | None:
    """One photo's depth map from its stereo neighbours, written to its file; why it failed, or None."""
    pair = [d for m in nb if (d := D.pair_depth(views[n], views[m], img(n), img(m), settings)) is not None]
    if len(pair) < settings.min_pair_agree:
        return f"only {len(pair)} neighbour pair(s) could be rectified"
    depth, had, gone = D.texture_test(D.combine_pairs(pair, settings), img(n), settings)
    D.write_depth(D.depth_file(folder, n), depth, {"neighbours": nb, "had_depth": had, "textureless": gone})
    return None


def textureless_share(folder: Path, names) -> dict:
    """What the texture test gave up over the written depth maps: pixels with a depth before it, given up, and
    the share (of the pixels that had a depth)."""
    had = gone = 0
    for n in names:
        f = D.depth_file(folder, n)
        if f.is_file():
            h, g = D.read_depth_counts(f)
            had, gone = had + h, gone + g
    return {"pixels_with_depth": had, "given_up": gone, "share": round(gone / had, 4) if had else 0.0}


# photos a depth task: consecutive photos (a flight strip) share neighbours, whose images the task
# reads once; small enough that two workers stay busy to the end and a killed run loses little
DEPTH_CHUNK = 8


def _depth_chunk(task: tuple) -> dict[str, str]:
    """An executor task: the depth maps of a run of photos (see :func:`depth_maps`), {name: why} of
    those that failed."""
    root, views, chunk, settings, folder = task
    img = _grey_pictures(Project.load(root), views)
    failed = {}
    for n, nb in chunk:
        if D.depth_file(Path(folder), n).is_file():  # another run finished it meanwhile
            continue
        why = _depth_map(n, nb, views, img, settings, Path(folder))
        if why:
            failed[n] = why
    return failed


def _depth_maps_on(executor, project: Project, views, neighbours, todo, settings: ModelSettings, folder: Path,
                   show: bool) -> dict:
    from ..localize.executors import iter_map, make_executor

    tasks = []
    for k in range(0, len(todo), DEPTH_CHUNK):
        chunk = todo[k:k + DEPTH_CHUNK]
        need = {n for n, nb in chunk} | {m for _n, nb in chunk for m in nb}
        tasks.append((str(project.paths.root), {n: views[n] for n in need}, chunk, settings, str(folder)))
    ex = make_executor(executor)
    failed: dict[str, str] = {}
    try:
        log.info("depth maps: %d to compute in %d tasks on %s (%d workers)", len(todo), len(tasks), ex.name,
                 getattr(ex, "workers", 1))
        with _bar(len(neighbours), "depth maps", show) as bar:
            bar.update(len(neighbours) - len(todo))
            for task, res in zip(tasks, iter_map(ex, _depth_chunk, tasks)):
                failed.update(res)
                bar.update(len(task[2]))
    finally:
        ex.close()
    return failed


class _MapCache:
    """Depth maps read on demand, the ``size`` most recently used kept (a photo's fusion neighbours are
    near it and photos go strip by strip, so few are read twice; memory stays bounded on large sites)."""

    def __init__(self, folder: Path, size: int = 48):
        from collections import OrderedDict

        self.folder, self.size, self._maps = folder, size, OrderedDict()

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self._maps:
            self._maps.move_to_end(name)
        else:
            self._maps[name] = D.read_depth(D.depth_file(self.folder, name))
            if len(self._maps) > self.size:
                self._maps.popitem(last=False)
        return self._maps[name]


FUSION_VERSION = 2   # bump when fusion's method changes (a finished fused cloud of another version is not reused)
SURFACE_VERSION = 1  # the same for the surface tiles


def fusion_key(settings: ModelSettings, depth_folder: Path, names: list[str]) -> str:
    keys = ("region_margin", "fusion_stride", "voxel_m", "pair_agree", "min_view_agree", "fusion_cell_m")
    d = settings_dict(settings)
    return settings_key({"depth": depth_folder.name, "maps": len(names), "version": FUSION_VERSION,
                         "fusion": {k: d[k] for k in keys}})


def fuse(project: Project, views, neighbours, settings: ModelSettings, folder: Path, show: bool = True,
         out: Path | None = None, force: bool = False) -> fusion.FusedCells:
    """Fuse the depth maps into a cloud kept on disk cell by cell (``work/model/fused/<key>/``; see
    :mod:`gtkit.model.fusion`): memory is one photo while lifting and one cell while averaging. A
    finished fusion with the same depth maps and settings is reused unless ``force``."""
    names = [n for n in neighbours if D.depth_file(folder, n).is_file()]
    root = out or folder.parent.parent / "fused"
    dest = root / fusion_key(settings, folder, names)
    if not force and fusion.FusedCells.done(dest):
        log.info("fusion: reusing %s", dest)
        return fusion.FusedCells(dest)
    if root.is_dir():                                  # other settings' fused clouds
        for d in root.iterdir():
            if d != dest:
                shutil.rmtree(d, ignore_errors=True) if d.is_dir() else d.unlink()
    maps = _MapCache(folder)
    near = fusion_neighbours(views, names)
    box = region(views, settings.region_margin)
    spill = fusion.CellSpill(root / "spill", settings.voxel_m, settings.fusion_cell_m)
    with _bar(len(names), "fusion", show) as bar:
        for n in names:
            v, dm = views[n], maps[n]
            xw, rc = fusion.lift(v, dm, settings.fusion_stride)
            others = [(views[m], maps[m]) for m in near[n]]
            keep = np.all((xw[:, :2] >= box[0]) & (xw[:, :2] <= box[1]), axis=1)
            keep[keep] = fusion.consistent_count(xw[keep], others, settings.pair_agree) >= settings.min_view_agree
            xw, rc = xw[keep], rc[keep]
            rgb = load_image(project, v, gray=False)[rc[:, 0], rc[:, 1]]
            to_cam = v.center - xw
            to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
            spill.add(xw, rgb, to_cam)
            bar.update(1)
    log.info("fusion: %d lifted points in %d cells; averaging per voxel", spill.n, len(list(spill.folder.glob("c*.bin"))))
    return spill.reduce(dest, {"photos": len(names), "lifted": spill.n})


def _write_model(project: Project, mesh: Mesh, use: bool | None) -> Path:
    """Write the OBJ where it belongs and record it in project.toml (see the module docstring)."""
    P = project.paths
    current = project.config.get("model", {})
    delivered = (P.model / MODEL_FILE).is_file() and current.get("source") != "built"
    if delivered and use:
        keep = P.model / "delivered"
        keep.mkdir(parents=True, exist_ok=True)
        for f in list(P.model.iterdir()):
            if f.is_file():
                shutil.move(str(f), keep / f.name)
        delivered = False
    out = (P.model / "built" / MODEL_FILE) if delivered else (P.model / MODEL_FILE)
    if out.parent.is_dir() and out.parent == P.model:  # a previous built model: replace its files
        for f in P.model.glob("reference*"):
            if f.is_file():
                f.unlink()
    write_obj(out, mesh)
    write_offset_sidecar(out, project.frame.crs_spec, project.frame.origin)
    project.config["model"] = {"source": "built" if not delivered else "delivered",
                               "path": str((P.model / MODEL_FILE).relative_to(P.root)),
                               "built": str(out.relative_to(P.root)),
                               "when": time.strftime("%Y-%m-%dT%H:%M:%S")}
    project.save()
    return out


def _inputs(project: Project) -> dict:
    block = block_dir(project)
    return {"poses": file_fingerprint(block / POSES), "intrinsics": file_fingerprint(block / INTRINSICS)}


def depth_folder(project: Project, settings: ModelSettings, method: str) -> Path:
    """``work/model/depth/<key>/``: the depth maps of this block made by ``method`` with these settings
    (a folder of another key is never read)."""
    depth_keys = {k: v for k, v in settings_dict(settings).items()
                  if k in ("max_image_size", "neighbours", "min_neighbours", "max_angle_deg", "baseline_ratio",
                           "target_ratio", "max_disparities", "block_size", "pair_agree", "min_pair_agree",
                           "sgbm_disparity_bias_px", "texture_min_contrast", "texture_window",
                           "texture_margin_px")}
    if method != "sgbm":                  # (the SGBM maps' folder name is what it was before there was a choice)
        depth_keys["method"] = method
    key = settings_key({"depth": depth_keys, "inputs": _inputs(project), "version": DEPTH_VERSION})
    return project.paths.stage(STAGE) / "depth" / key


def run(project: Project | str | Path, settings: ModelSettings, *, force: bool = False,
        use: bool | None = None, show: bool = True, executor=None) -> dict:
    """Build the reference model; returns the summary (also in ``work/model/stage.json``).
    ``executor``: where the SGBM depth maps run (:func:`depth_maps`; None: in this process)."""
    project = project if isinstance(project, Project) else Project.load(project)
    method = patchmatch.resolve_method(settings.depth_method)     # a path that cannot run is refused first
    P = project.paths
    work = P.stage(STAGE)
    block = block_dir(project)
    views, skipped = load_views(project, settings)
    n_photos = len(views) + len(skipped)
    inputs = _inputs(project)
    if not force and stage_done(work, settings, inputs) and use is None:
        return read_stage_record(work).summary
    start_stage_clock(work)
    if len(views) < 3:
        raise NoStereo(f"only {len(views)} usable registered photos in the reference block", block)
    t = {"start": time.time()}
    mem, cpu = {}, {"start": _cpu_s()}
    _reset_peak()
    neighbours, sk = choose_neighbours(views, settings)
    skipped.update(sk)
    for n, why in sk.items():
        log.warning("skipping %s: %s", n, why)
    if not neighbours:
        raise NoStereo("no photo has enough neighbours for stereo (see the reasons with -v)", block)
    folder = depth_folder(project, settings, method)
    folder.mkdir(parents=True, exist_ok=True)
    kids = _children_peak_gb()
    if method == "patchmatch":
        failed = patchmatch.depth_maps(project, views, neighbours, settings, folder, block, show)
    else:
        failed = depth_maps(project, views, neighbours, settings, folder, show, executor=executor)
    skipped.update(failed)
    _mark("depth", t, mem, cpu)
    if method != "patchmatch" and executor is not None and _children_peak_gb() > kids:
        mem["depth"] = max(mem["depth"], _children_peak_gb())   # a local worker's peak, if more than this process's
    textureless = textureless_share(folder, neighbours) if method != "patchmatch" else None
    _step_done("depth", t, mem, f"{len(neighbours) - len(failed)} depth maps ({method})" + (
        f"; texture test: {100 * textureless['share']:.1f} % of the depth given up as textureless "
        f"(contrast < {settings.texture_min_contrast:g} DN over {settings.texture_window} px, and "
        f"{settings.texture_margin_px} px around)" if textureless else ""))

    cloud = fuse(project, views, neighbours, settings, folder, show, force=force)
    n_points = len(cloud)
    if n_points < 100:
        raise NoStereo(f"fusion kept only {n_points} points: the {len(neighbours) - len(failed)} depth maps do not "
                       "agree where they overlap", folder)
    laz = work / "points.laz"
    stamp = cloud.folder / "laz.done"
    if force or not (laz.is_file() and stamp.is_file()):
        fusion.write_laz_cells(laz, cloud, np.asarray(project.frame.origin), project.frame.crs_spec)
        stamp.write_text(str(laz.stat().st_size))
    _mark("fusion", t, mem, cpu)
    _step_done("fusion", t, mem, f"{n_points} points in {len(cloud.cells)} cells")

    skey = settings_key({"fusion": cloud.folder.name, "version": SURFACE_VERSION,
                         "surface": {k: v for k, v in settings_dict(settings).items()
                                     if k in ("poisson_depth", "trim_m", "max_triangles", "tile_m", "tile_overlap_m", "voxel_m")}})
    sdir = work / "surface" / skey
    if sdir.parent.is_dir():
        for d in sdir.parent.iterdir():
            if d != sdir or force:
                shutil.rmtree(d, ignore_errors=True) if d.is_dir() else d.unlink()
    V, F, n_poisson, n_tiles = surface.tiled_surface(cloud, settings, log=log, save=sdir)
    del cloud
    if not len(F):
        raise GtkitError("the Poisson surface is empty after trimming", folder)
    _mark("surface", t, mem, cpu)
    _step_done("surface", t, mem, f"{len(F)} triangles in {n_tiles} tile(s)")

    with _bar(len(views), "texture (visibility)", show) as bar:
        names, best = texture.choose_views(V, F, views, progress=bar)
    def rgb_of(v):
        return load_image(project, v, gray=False)

    seams = texture.seam_colours(V, F, views, names, best, rgb_of)
    gains = texture.colour_gains(seams, len(names)) if settings.colour_balance else None
    seam_diff = {"edges": int(len(seams["a"])), "before": round(texture.seam_difference(seams), 2),
                 "after": round(texture.seam_difference(seams, gains), 2)}
    log.info("colour at seams: median |dRGB| %.2f -> %.2f over %d seam edges", seam_diff["before"],
             seam_diff["after"], seam_diff["edges"])
    del seams
    parts = texture.textured_parts(V, F, views, names, best, rgb_of, gains=gains)
    mesh, n_parts = Mesh(parts), len(parts)
    out = _write_model(project, mesh, use)
    tiles = out.parent / TILES_DIR
    if tiles.is_dir():
        shutil.rmtree(tiles)
    if n_tiles > 1:     # a large site: also the tiled model (ContextCapture layout), for memory-bounded readers
        from ..io.tiled import write_tiled

        write_tiled(mesh, tiles, project.frame.crs_spec, project.frame.origin, settings.tile_m, texture="pack")
        project.config["model"]["tiled"] = str(tiles.relative_to(P.root))
        project.save()
    del mesh, parts
    _mark("texture", t, mem, cpu)
    _step_done("texture", t, mem, f"{out.relative_to(P.root)}" + (f" and {n_tiles} tiles" if n_tiles > 1 else ""))

    steps = ["depth", "fusion", "surface", "texture"]
    prev, seconds, cpu_s = t["start"], {}, {}
    for s in steps:
        seconds[s], prev = round(t[s] - prev, 1), t[s]
    prev = cpu["start"]
    for s in steps:
        cpu_s[s], prev = round(cpu[s] - prev, 1), cpu[s]
    summary = {"model": str(out.relative_to(P.root)), "photos": n_photos,
               "depth_maps": len(neighbours) - len(failed), "depth_method": method, "textureless": textureless, "skipped": skipped, "points": int(n_points),
               "poisson_triangles": int(n_poisson), "triangles": int(len(F)), "parts": n_parts,
               "surface_tiles": n_tiles, "unseen_faces": int((best < 0).sum()), "seam_colour_diff": seam_diff, "seconds": seconds,
               "cpu_seconds": cpu_s, "peak_memory_gb": {k: round(v, 2) for k, v in mem.items()},
               "peak_memory_gb_max": round(max(mem.values()), 2)}
    outputs = [f for f in P.model.iterdir() if f.name != "delivered"]  # not the delivered model kept aside
    mark_stage_done(work, settings, inputs, outputs=outputs, **summary)
    return summary
