"""Target-tracking accuracy on a sample site, for several pose sources and foot-point choices.

    .venv/bin/python benchmarks/bench_tracking_accuracy.py SITE [--localized FILE] [--noise 0.5,0.2]

SITE is a sample project (``gtkit sample create SITE --preset small``); it is modified in place
(exports/dsm.tif, work/rig, detections_sim_*.csv, exports/tracks*.csv, reports/tracking*.json).
Detections are simulated from the truth (evaluation code: the targets' true 3D boxes projected
with the true zoom poses, 1 px noise), since the sample has no detector. Variants:

  true poses, point     the true ground point's pixel (no foot-point error): the floor set by
                        the DSM and the rig calibration alone
  true poses, box       box bottom centre / box centre lifted by half the target height
  noisy poses, box      true wide poses + N(0, sigma_pos) per axis on the centre and
                        N(0, sigma_rot) per axis on the rotation (labelled as such)
  localized, box        the localization stage's poses (--localized, default work/localize/poses.txt)

reports/tracking.json (+ .png, .md) is the localized (else true-pose) box-centre variant; every
variant's report is reports/tracking_<variant>.json. Prints a table.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtkit.evaluate.tracking import evaluate_tracking, simulate_detections  # noqa: E402
from gtkit.export import dsm as dsm_stage  # noqa: E402
from gtkit.io.poses import read_poses, write_poses  # noqa: E402
from gtkit.pose import Pose  # noqa: E402
from gtkit.project import Project  # noqa: E402
from gtkit.stages import settings_for  # noqa: E402
from gtkit.track import calibrate  # noqa: E402
from gtkit.track.tracker import TrackSettings, run as track  # noqa: E402


def noisy_poses(truth: Path, out: Path, sigma_pos: float, sigma_rot_deg: float, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    poses = {}
    for name, p in sorted(read_poses(truth).items()):
        if not name.startswith("queries/") or not name.rsplit(".", 1)[0].endswith("_W"):
            continue
        R = Rotation.from_rotvec(rng.normal(0, np.radians(sigma_rot_deg), 3)).as_matrix() @ p.R
        poses[name] = Pose.from_center(R, p.center + rng.normal(0, sigma_pos, 3))
    return write_poses(out, poses, header=f"true wide poses + noise ({sigma_pos} m, {sigma_rot_deg} deg per axis)")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("site")
    ap.add_argument("--localized", default="", help="localized wide poses (default work/localize/poses.txt)")
    ap.add_argument("--noise", default="0.5,0.2", help="sigma_pos_m,sigma_rot_deg for the noisy-pose variant")
    a = ap.parse_args()
    proj = Project.load(a.site)
    P = proj.paths
    t = time.perf_counter()
    if not P.dsm.is_file():
        dsm_stage.run(proj, settings_for("export_dsm", proj))
    print(f"dsm: {time.perf_counter() - t:.1f} s")
    t = time.perf_counter()
    rig = calibrate.run(proj, settings_for("track", proj)["rig"])
    print(f"rig: {rig.info['n_pairs']} pairs, {time.perf_counter() - t:.1f} s")
    det_box = P.root / "detections_sim_box.csv"
    det_pt = P.root / "detections_sim_point.csv"
    nb = simulate_detections(P, det_box, sigma_px=1.0, mode="box")
    npt = simulate_detections(P, det_pt, sigma_px=1.0, mode="point")
    print(f"simulated detections: {nb} boxes, {npt} points")
    sp, sr = (float(v) for v in a.noise.split(","))
    noisy = noisy_poses(P.truth / "poses.txt", P.stage("track") / "poses_true_plus_noise.txt", sp, sr)
    loc = Path(a.localized) if a.localized else P.stage("localize") / "poses.txt"
    variants = [("true_point", str(P.truth / "poses.txt"), det_pt, "bottom_centre"),
                ("true_box_bottom", str(P.truth / "poses.txt"), det_box, "bottom_centre"),
                ("true_box_centre", str(P.truth / "poses.txt"), det_box, "centre"),
                (f"noisy_{sp:g}m_{sr:g}deg_box_bottom", str(noisy), det_box, "bottom_centre"),
                (f"noisy_{sp:g}m_{sr:g}deg_box_centre", str(noisy), det_box, "centre")]
    if loc.is_file():
        variants += [("localized_box_bottom", str(loc), det_box, "bottom_centre"),
                     ("localized_box_centre", str(loc), det_box, "centre")]
    else:
        print(f"(no localized poses at {loc}; localized variants skipped)")
    rows = []
    for name, poses, det, foot in variants:
        t = time.perf_counter()
        track(proj, TrackSettings(poses=poses, detections=str(det), foot_point=foot), force=True)
        dt = time.perf_counter() - t
        out_csv = P.exports / f"tracks_{name}.csv"
        shutil.copyfile(P.tracks, out_csv)
        rep = evaluate_tracking(P, tracks=out_csv, out=P.reports / f"tracking_{name}.json", label=name)
        sm = rep.get("smoothed") or {}
        rows.append((name, rep["n_targets"], rep["n_failed"], rep["median_err_h_m"], rep["median_err_3d_m"],
                     rep["recall_h"]["1m"], rep["recall_h"]["3m"], rep["recall_h"]["5m"], sm.get("median_err_h_m"),
                     rep.get("median_sigma_h_m"), dt))
    headline = "localized_box_centre" if loc.is_file() else "true_box_centre"
    evaluate_tracking(P, tracks=P.exports / f"tracks_{headline}.csv", label=headline)  # reports/tracking.json
    print(f"\n{'variant':34s} {'n':>4s} {'fail':>4s} {'med h m':>8s} {'med 3d m':>8s} {'R@1m':>5s} {'R@3m':>5s} "
          f"{'R@5m':>5s} {'smooth h':>8s} {'sigma h':>7s} {'s':>6s}")
    for r in rows:
        f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"{r[0]:34s} {r[1]:4d} {r[2]:4d} {f(r[3]):>8s} {f(r[4]):>8s} {r[5]:5.2f} {r[6]:5.2f} {r[7]:5.2f} "
              f"{f(r[8]):>8s} {f(r[9]):>7s} {r[10]:6.1f}")
    rr = evaluate_tracking(P, tracks=P.exports / f"tracks_{headline}.csv", out=P.reports / "tracking_rig_check.json",
                           plot=False)["rig"]
    if rr:
        print(f"\nrig vs truth: rotation error {rr['rotation_err_deg']:.4f} deg (true misalignment "
              f"{rr['rotation_true_deg']:.3f} deg), focal error {rr['focal_err_pct']:.3f} % (nominal was "
              f"{rr['focal_nominal_err_pct']:.1f} % off), {rr['n_pairs']} pairs")
    print("paper (UAVD4L): 'meter-level' target accuracy")


if __name__ == "__main__":
    main()
