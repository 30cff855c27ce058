"""The real-size sample against the same site at sample size (issue 48), in one command:

    python benchmarks/bench_fullsize.py --work W [--seeds 0 1] [--max-rss-gb 12] [--nice 10]

For each seed: ``gtkit sample create --preset fullsize`` and ``python -m pipelines.full``, then the same
for ``--preset small`` (the same world, flights and GPS at 1024 x 768 / 640 x 480), each measured by
:mod:`bench_scale` (wall, CPU of the process tree, its peak RSS polled each second; killed above
``--max-rss-gb``). A project already finished is only read. Then it prints bench_scale's table (every
stage's wall / CPU / peak memory / disk, each stage's working resolution beside the photos' size) and
the accuracy of both sizes against the truth (reports/summary.json), with the issue's checks: the whole
job within 3 x the small one, peak memory within 12 GB, pseudo-GT, localization and tracking no worse.
Overlay misalignment is in each photo's own full-resolution pixels; it is also given in milliradians
(px / focal), the figure that compares across sizes.

Wall seconds on a machine others use are upper bounds: the load average is printed with the table.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_scale  # noqa: E402


def _json(p: Path) -> dict:
    try:
        return json.loads(Path(p).read_text())
    except (OSError, ValueError):
        return {}


def _misalignment_mrad(root: Path) -> float | None:
    """Median overlay misalignment as an angle: each photo's px over its focal length (truth intrinsics)."""
    from gtkit.io.poses import read_intrinsics

    ali = _json(root / "reports" / "overlays" / "alignment.json").get("images") or {}
    try:
        cams = read_intrinsics(root / "truth" / "intrinsics.txt")
    except Exception:  # noqa: BLE001 - a project without truth: no figure
        return None
    v = [a["misalignment_px"] / cams[n].fx * 1e3 for n, a in ali.items()
         if n in cams and a.get("misalignment_px") is not None]
    return float(np.median(v)) if v else None


def accuracy(root: Path) -> dict:
    """The main job's figures against the truth (reports/summary.json), None where a stage did not run."""
    s = _json(root / "reports" / "summary.json")
    pg, loc, tr = s.get("pseudo_gt") or {}, s.get("localization") or {}, (s.get("tracking") or {})
    ev, rig = tr.get("evaluation") or {}, _json(root / "reports" / "tracking.json").get("rig") or {}
    return {"pseudo_gt_registered": f"{pg.get('n_registered')}/{pg.get('n_images')}" if pg else None,
            "pseudo_gt_median_m": pg.get("median_pos_err_m"), "pseudo_gt_median_deg": pg.get("median_rot_err_deg"),
            "overlay_misalignment_px": (s.get("overlays") or {}).get("median_misalignment_px"),
            "overlay_misalignment_mrad": _misalignment_mrad(root),
            "localized": f"{loc.get('n_localized')}/{loc.get('n_queries')}" if loc else None,
            "recall_1m1deg": loc.get("recall_1m1deg"), "localization_median_m": loc.get("median_pos_err_m"),
            "s_a_query": loc.get("sec_per_query"),
            "tracking_median_h_m": ev.get("median_err_h_m"), "tracking_failed": ev.get("n_failed"),
            "rig_rotation_err_deg": rig.get("rotation_err_deg"), "rig_pairs": rig.get("n_pairs")}


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def compare(full: list[Path], small: list[Path]) -> str:
    keys = list(accuracy(full[0]).keys()) if full else []
    cols = [p.name for p in full + small]
    acc = {p.name: accuracy(p) for p in full + small}
    lines = ["| figure | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    lines += [f"| {k} | " + " | ".join(_fmt(acc[c][k]) for c in cols) + " |" for k in keys]
    checks = []
    for f, s in zip(full, small):
        rf, rs = _json(f / "reports" / "scale_run.json"), _json(s / "reports" / "scale_run.json")
        wf, ws = (rf.get("full") or {}).get("wall_s"), (rs.get("full") or {}).get("wall_s")
        pk = max([r.get("peak_tree_rss_gb") or 0 for r in (rf.get("sample") or {}, rf.get("full") or {})])
        checks.append(f"{f.name} vs {s.name}: main job {_fmt(wf)} s vs {_fmt(ws)} s "
                      f"({_fmt(wf / ws if wf and ws else None)} x; issue: within 3 x), peak {pk:.2f} GB "
                      f"(issue: within 12 GB)")
    return "\n".join(lines + [""] + checks)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True, help="projects go to WORK/fullsize_SEED, WORK/small_SEED")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--max-rss-gb", type=float, default=14.0, help="kill a measured run above this")
    ap.add_argument("--nice", type=int, default=10)
    ap.add_argument("--only", choices=("fullsize", "small"), help="run one size only (the other is read if there)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    full, small = [], []
    for seed in a.seeds:
        for preset, out in (("fullsize", full), ("small", small)):
            proj = a.work / f"{preset}_{seed}"
            done = (proj / "reports" / "summary.json").is_file() and (proj / "reports" / "scale_run.json").is_file()
            if not done and a.only in (None, preset):
                bench_scale.create_and_run(preset, seed, a.work, ROOT, None, a.max_rss_gb, a.nice)
            if (proj / "project.toml").is_file():
                out.append(proj)
    projects = full + small
    text, data = bench_scale.table(projects, per_site=True)
    load = os.getloadavg()
    print(text)
    print(f"\nload average now {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (2-core machine: above 2, wall "
          "seconds are upper bounds)\n")
    print(compare(full, small))
    if a.json:
        a.json.write_text(json.dumps({**data, "accuracy": {p.name: accuracy(p) for p in projects},
                                      "load_now": load}, indent=1, default=str))


if __name__ == "__main__":
    main()
