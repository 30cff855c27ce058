"""Does the pseudo-GT's stated sigma hold on real photos? (issue 48) The held-out protocol of
``shared/tools/heldout_eval.py`` with each photo's stated sigma and the yardstick's own noise.

ALL is an SfM of every photo (the yardstick: ``gtkit sfm ALL --block reference``), each HELD project
the same photos with some held out as a query sequence and registered by ``gtkit run`` (or ``gtkit
register``). The two blocks are tied by a similarity on the centres of the reference photos both
hold (CRS coordinates, so origins and GPS-grade georeferencing drop out). The yardstick's noise is
measured, not assumed: the misfit of that similarity on the shared photos (their median and RMS
distance); a held-out photo counts as held where its error is within
``2 sqrt(sigma^2 + yardstick^2)`` (sigma: the stated position sigma, ``sqrt(trace C)`` of the
camera centre, ``registration.json``), with the yardstick's median misfit as the issue states it
(and with its RMS, the 1-sigma radius in the same terms as sigma).

    python benchmarks/bench_sigma_real.py ALL HELD_A HELD_B ...   [--json out.json]
    python benchmarks/bench_sigma_real.py --truth SITE ...        # a sample with truth (no yardstick)

Prints one line per held-out photo (error, stated sigma, the sigma before issue 48 -- the BA's, plus
the systematic swing where it applies, from the record's ``sigma_terms`` -- the yardstick's noise,
held or not) and one summary line per project. ``--truth``: sample sites, judged as the GT report
does (absolute, against ``truth/poses.txt``; the yardstick's noise is 0).
"""
from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from gtkit.sfm.similarity import umeyama as similarity_umeyama  # noqa: E402


def _centres(proj: Path, rel: str) -> dict:
    """name (file name) -> (world-to-camera R, centre in CRS coordinates)."""
    from gtkit.io.poses import read_poses

    f = proj / rel
    if not f.is_file():
        return {}
    origin = np.array(tomllib.loads((proj / "project.toml").read_text())["crs"].get("origin", [0, 0, 0]), float)
    return {n.split("/")[-1]: (p.R, p.center + origin) for n, p in read_poses(f).items()}


def _umeyama(src: np.ndarray, dst: np.ndarray):
    """Least-squares similarity dst ~ c R src + t (gtkit's Umeyama): (c, R, t)."""
    S = similarity_umeyama(src, dst)
    return S.scale, S.R, S.t


def _images(held: Path) -> dict:
    reg = json.loads((held / "work" / "register" / "registration.json").read_text())
    return {n.split("/")[-1]: v for n, v in reg.get("images", {}).items()}


def judge(all_project: Path, held: Path) -> dict:
    """Per held-out photo: error vs the yardstick, stated sigma; the yardstick's misfit."""
    ya = _centres(all_project, "work/sfm_reference/poses.txt")
    rb = _centres(held, "work/sfm_reference/poses.txt")
    pg = _centres(held, "work/register/poses.txt")
    info = _images(held)
    queries = sorted(p.name for p in (held / "images" / "queries").rglob("*")
                     if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif"))
    common = sorted(set(ya) & set(rb))
    c, R, t = _umeyama(np.array([ya[n][1] for n in common]), np.array([rb[n][1] for n in common]))
    misfit = np.array([np.linalg.norm(c * R @ ya[n][1] + t - rb[n][1]) for n in common])
    rows = []
    for q in queries:
        if q not in ya:
            continue   # the yardstick could not place it
        row = {"photo": q, "error_m": None, "sigma_m": None, "sigma_ba_m": None}
        if q in pg:
            e = pg[q][1] - (c * R @ ya[q][1] + t)
            row["error_m"] = float(np.linalg.norm(e))
            row["error_cam_m"] = (pg[q][0] @ e).tolist()     # in the photo's camera axes (x, y, z=view)
            row["sigma_m"] = info.get(q, {}).get("sigma_pos_m")
            row["sigma_ba_m"] = info.get(q, {}).get("sigma_pos_ba_m")
            row["terms"] = info.get(q, {}).get("sigma_terms")
        rows.append(row)
    return {"held": str(held), "n_common": len(common), "yardstick_median_m": float(np.median(misfit)),
            "yardstick_rms_m": float(np.sqrt(np.mean(misfit ** 2))), "rows": rows}


def judge_truth(site: Path) -> dict:
    """A sample site: the pseudo-GT against its truth, absolute (as the GT report judges it); the
    yardstick is the truth (no noise)."""
    from gtkit.io.poses import read_poses

    truth = read_poses(site / "truth" / "poses.txt")
    est = read_poses(site / "work" / "register" / "poses.txt")
    reg = json.loads((site / "work" / "register" / "registration.json").read_text())["images"]
    rows = []
    for n in sorted(n for n in truth if n in reg):   # the photos the stage registers (the zoom rig aside)
        row = {"photo": n, "error_m": None, "sigma_m": None, "sigma_ba_m": None}
        if n in est:
            e = est[n].center - truth[n].center
            row.update(error_m=float(np.linalg.norm(e)), error_cam_m=(est[n].R @ e).tolist(),
                       sigma_m=reg.get(n, {}).get("sigma_pos_m"), sigma_ba_m=reg.get(n, {}).get("sigma_pos_ba_m"),
                       terms=reg.get(n, {}).get("sigma_terms"))
        rows.append(row)
    return {"held": str(site), "n_common": 0, "yardstick_median_m": 0.0, "yardstick_rms_m": 0.0,
            "rows": rows}


def sigma_before(row: dict) -> float | None:
    """The sigma the stage stated before issue 48: the BA's, plus the systematic swing where it applied."""
    t = row.get("terms") or {}
    return None if t.get("ba_m") is None else float(np.hypot(t["ba_m"], t.get("swing_m") or 0.0))


def shares(res: dict) -> dict:
    """Within-2-sigma shares over the registered photos (yardstick noise as median and as RMS), with
    the stated sigma and with the sigma before issue 48."""
    ok = [r for r in res["rows"] if r["error_m"] is not None and r["sigma_m"] is not None]
    out = {"n": len(ok), "of": len(res["rows"])}
    for k in ("median", "rms"):
        y = res[f"yardstick_{k}_m"]
        out[f"within_{k}"] = (float(np.mean([r["error_m"] <= 2 * np.hypot(r["sigma_m"], y) for r in ok]))
                              if ok else None)
        before = [r for r in ok if sigma_before(r) is not None]
        out[f"within_{k}_before"] = (float(np.mean([r["error_m"] <= 2 * np.hypot(sigma_before(r), y)
                                                    for r in before])) if before else None)
    out["within_alone"] = float(np.mean([r["error_m"] <= 2 * r["sigma_m"] for r in ok])) if ok else None
    out["within_alone_before"] = (float(np.mean([r["error_m"] <= 2 * sigma_before(r) for r in ok]))
                                  if ok and all(sigma_before(r) is not None for r in ok) else None)
    out["median_sigma_before_m"] = (float(np.median([sigma_before(r) for r in ok if sigma_before(r) is not None]))
                                    if ok and all(sigma_before(r) is not None for r in ok) else None)
    out["median_error_m"] = float(np.median([r["error_m"] for r in ok])) if ok else None
    out["median_sigma_m"] = float(np.median([r["sigma_m"] for r in ok])) if ok else None
    return out


def main(argv=None) -> int:
    from gtkit.sfm.register.real_photo_terms import variance_scale

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("projects", nargs="+", help="ALL then HELD projects (or sites with --truth)")
    ap.add_argument("--truth", action="store_true", help="sample sites judged against their truth")
    ap.add_argument("--json", help="write every row here")
    a = ap.parse_args(argv)
    results = ([judge_truth(Path(p)) for p in a.projects] if a.truth
               else [judge(Path(a.projects[0]), Path(p)) for p in a.projects[1:]])
    for res in results:
        s = shares(res)
        res["summary"] = s
        print(f"{res['held']}: yardstick misfit over {res['n_common']} shared photos median "
              f"{res['yardstick_median_m']:.3f} m, RMS {res['yardstick_rms_m']:.3f} m")
        for r in res["rows"]:
            if r["error_m"] is None:
                print(f"  {r['photo']:28s} not registered")
                continue
            sig = r["sigma_m"] if r["sigma_m"] is not None else float("nan")
            lim = 2 * np.hypot(sig, res["yardstick_median_m"])
            t = r.get("terms") or {}
            print(f"  {r['photo']:28s} error {r['error_m']:.3f} m  sigma {sig:.3f} m (before "
                  f"{sigma_before(r) or float('nan'):.3f}; BA {t.get('ba_m') or float('nan'):.3f} x factor "
                  f"{variance_scale(t.get('feature_px') or 1.0, t.get('residual_factor')):.2f}, reference "
                  f"{t.get('reference_m') or 0.0:.3f}, swing "
                  f"{t.get('swing_m') or 0.0:.3f})  limit {lim:.3f} m  {'held' if r['error_m'] <= lim else 'OUT'}"
                  f"  cam-axis error {np.round(r['error_cam_m'], 3).tolist()}")
        f = (lambda v: "-" if v is None else f"{v:.3f}")
        print(f"  summary: {s['n']}/{s['of']} registered, median error {f(s['median_error_m'])} m, median sigma "
              f"{f(s['median_sigma_m'])} m (before {f(s['median_sigma_before_m'])} m); within 2 sqrt(sigma^2+yard^2): "
              f"{f(s['within_median'])} (before {f(s['within_median_before'])}) with the yardstick's median misfit, "
              f"{f(s['within_rms'])} (before {f(s['within_rms_before'])}) with its RMS; within 2 sigma alone "
              f"{f(s['within_alone'])} (before {f(s['within_alone_before'])})")
    if len(results) > 1:
        sm = [r["summary"] for r in results if r["summary"]["n"] and r["summary"]["within_median_before"] is not None]
        n = sum(x["n"] for x in sm)
        pooled = {k: sum(x[k] * x["n"] for x in sm if x[k] is not None) / n
                  for k in ("within_median", "within_median_before", "within_rms", "within_rms_before", "within_alone",
                            "within_alone_before")} if n else {}
        print(f"pooled over {len(sm)} projects, {n} photos: within 2 sqrt(sigma^2+yard^2) "
              + ", ".join(f"{k} {v:.3f}" for k, v in pooled.items())
              + f"; per project within_median: min {min(x['within_median'] for x in sm):.3f}, median "
              f"{float(np.median([x['within_median'] for x in sm])):.3f} (before: min "
              f"{min(x['within_median_before'] for x in sm):.3f}, median "
              f"{float(np.median([x['within_median_before'] for x in sm])):.3f})")
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
