"""Tracking evaluation against a sample site's truth (evaluation code: it reads ``truth/``).

``evaluate_tracking(paths)`` compares ``exports/tracks.csv`` with ``truth/targets.csv``: each
located detection is matched to the true position of its target (by label) at the photo's
instant (``truth/shots.json`` time of the zoom photo; else the detection's own time column,
aligned with the truth's ``datetime``), linearly interpolated in the true track. Errors:
horizontal and 3D, median and recall at 1/3/5/10 m (failed detections count as misses), for
the raw points and, when present, the smoothed track. Also the rig calibration against
``truth/rig.json`` (rotation error in degrees, focal error in %). Writes
``reports/tracking.json`` and a plot ``reports/tracking.png`` (true vs estimated tracks).

``simulate_detections(paths, out, ...)``: what a detector would report in every zoom photo
that sees a target -- the target's true 3D box (size from ``truth/world.json``, heading from
the track) projected with the TRUE zoom pose and camera, plus pixel noise. Only for sample
sites and tests (it reads truth).
"""
from __future__ import annotations

import csv
import json
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..conventions import rotation_angle_deg
from ..errors import GtkitError
from ..io.atomic import atomic_path, write_json, write_text
from ..io.poses import read_intrinsics, read_poses
from ..project import Paths, Project, relative_paths

THRESHOLDS_M = (1.0, 3.0, 5.0, 10.0)


# --- truth ------------------------------------------------------------------------------------

def _csv_rows(path: Path) -> list[dict]:
    if not path.is_file():
        raise GtkitError("file not found", path)
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip() and not ln.startswith("#")]
    return list(csv.DictReader(lines))


def _iso_seconds(s: str) -> float:
    d = datetime.fromisoformat(s)
    return (d if d.tzinfo else d.replace(tzinfo=timezone.utc)).timestamp()


class TruthTracks:
    """truth/targets.csv: per target, time (s after the query date) -> world (x, y, z)."""

    def __init__(self, path: Path):
        rows = _csv_rows(path)
        if not rows or not {"target", "time_s", "x", "y", "z"} <= set(rows[0]):
            raise GtkitError("expected columns target,time_s,...,x,y,z", path)
        self.tracks: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        by: dict[str, list] = {}
        self.epoch = None  # absolute seconds of time_s = 0 (from the datetime column)
        for r in rows:
            by.setdefault(r["target"], []).append((float(r["time_s"]), float(r["x"]), float(r["y"]), float(r["z"])))
            if self.epoch is None and r.get("datetime"):
                self.epoch = _iso_seconds(r["datetime"]) - float(r["time_s"])
        for k, v in by.items():
            a = np.array(sorted(v))
            self.tracks[k] = (a[:, 0], a[:, 1:])

    def at(self, label: str, t: float) -> np.ndarray | None:
        if label not in self.tracks:
            return None
        ts, P = self.tracks[label]
        if t < ts[0] - 1e-6 or t > ts[-1] + 1e-6:
            return None
        return np.array([np.interp(t, ts, P[:, i]) for i in range(3)])

    def heading(self, label: str, t: float, dt: float = 0.25) -> float:
        a, b = self.at(label, max(t - dt, self.tracks[label][0][0])), self.at(label, t + dt)
        if a is None or b is None or np.hypot(*(b - a)[:2]) < 1e-6:
            return 0.0
        return float(np.arctan2(b[1] - a[1], b[0] - a[0]))


def shot_times(paths: Paths) -> dict[str, float]:
    f = paths.truth / "shots.json"
    if not f.is_file():
        return {}
    return {s["name"]: float(s["time_s"]) for s in json.loads(f.read_text())["shots"]}


# --- simulated detections ---------------------------------------------------------------------

def _box_corners(centre, heading, size):
    L, W, H = size
    c, s = np.cos(heading), np.sin(heading)
    pts = np.array([[x, y, z] for x in (-L / 2, L / 2) for y in (-W / 2, W / 2) for z in (0.0, H)])
    xy = pts[:, :2] @ np.array([[c, s], [-s, c]])
    return np.column_stack([xy + centre[:2], pts[:, 2] + centre[2]])


class _TrueWorld:
    """Line-of-sight tests against the true world mesh (Open3D ray casting)."""

    def __init__(self, ply: Path):
        import open3d as o3d
        import trimesh

        m = trimesh.load(str(ply), process=False)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32))

    def hidden(self, eye, point, margin: float = 0.3) -> bool:
        import open3d as o3d

        d = np.asarray(point, float) - eye
        dist = float(np.linalg.norm(d))
        ray = np.concatenate([eye, d / dist]).astype(np.float32)[None]
        t = float(self.scene.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])
        return np.isfinite(t) and t < dist - margin


def simulate_detections(paths: Paths, out: Path, *, sigma_px: float = 1.0, mode: str = "box",
                        min_box_px: float = 4.0, seed: int = 0) -> int:
    """Write a detections CSV (``image,xmin,ymin,xmax,ymax,label,time`` for ``mode="box"``, or
    ``image,x,y,label,time`` with the projected true ground point for ``mode="point"``) for
    every zoom photo whose view holds a target that is not hidden from the camera (line of sight to
a point at 80% of its height, tested on ``truth/world.ply``). Returns the number of detections."""
    truth = TruthTracks(paths.truth / "targets.csv")
    poses = read_poses(paths.truth_poses)
    cams = read_intrinsics(paths.truth_intrinsics)
    times = shot_times(paths)
    world = json.loads((paths.truth / "world.json").read_text()) if (paths.truth / "world.json").is_file() else {}
    sizes = {k: tuple(v["size"]) for k, v in world.get("targets", {}).items()}
    rng = np.random.default_rng(seed)
    occluder = _TrueWorld(paths.truth / "world.ply") if (paths.truth / "world.ply").is_file() else None
    rows = []
    for name in sorted(poses):
        if not name.rsplit(".", 1)[0].endswith("_Z") or name not in times:
            continue
        pose, cam = poses[name], cams[name]
        t = times[name]
        for label in sorted(truth.tracks):
            X = truth.at(label, t)
            if X is None:
                continue
            size = sizes.get(label, (1.0, 1.0, 1.5))
            if occluder is not None and occluder.hidden(pose.center, X + [0, 0, 0.8 * size[2]]):
                continue  # a detector cannot see a target hidden by a building or a tree
            if mode == "point":
                uv, front = cam.project(pose.transform(X[None]))
                if not front[0] or not cam.in_image(uv[0]):
                    continue
                u, v = uv[0] + rng.normal(0, sigma_px, 2)
                rows.append(f"{name},{u:.2f},{v:.2f},{label},{t:.3f}")
                continue
            corners = _box_corners(X, truth.heading(label, t), size)
            uv, front = cam.project(pose.transform(corners))
            if not front.all():
                continue
            lo, hi = uv.min(0), uv.max(0)
            lo, hi = np.maximum(lo, 0), np.minimum(hi, [cam.width, cam.height])
            if np.any(hi - lo < min_box_px) or not cam.in_image(0.5 * (lo + hi)):
                continue
            box = np.concatenate([lo, hi]) + rng.normal(0, sigma_px, 4)
            rows.append(f"{name},{box[0]:.2f},{box[1]:.2f},{box[2]:.2f},{box[3]:.2f},{label},{t:.3f}")
    head = "image,x,y,label,time" if mode == "point" else "image,xmin,ymin,xmax,ymax,label,time"
    write_text(out, f"# simulated detections from truth ({mode}, sigma {sigma_px} px); time = s after the "
               "query date\n" + head + "\n" + "\n".join(rows) + "\n")
    return len(rows)


# --- evaluation -------------------------------------------------------------------------------

def _stats(errs: list[float | None], prefix: str) -> dict:
    ok = np.array([e for e in errs if e is not None], float)
    n = max(len(errs), 1)
    out = {f"median_err_{prefix}_m": float(np.median(ok)) if len(ok) else None,
           f"mean_err_{prefix}_m": float(np.mean(ok)) if len(ok) else None,
           f"p90_err_{prefix}_m": float(np.percentile(ok, 90)) if len(ok) else None,
           f"recall_{prefix}": {f"{m:g}m": float(np.sum(ok <= m) / n) for m in THRESHOLDS_M}}
    return out


def evaluate_rig(paths: Paths) -> dict | None:
    from ..track.rig import Rig

    tf = paths.truth / "rig.json"
    if not tf.is_file() or not paths.rig.is_file():
        return None
    t = json.loads(tf.read_text())
    R_true = np.array(t["R"])
    f = t["zoom"].split()
    zoom_true = Camera(f[0], int(f[1]), int(f[2]), tuple(float(v) for v in f[3:]))
    est = Rig.load(paths.rig)
    cam = est.zoom_camera(zoom_true.width, zoom_true.height)
    off_true = -R_true.T @ np.array(t.get("t", [0, 0, 0]), float)
    nominal = est.info.get("nominal", [])
    nom_f = float(nominal[0].split()[3]) if nominal else None
    return {"rotation_err_deg": rotation_angle_deg(est.R_zw, R_true),
            "rotation_true_deg": rotation_angle_deg(np.eye(3), R_true),
            "focal_err_pct": float(100 * (cam.fx - zoom_true.fx) / zoom_true.fx),
            "focal_est_px": cam.fx, "focal_true_px": zoom_true.fx,
            "focal_nominal_err_pct": None if nom_f is None else float(100 * (nom_f - zoom_true.fx) / zoom_true.fx),
            "offset_true_m": off_true.tolist(), "offset_used_m": est.offset.tolist(),
            "n_pairs": est.info.get("n_pairs"), "median_px": est.info.get("median_px")}


def evaluate_tracking(paths: Paths | str | Path, tracks: Path | None = None, out: Path | None = None,
                      plot: bool = True, label: str = "") -> dict:
    """Score the tracks; write ``reports/tracking.json`` (or ``out``) and the plot; return the report."""
    paths = paths if isinstance(paths, Paths) else Paths(paths)
    tracks = Path(tracks) if tracks else paths.tracks
    out = Path(out) if out else paths.tracking_report
    truth = TruthTracks(paths.truth / "targets.csv")
    times = shot_times(paths)
    rows = _csv_rows(tracks)
    if not rows:
        raise GtkitError("no tracks to evaluate", tracks)
    origin = np.array(Project.load(paths.root).frame.origin)
    per, eh, e3, sh, s3 = [], [], [], [], []
    for r in rows:
        t = times.get(r["image"])
        if t is None and r.get("time") and truth.epoch is not None:
            t = float(r["time"]) - truth.epoch if float(r["time"]) > 1e8 else float(r["time"])
        X = truth.at(r["label"], t) if t is not None else None
        rec = {"image": r["image"], "label": r["label"], "time_s": t, "status": r["status"]}
        if r.get("on_filled_dsm") == "1":
            rec["on_filled_dsm"] = True
        if X is None:
            rec["note"] = "no true position at this time (unknown label or time)"
        if r["status"] == "ok" and X is not None:
            est = np.array([float(r["x"]), float(r["y"]), float(r["z"])]) - origin
            d = est - X
            rec.update(err_h_m=float(np.hypot(d[0], d[1])), err_3d_m=float(np.linalg.norm(d)),
                       err_z_m=float(d[2]), sigma_h_m=float(r["sigma_h_m"]) if r.get("sigma_h_m") else None,
                       est=est.tolist(), true=X.tolist())
            if r.get("smoothed_x"):
                sm = np.array([float(r["smoothed_x"]), float(r["smoothed_y"]), float(r["smoothed_z"])]) - origin
                ds = sm - X
                rec.update(smoothed_err_h_m=float(np.hypot(ds[0], ds[1])), smoothed_err_3d_m=float(np.linalg.norm(ds)),
                           smoothed=sm.tolist())
        per.append(rec)
        eh.append(rec.get("err_h_m"))
        e3.append(rec.get("err_3d_m"))
        sh.append(rec.get("smoothed_err_h_m"))
        s3.append(rec.get("smoothed_err_3d_m"))
    rep = {"label": label, "tracks": str(tracks), "n_targets": len(per),
           "n_failed": sum(1 for r in per if r["status"] != "ok"),
           "failures": {}, **_stats(eh, "h"), **_stats(e3, "3d")}
    filled = [r for r in per if r.get("on_filled_dsm")]
    rep["n_on_filled_dsm"] = len(filled)   # placed on DSM cells interpolated over a gap (tracks.csv on_filled_dsm)
    if filled:
        rep["on_filled_dsm"] = _stats([r.get("err_h_m") for r in filled], "h")
    for r in per:
        if r["status"] != "ok":
            rep["failures"][r["status"]] = rep["failures"].get(r["status"], 0) + 1
    if any(v is not None for v in sh):
        rep["smoothed"] = {**_stats(sh, "h"), **_stats(s3, "3d")}
    sig = [(r["err_h_m"], r["sigma_h_m"]) for r in per if r.get("sigma_h_m")]
    if sig:
        a = np.array(sig)
        rep["share_within_2sigma_h"] = float(np.mean(a[:, 0] <= 2 * a[:, 1]))
        rep["median_sigma_h_m"] = float(np.median(a[:, 1]))
    by_label = {}
    for lab in sorted({r["label"] for r in per}):
        rs = [r for r in per if r["label"] == lab]
        by_label[lab] = {"n": len(rs), **_stats([r.get("err_h_m") for r in rs], "h")}
    rep["by_label"] = by_label
    rep["rig"] = evaluate_rig(paths)
    rep["paper"] = "UAVD4L reports 'meter-level' target tracking accuracy (no number given)"
    rep["per_detection"] = per
    if plot:
        rep["plot"] = str(plot_tracks(per, truth, out.with_suffix(".png")))
    rep = relative_paths(rep, paths.root)  # portable: the tracks and the plot named inside the project
    write_json(out, rep)
    write_text(out.with_suffix(".md"), readable(rep))
    return rep


def evaluate_project(project, **_options) -> dict:
    """Entry point for ``gtkit evaluate`` (``--what tracking``)."""
    paths = project.paths if hasattr(project, "paths") else Paths(project)
    return evaluate_tracking(paths)


def readable(rep: dict) -> str:
    def f(v, nd=2):
        return "-" if v is None else f"{v:.{nd}f}"

    lines = [f"# Target tracking vs truth {rep.get('label') or ''}".rstrip(), "",
             f"tracks: `{rep['tracks']}`", "",
             f"- detections: {rep['n_targets']}, failed (no coordinate): {rep['n_failed']} {rep['failures'] or ''}",
             f"- median error horizontal {f(rep['median_err_h_m'])} m, 3D {f(rep['median_err_3d_m'])} m "
             f"(p90 horizontal {f(rep['p90_err_h_m'])} m)",
             "- recall (horizontal): " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in rep["recall_h"].items()),
             "- recall (3D): " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in rep["recall_3d"].items())]
    if rep.get("n_on_filled_dsm"):
        lines.append(f"- on filled DSM cells (interpolated over a gap): {rep['n_on_filled_dsm']} detections, median "
                     f"horizontal {f(rep['on_filled_dsm']['median_err_h_m'])} m")
    if rep.get("smoothed"):
        sm = rep["smoothed"]
        lines.append(f"- smoothed track: median horizontal {f(sm['median_err_h_m'])} m, 3D {f(sm['median_err_3d_m'])} m")
    if rep.get("median_sigma_h_m") is not None:
        lines.append(f"- propagated sigma (horizontal, median) {f(rep['median_sigma_h_m'])} m; errors within "
                     f"2 sigma: {100 * rep['share_within_2sigma_h']:.0f}%")
    for lab, b in rep.get("by_label", {}).items():
        lines.append(f"- {lab}: {b['n']} detections, median horizontal {f(b['median_err_h_m'])} m")
    if rep.get("rig"):
        r = rep["rig"]
        lines.append(f"- rig calibration: rotation error {f(r['rotation_err_deg'], 4)} deg, focal error "
                     f"{f(r['focal_err_pct'], 3)} % ({r.get('n_pairs')} pairs)")
    lines += ["", f"paper: {rep['paper']}", ""]
    return "\n".join(lines)


def plot_tracks(per: list[dict], truth: TruthTracks, path: Path) -> Path:
    """True vs estimated tracks (top view), one panel per target, errors as segments."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = sorted({r["label"] for r in per if "est" in r}) or sorted(truth.tracks)
    fig, axes = plt.subplots(2, len(labels), figsize=(6 * len(labels), 8.0), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.4]})
    for ax, ex, lab in zip(axes[0], axes[1], labels):
        rs = [r for r in per if r["label"] == lab and "est" in r]
        if rs:
            t0 = min(r["time_s"] for r in rs) - 2
            t1 = max(r["time_s"] for r in rs) + 2
            ts, P = truth.tracks[lab]
            m = (ts >= t0) & (ts <= t1)
            ax.plot(P[m, 0], P[m, 1], "-", color="green", lw=1.5, label="true track")
            E = np.array([r["est"] for r in rs])
            Tt = np.array([r["true"] for r in rs])
            for e, tr in zip(E, Tt):
                ax.plot([e[0], tr[0]], [e[1], tr[1]], "-", color="0.6", lw=0.8)
            ax.plot(Tt[:, 0], Tt[:, 1], "o", mfc="none", color="green", ms=5, label="true at photo time")
            ax.plot(E[:, 0], E[:, 1], "x", color="red", ms=6,
                    label=f"estimated (median {np.median([r['err_h_m'] for r in rs]):.2f} m)")
            seqs = sorted({r["image"].rsplit("/", 1)[0] for r in rs})
            for k, seq in enumerate(seqs):  # one smoothed track per sequence
                S = [r["smoothed"] for r in sorted(rs, key=lambda r: r["time_s"])
                     if "smoothed" in r and r["image"].rsplit("/", 1)[0] == seq]
                if len(S) >= 2:
                    S = np.array(S)
                    ax.plot(S[:, 0], S[:, 1], "-", color="blue", lw=1, label="smoothed" if k == 0 else None)
            rt = sorted(rs, key=lambda r: r["time_s"])
            idx = np.arange(len(rt))
            ex.plot(idx, [r["err_h_m"] for r in rt], "x", color="red", label="horizontal")
            ex.plot(idx, [r["err_3d_m"] for r in rt], ".", color="black", label="3D")
            sm = [(i, r["smoothed_err_h_m"]) for i, r in zip(idx, rt) if "smoothed_err_h_m" in r]
            if sm:
                ex.plot(*zip(*sm), "+", color="blue", label="smoothed, horizontal")
            ex.set_xticks(idx)
            ex.set_xticklabels([r["image"].rsplit(".", 1)[0].replace("queries/", "") for r in rt], rotation=90,
                               fontsize=6)
            ex.set_xlabel("detection (in time order)")
            ex.set_ylabel("error (m)")
            ex.set_ylim(bottom=0)
            ex.legend(fontsize=7)
        ax.set_title(f"{lab}: {len(rs)} located")
        ax.set_aspect("equal")
        ax.set_xlabel("x east (m, world)")
        ax.set_ylabel("y north (m, world)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
