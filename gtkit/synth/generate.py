"""``create_sample``: write a complete sample project folder (see BRIEF / README for the layout).

Deterministic: the same settings and seed give byte-identical files (seeded RNG streams per
part, simulated timestamps only, sorted outputs, atomic writes).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..geo import GeoFrame
from ..io.atomic import write_bytes, write_json, write_text
from ..io.mesh import Mesh, write_obj, write_offset_sidecar
from ..io.poses import write_intrinsics, write_poses
from ..io.tiepoints import write_tiepoints
from ..progress import progress_bar
from ..project import Paths, Project
from ..render.renderer import Renderer
from . import annotate, flights, photos
from .refmodel import reference_model
from .settings import SynthSettings
from .shading import MICRO_BELOW_M, finest_footprint_m, world_glsl
from .targets import make_tracks
from .world import build_world, true_mesh

log = logging.getLogger(__name__)
GENERATOR = "gtkit.synth 1"
MODEL_NAMES = {"reference": "FiveEye-Oblique (simulated)", "wide": "ZH20T (simulated)", "zoom": "ZH20T (simulated)"}


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), stream])


def _bar(desc: str, total: int | None, quiet: bool):
    return progress_bar(total, desc, unit="img" if "photo" in desc else "it", show=not quiet)


def create_sample(root: str | Path, s: SynthSettings, *, quiet: bool = False) -> dict:
    """Generate the sample project into ``root`` (must be absent or empty). Returns a summary."""
    root = Path(root)
    if root.exists() and any(root.iterdir()):
        raise GtkitError("folder exists and is not empty; give a new folder", root)
    t0 = time.perf_counter()
    timings = {}
    paths = Paths(root)
    frame = GeoFrame.for_lonlat(s.site.lon, s.site.lat, 0.0)

    # --- the true world ---------------------------------------------------------------------
    t = time.perf_counter()
    world = build_world(s, _rng(s.seed, 1))
    mesh = true_mesh(world, s, _rng(s.seed, 11))
    glsl = world_glsl(world, micro=finest_footprint_m(s) < MICRO_BELOW_M)
    tracks = make_tracks(world, (s.targets.car_speed, s.targets.person_speed), _rng(s.seed, 12))
    world_r = Renderer(mesh, glsl)
    target_r = Renderer()
    timings["world"] = time.perf_counter() - t
    Project.create(root, frame, name=f"sample-{s.preset}", extra={"sample": {
        "preset": s.preset, "seed": s.seed, "gps_denied": s.gps_denied, "generator": GENERATOR,
        "note": "generated sample site; truth/ is for evaluation only"}})

    # --- reference flight -------------------------------------------------------------------
    t = time.perf_counter()
    ref = flights.reference_shots(world, s)
    rs = s.reference
    light_ref = photos.sun_lighting(rs.sun_azimuth_deg, rs.sun_elevation_deg, rs.ambient, rs.gain)
    takeoff_z = float(world.terrain_height(0.0, 0.0))
    ref_depth: dict[str, np.ndarray] = {}   # for visibility tests; subsampled on big flights
    depth_step = 1 if len(ref) * rs.width * rs.height < 1.5e8 else 2
    rng_meta, rng_noise = _rng(s.seed, 3), _rng(s.seed, 4)
    with _bar("reference photos", len(ref), quiet) as bar:
        for sh in ref:
            rgb, depth, _ = photos.render_view(world_r, sh.camera, sh.pose, light_ref)
            ref_depth[sh.name] = depth[::depth_step, ::depth_step].astype(np.float16)
            img = photos.degrade(rgb, rng_noise, blur_sigma=rs.blur_sigma_px, noise_sigma=rs.noise_sigma)
            meta = photos.photo_meta(frame, sh.pose, sh.flight_yaw, takeoff_z, rng_meta, gps_sigma=rs.gps_sigma_m,
                                     alt_sigma=rs.gps_sigma_m * 1.5, angle_sigma=rs.angle_sigma_deg, gps=True)
            photos.write_photo(paths.images / sh.name, img, meta, timestamp=photos.exif_time(rs.date, sh.time_s),
                               model=MODEL_NAMES["reference"], camera=sh.camera,
                               sensor_width_mm=photos.SENSOR_WIDTH_MM[sh.kind], quality=rs.jpeg_quality)
            bar.update(1)
    timings["reference_photos"] = time.perf_counter() - t

    # --- GCPs ---------------------------------------------------------------------------------
    rng_ann = _rng(s.seed, 5)
    clicks = annotate.gcp_clicks(world.gcps, ref, ref_depth, s.annotation.gcp_click_sigma_px,
                                 s.annotation.gcp_max_clicks, rng_ann)
    gcp_crs = frame.local_to_crs(world.gcps)
    lines = [frame.crs_spec]
    for g, name, px, py in clicks:
        E, N, H = gcp_crs[g]
        lines.append(f"{E:.4f} {N:.4f} {H:.4f} {px:.2f} {py:.2f} {name} gcp{g + 1:02d}")
    write_text(paths.gcp_list, "\n".join(lines) + "\n")

    # --- query flights ------------------------------------------------------------------------
    t = time.perf_counter()
    qs = s.queries
    qshots = flights.query_shots(world, tracks, s, _rng(s.seed, 2))
    light_q = photos.sun_lighting(qs.sun_azimuth_deg, qs.sun_elevation_deg, qs.ambient, qs.gain)
    tps, tp_truth = [], []   # tie points of each photo as it is rendered (no photo is kept)
    t_ties = 0.0
    meta_by_base: dict[str, dict] = {}
    with _bar("query photos", len(qshots), quiet) as bar:
        for sh in qshots:
            targets = Mesh([tr.mesh_at(sh.time_s, world) for tr in tracks.values()])
            gain = 1.0 + float(rng_noise.uniform(-qs.gain_jitter, qs.gain_jitter))
            rgb, depth, tmask = photos.render_view(world_r, sh.camera, sh.pose, light_q, target_r, targets)
            img = photos.degrade(rgb, rng_noise, tint=qs.tint, gain=gain, blur_sigma=qs.blur_sigma_px,
                                 noise_sigma=qs.noise_sigma)
            base = sh.name.rsplit("_", 1)[0]
            if base not in meta_by_base:  # the zoom photo carries the same gimbal record as its wide twin
                wide_pose = sh.pose
                meta_by_base[base] = photos.photo_meta(
                    frame, wide_pose, sh.flight_yaw, takeoff_z, rng_meta, gps_sigma=qs.gps_sigma_m,
                    alt_sigma=qs.alt_sigma_m, angle_sigma=qs.angle_sigma_deg, gps=not s.gps_denied)
            photos.write_photo(paths.images / sh.name, img, meta_by_base[base],
                               timestamp=photos.exif_time(qs.date, sh.time_s), model=MODEL_NAMES[sh.kind],
                               camera=sh.camera, sensor_width_mm=photos.SENSOR_WIDTH_MM[sh.kind],
                               quality=qs.jpeg_quality)
            t1 = time.perf_counter()
            gray = (rgb.astype(np.float32) @ [0.299, 0.587, 0.114]).astype(np.uint8)
            annotate.query_tie_points((sh, gray, depth, tmask), ref, ref_depth, s.annotation, rng_ann, tps, tp_truth)
            t_ties += time.perf_counter() - t1
            bar.update(1)
    timings["query_photos"] = time.perf_counter() - t - t_ties

    # --- tie points (each photo's above; the gross mistakes over all) -------------------------
    t = time.perf_counter()
    annotate.add_gross_mistakes(tps, tp_truth, ref, s.annotation, rng_ann)
    write_tiepoints(paths.tiepoints, tps)
    timings["tiepoints"] = time.perf_counter() - t + t_ties

    # --- reference model ----------------------------------------------------------------------
    t = time.perf_counter()
    with _bar("reference model (textures)", None, quiet) as bar:
        model = reference_model(world, s, glsl, _rng(s.seed, 6), progress=bar)
    off = np.floor(np.asarray(frame.origin) / s.model.offset_round_m) * s.model.offset_round_m
    off[2] = 0.0
    model_path = paths.model / "reference.obj"
    write_obj(model_path, model.translated(np.asarray(frame.origin) - off))
    write_offset_sidecar(model_path, frame.crs_spec, off)
    timings["reference_model"] = time.perf_counter() - t

    # --- cameras as the user knows them, and the truth -------------------------------------------
    t = time.perf_counter()
    allshots = ref + qshots
    write_intrinsics(paths.cameras, {sh.name: sh.camera for sh in allshots})
    write_poses(paths.truth_poses, {sh.name: sh.pose for sh in allshots},
                header="true poses of every photo (sample generator)")
    write_intrinsics(paths.truth_intrinsics, {sh.name: sh.camera for sh in allshots})
    write_ply(paths.truth / "world.ply", mesh)
    Rzw, tzw = flights.zoom_from_wide(s)
    write_json(paths.truth / "rig.json", {
        "convention": "x_zoom = R @ x_wide + t (camera frames, OpenCV axes, metres)",
        "R": np.round(Rzw, 12).tolist(), "t": tzw.tolist(), "rotvec_deg": list(qs.zoom_rotation_deg),
        "wide": flights.wide_camera(s).to_line(), "zoom": flights.zoom_camera(s).to_line(),
        "note": "zoom photos carry the gimbal record (GPS, DJI angles) of their wide twin"})
    write_json(paths.truth / "world.json", {
        "generator": GENERATOR, "preset": s.preset, "seed": s.seed, "crs": frame.crs_spec,
        "origin": list(frame.origin), "settings": s.as_dict(), "world": world.to_json(),
        "mesh": "world.ply: x y z (world frame), u v (pattern uv), red green blue, material",
        "materials": {"0": "terrain (land cover from position)", "1": "wall", "2": "flat roof", "3": "tiled roof",
                      "4": "tree canopy", "5": "GCP target"},
        "lighting": {"reference": vars(light_ref), "queries": vars(light_q)},
        "targets": {k: {"path": v.path.tolist(), "speed": v.speed, "closed": v.closed, "size": list(v.size)}
                    for k, v in tracks.items()},
        "takeoff_z": takeoff_z, "reference_date": rs.date, "query_date": qs.date,
        "procedural_glsl": glsl})
    write_targets_csv(paths.truth / "targets.csv", tracks, world, frame, qshots, s)
    write_json(paths.truth / "tiepoints_truth.json", {
        "gross_share_setting": s.annotation.gross_share, "tiepoints": tp_truth})
    write_json(paths.truth / "shots.json", {"shots": [
        {"name": sh.name, "kind": sh.kind, "sequence": sh.sequence, "time_s": sh.time_s, "manual": sh.manual,
         "follow": sh.follow, "flight_yaw": round(sh.flight_yaw, 6)} for sh in allshots]})
    timings["truth"] = time.perf_counter() - t
    world_r.release()
    target_r.release()
    timings["total"] = time.perf_counter() - t0
    log.debug("sample %s (seed %d) written to %s in %.1f s", s.preset, s.seed, root, timings["total"])
    return {"root": str(root), "n_reference": len(ref), "n_query": len(qshots), "n_gcp_clicks": len(clicks),
            "n_tiepoints": len(tps), "timings_s": timings}


def write_ply(path: Path, mesh: Mesh) -> Path:
    """Binary little-endian PLY of the whole mesh (deterministic, no comments with dates)."""
    V = np.concatenate([p.vertices for p in mesh.parts])
    UV = np.concatenate([p.uv if p.uv is not None else np.zeros((len(p.vertices), 2)) for p in mesh.parts])
    C = np.concatenate([p.colors if p.colors is not None else np.full((len(p.vertices), 3), 128, np.uint8)
                        for p in mesh.parts])
    M = np.concatenate([p.material if p.material is not None else np.zeros(len(p.vertices)) for p in mesh.parts])
    F, off = [], 0
    for p in mesh.parts:
        F.append(p.faces + off)
        off += len(p.vertices)
    F = np.concatenate(F)
    head = ("ply\nformat binary_little_endian 1.0\ncomment gtkit sample world (world frame, metres)\n"
            f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
            "property float u\nproperty float v\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
            f"property uchar material\nelement face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    vt = np.dtype([("p", "<f8", 3), ("uv", "<f4", 2), ("c", "u1", 3), ("m", "u1")])
    va = np.empty(len(V), vt)
    va["p"], va["uv"], va["c"], va["m"] = V, UV, C, M.astype(np.uint8)
    ft = np.dtype([("n", "u1"), ("i", "<i4", 3)])
    fa = np.empty(len(F), ft)
    fa["n"], fa["i"] = 3, F
    return write_bytes(path, head.encode() + va.tobytes() + fa.tobytes())


def write_targets_csv(path: Path, tracks, world, frame, qshots, s: SynthSettings) -> Path:
    import datetime as dt

    t_end = max(sh.time_s for sh in qshots) + 10.0
    times = np.arange(0.0, t_end + 1e-9, s.targets.track_step_s)
    base = dt.datetime.fromisoformat(s.queries.date)
    rows = ["target,time_s,datetime,x,y,z,easting,northing,height,lon,lat"]
    for name in sorted(tracks):
        P = np.array([tracks[name].position(t, world) for t in times])
        crs = frame.local_to_crs(P)
        wgs = frame.local_to_wgs84(P)
        for t, p, c, g in zip(times, P, crs, wgs):
            stamp = (base + dt.timedelta(seconds=float(t))).isoformat(timespec="milliseconds")
            rows.append(f"{name},{t:.2f},{stamp},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},{c[0]:.4f},{c[1]:.4f},"
                        f"{c[2]:.4f},{g[0]:.9f},{g[1]:.9f}")
    return write_text(path, "\n".join(rows) + "\n")
