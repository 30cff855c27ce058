"""What the sample's clicks can tell a registration at all, from the registration's own linearised BA.

    .venv/bin/python benchmarks/click_information.py --work W --seeds 33 34 35

Reads, for each seed, the site ``W/s<seed>`` and the registration ``bench_guided_clicks.py --auto``
made with no clicks (``W/gs<seed>_auto_k0``: the automatic ties alone, its ``sequence_covariance.npz``
and model). For each sequence, with the guidance's first-order model (:mod:`gtkit.sfm.guided_clicks`):

- with the automatic ties: the sequence sigma now, after the first 4 / 8 / 16 of the sample's clicks in
  its photos (file order), after the 16 the guidance takes first, and after every one of them;
- clicks alone on the sequence as a rigid whole (its shape held perfect, only where it lies left to
  the clicks: the best any estimator can do with the clicks, biased automatic ties discounted): the
  sigma of its camera centres from 8 / 16 / all of its clicks, at the sample's click noise and with
  clicks ``--scale`` x as precise;
- the same for the sample's clicks in the zoom photos, through the truth rig (analysis only: what zoom
  clicks could add at best if the registration used them; it does not).

Truth is read only for the zoom rig; the sigmas are the model's, not errors (bench_guided_clicks.py
measures those).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pycolmap  # noqa: E402

from benchmarks.bench_guided_clicks import candidates  # noqa: E402
from gtkit.camera import Camera  # noqa: E402
from gtkit.io.tiepoints import read_tiepoints  # noqa: E402
from gtkit.pose import Pose  # noqa: E402
from gtkit.sfm import guided_clicks as gc  # noqa: E402
from gtkit.sfm.geometry import triangulate_clicks  # noqa: E402


def zoom_pose(pose_w: Pose, R_zw, offset) -> Pose:
    """The zoom twin's pose from the wide photo's and the rig (``x_zoom = R_zw (x_wide - offset)``)."""
    return Pose(R_zw @ pose_w.R, R_zw @ (pose_w.t - offset))


def zoom_information(pose_w: Pose, R_zw, offset, camz: Camera, xyz, refs) -> np.ndarray:
    """``click_information`` of a click in the zoom twin of a wide photo, on the wide photo's pose: a
    perturbation (dr, dt) of the wide pose is (R_zw dr, R_zw dt) of the zoom pose."""
    pose_z = zoom_pose(pose_w, R_zw, offset)
    A = np.block([[R_zw, np.zeros((3, 3))], [np.zeros((3, 3)), R_zw]])
    return A.T @ gc.click_information(pose_z, camz, np.asarray(xyz, float), refs)


def after(st: gc.SequenceState, infos) -> float:
    cov = st.cov
    for k, L in infos:
        cov = gc.with_click(cov, k, L)
    return st.sigma(cov)


def rigid_sigma(st: gc.SequenceState, infos, scale: float = 1.0) -> float:
    """RMS camera-centre sigma of the sequence moved as a rigid whole, from the clicks ``infos`` alone
    (click noise x ``scale``). A world motion (w, v) moves photo k's pose by (dr, dt) = -R_k (w, v)."""
    G = [np.block([[-p.R, np.zeros((3, 3))], [np.zeros((3, 3)), -p.R]]) for p in st.poses]
    info = np.zeros((6, 6))
    for k, L in infos:
        A = G[k].T @ L / scale
        info += A @ A.T
    if np.linalg.matrix_rank(info) < 6:
        return float("inf")
    S = np.linalg.inv(info)
    Jc = st.centre_jacobians()
    return float(np.sqrt(np.mean([np.trace(Jc[k] @ G[k] @ S @ G[k].T @ Jc[k].T) for k in range(len(st.poses))])))


def seed_rows(work: Path, seed: int, scale: float) -> list[dict]:
    root, reg = work / f"s{seed}", work / f"gs{seed}_auto_k0"
    states = gc.load_states(reg / gc.COVARIANCE_FILE, pycolmap.Reconstruction(reg / "model"))
    refs = gc.reference_views(pycolmap.Reconstruction(root / "work" / "sfm_reference" / "model"))
    ties = read_tiepoints(root / "tiepoints.json")
    rig = json.loads((root / "truth" / "rig.json").read_text())
    R_zw, t = np.array(rig["R"]), np.array(rig["t"])
    offset = -R_zw.T @ t
    z = rig["zoom"].split()
    camz = Camera.pinhole(int(z[1]), int(z[2]), float(z[3]))
    rows = []
    for q, st in sorted(states.items()):
        poses = {n: p for n, (p, _) in refs.items()}
        cams = {n: c for n, (_, c) in refs.items()}
        poses.update(zip(st.names, st.poses))
        cams.update(zip(st.names, st.cams))
        cands = candidates([tp for tp in ties if any(o.image in st.names for o in tp.observations)], poses, cams)
        wide = [gc.candidate_information(st, c, refs) for c in cands]
        greedy = gc.greedy(st, cands, refs, 16)
        zoom = []
        for tp in ties:
            zq = [o for o in tp.observations if o.image.startswith(f"queries/{q}/") and o.image.endswith("_Z.jpg")]
            w = zq[0].image[:-len("_Z.jpg")] + "_W.jpg" if zq else None
            rr = [o for o in tp.observations if o.image in refs]
            if w not in st.names or not rr:
                continue
            k = st.names.index(w)
            pw = st.poses[k]
            tri = triangulate_clicks([cams[o.image] for o in rr] + [camz],
                                     [poses[o.image] for o in rr] + [zoom_pose(pw, R_zw, offset)],
                                     np.array([[o.x, o.y] for o in rr] + [[zq[0].x, zq[0].y]]), max_px=4.0)
            if tri.xyz is not None:
                zoom.append((k, zoom_information(pw, R_zw, offset, camz, tri.xyz, [refs[o.image] for o in rr])))
        rows.append({
            "seed": seed, "seq": q, "sigma_m": st.sigma(), "n_wide": len(wide), "n_zoom": len(zoom),
            "with_auto": {"4": after(st, wide[:4]), "8": after(st, wide[:8]), "16": after(st, wide[:16]),
                          "guided 16": greedy[-1][1] if greedy else st.sigma(), "all": after(st, wide)},
            "rigid_alone": {"8": rigid_sigma(st, wide[:8]), "16": rigid_sigma(st, wide[:16]), "all": rigid_sigma(st, wide),
                            f"all x{scale:g}": rigid_sigma(st, wide, scale), f"16 x{scale:g}": rigid_sigma(st, wide[:16], scale),
                            "zoom all": rigid_sigma(st, zoom), "wide+zoom all": rigid_sigma(st, wide + zoom)}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--scale", type=float, default=0.25, help="also: clicks this x the sample's click noise")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    rows = [r for s in a.seeds for r in seed_rows(a.work, s, a.scale)]
    print("sequence sigma (m) with the automatic ties, before and after the sample's clicks:")
    print(f"{'seed seq':10s} {'now':>7s} " + " ".join(f"{k:>9s}" for k in rows[0]["with_auto"]) + "   drop with all")
    for r in rows:
        w = r["with_auto"]
        print(f"s{r['seed']} {r['seq']:5s} {r['sigma_m']:7.4f} " + " ".join(f"{v:9.4f}" for v in w.values())
              + f"   {100 * (1 - w['all'] / r['sigma_m']):5.1f} % ({r['n_wide']} clicks)")
    print("\nclicks alone, the sequence as a rigid whole: camera-centre sigma (m)")
    keys = list(rows[0]["rigid_alone"])
    print(f"{'seed seq':10s} " + " ".join(f"{k:>13s}" for k in keys))
    for r in rows:
        print(f"s{r['seed']} {r['seq']:5s} " + " ".join(f"{v:13.3f}" for v in r["rigid_alone"].values()))
    drops = [1 - r["with_auto"]["all"] / r["sigma_m"] for r in rows]
    print(f"\n{len(rows)} sequences: every click lowers the sigma with the automatic ties by median "
          f"{100 * np.median(drops):.1f} % (max {100 * max(drops):.1f} %)")
    for k in keys:
        v = [r["rigid_alone"][k] for r in rows]
        print(f"clicks alone, rigid, {k}: median {np.median(v):.3f} m, range {min(v):.3f}-{max(v):.3f} m")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
