"""Georegistration on every kind of block (issue 45): one row per variant x seed, measured against truth.

Sample rows: a ``tiny`` sample per seed (generated once into WORK/base_<seed>), copied per variant,
the variants applied (gtkit.synth.variants), then the reference SfM + georegistration
(``gtkit.sfm.blocks.run_reference``, defaults as a user runs them). Function rows (``level-*``):
``level_block`` (8 level photos of a wall along a 50 deg arc or a line, 5 mm survey, no attitude;
SfM model exact, in an arbitrary frame) through ``georegister`` directly; ``level-half-clicks``: 6
GCPs on the wall clicked at half size, no positions (``-off``: gcp_click_scale = "off", a refusal
expected); ``level-consumer``: 11 photos 8 m from the wall, positions off by 0.5 m with no stated
accuracy (they cannot hold the tilt: a refusal expected).

Each row: the fit chosen (mode, and why, shortened), what it used, the block against truth (tilt,
heading, median horizontal / vertical camera-centre offset; shape = centres after the best
similarity, the SfM's own error), the accuracy claimed (h / v, 1 sigma), and a verdict: ``ok``
(offsets within 3 x the claim + the shape error, tilt < 2 deg), ``WRONG`` (placed, outside its
claim), or ``refused`` with its one-line cause. Then the accuracy the block itself claims (its
georegistration's ``claimed_accuracy`` record, issue 57: h / v 1 sigma and its source) and whether
it covers the truth (``gtkit.evaluate.gt_report.claim_covers``: the median horizontal / vertical
camera-centre offsets within 3 x the claim; the two ratios in sigmas).

    python benchmarks/bench_georegistration.py --seeds 0 1 2 [--variants rtk consumer facade-proxy ...] \
        [--work W] [--no-prior-ba] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# name -> the sample variants applied, in order
SAMPLE_VARIANTS = {
    "rtk+gcp": [],                                        # the sample as generated: RTK EXIF GPS, gimbal, 4 GCPs
    "rtk": ["no-gcps"],
    "no-attitude": ["no-attitude", "no-gcps"],
    "consumer": ["consumer-gps", "no-gcps"],
    "survey-geo": ["survey-geo", "no-gps", "no-gcps"],   # mm positions in geo.txt, no EXIF GPS, no attitude
    "facade-proxy": ["facade-proxy"],
    "rtk-few": ["rtk-few"],
    "gcp-only": ["no-gps"],
    "gcp-half": ["no-gps", "gcp-half"],
}
FUNCTION_VARIANTS = ("level-arc", "level-line", "level-half-clicks", "level-half-clicks-off", "level-consumer")


def _claims(geo: dict, lever: float | None = None) -> tuple[float | None, float | None]:
    """The accuracy the fit claims for the camera centres (1 sigma, h / v): the GPS quality's where
    positions placed it; for a GCP fit its GCP RMSE carried to the cameras by the lever arm
    (``lever``: cameras' distance from the GCPs' centre over the GCPs' spread; a tilt error of
    rmse / spread moves a camera by that times its distance)."""
    q = geo.get("gps_quality") or {}
    h, v = q.get("absolute_accuracy_h_m"), q.get("absolute_accuracy_v_m")
    if h is None or (geo.get("used") == "gcp"):
        h = geo.get("gcp_rmse_m") or geo.get("rmse_inliers_m")
        if h is not None and lever:
            h = h * (1.0 + lever)
        v = h
    return h, v


def lever_arm(gcps, truth: dict) -> float | None:
    """Median camera distance from the GCPs' centre over the GCPs' RMS spread (truth cameras)."""
    if not gcps:
        return None
    X = np.array([g.xyz for g in gcps])
    c = X.mean(0)
    spread = float(np.sqrt(np.mean(np.sum((X - c) ** 2, axis=1))))
    C = np.array([p.center for n, p in truth.items() if n.startswith(("reference/", "facade/"))])
    return float(np.median(np.linalg.norm(C - c, axis=1)) / max(spread, 1e-9)) if len(C) else None


def _verdict(e: dict | None, geo: dict, lever: float | None = None) -> str:
    if "error" in geo:
        return "refused"
    if e is None:
        return "?"
    h, v = _claims(geo, lever)
    shape = e.get("shape_m") or 0.0
    ok = (e["tilt_deg"] < 2.0 and h is not None and e["horizontal_m"] <= 3 * h + shape
          and e["vertical_m"] <= 3 * (v or h) + shape)
    return "ok" if ok else "WRONG"


def _short(s: str, n: int = 110) -> str:
    s = (s or "").replace("|", "/")
    return s if len(s) <= n else s[: n - 3] + "..."


def sample_row(base: Path, work: Path, seed: int, name: str, prior_ba: bool) -> dict:
    from gtkit.errors import GtkitError
    from gtkit.evaluate.poses import block_frame_errors
    from gtkit.io.poses import read_poses
    from gtkit.project import Project
    from gtkit.sfm.blocks import run_reference
    from gtkit.stages import settings_for
    from gtkit.synth.variants import apply_variant

    proj = work / f"{name}_{seed}"
    shutil.rmtree(proj, ignore_errors=True)
    shutil.copytree(base, proj, ignore=shutil.ignore_patterns("work", "reports", "exports"))
    for v in SAMPLE_VARIANTS[name]:
        apply_variant(proj, v, seed=seed)
    if not prior_ba:
        t = (proj / "project.toml").read_text()
        (proj / "project.toml").write_text(t.rstrip("\n") + "\n\n[sfm]\nhold_by_positions = false\n")
    t0 = time.time()
    try:
        r = run_reference(proj, settings_for("sfm_reference", Project.load(proj)))
    except GtkitError as ex:
        b = json.loads((proj / "work/sfm_reference/block.json").read_text()) if (proj / "work/sfm_reference/block.json").is_file() else {}
        r = b or {"georegistration": {"error": str(ex)}}
    geo = r.get("georegistration") or {"error": "no georegistration"}
    f = proj / "work/sfm_reference/poses.txt"
    e = block_frame_errors(read_poses(f), read_poses(proj / "truth/poses.txt")) if f.is_file() and "error" not in geo else None
    lever = None
    if (proj / "gcp_list.txt").is_file():
        from gtkit.io.odm import read_gcp_list

        lever = lever_arm(read_gcp_list(proj / "gcp_list.txt", Project.load(proj).frame), read_poses(proj / "truth/poses.txt"))
    return {"variant": name, "seed": seed, "seconds": round(time.time() - t0, 1), "geo": geo, "errors": e, "lever": lever,
            "n_registered": r.get("n_registered"), "n_images": r.get("n_images"),
            "held_by_positions": (r.get("held_by_positions") or {}).get("residual_median_m")}


def function_row(seed: int, name: str) -> dict:
    from gtkit.sfm.geometry import RegistrationError
    from gtkit.sfm.georegister import GeoregisterSettings, georegister
    from gtkit.evaluate.poses import block_frame_errors
    from gtkit.sfm.geometry import model_poses
    from gtkit.synth.variants import level_block, level_block_gcps

    t0 = time.time()
    if name == "level-consumer":
        rec, pos, acc, truth = level_block(seed, position_noise_m=0.5, n_photos=11, distance_m=8.0)
        acc = None
    else:
        rec, pos, acc, truth = level_block(seed, straight=name == "level-line")
    gcps = level_block_gcps(truth, seed=seed, scale=0.5) if name.startswith("level-half-clicks") else []
    try:
        if gcps:
            geo = georegister(rec, {}, gcps, GeoregisterSettings(
                use="gcp", gcp_click_scale="off" if name.endswith("-off") else "auto"))
        else:
            geo = georegister(rec, pos, [], GeoregisterSettings(), acc, {})
        e = block_frame_errors(model_poses(rec), truth)
    except RegistrationError as ex:
        geo, e = {"error": str(ex)}, None
    return {"variant": name, "seed": seed, "seconds": round(time.time() - t0, 2), "geo": geo, "errors": e,
            "n_registered": len(truth), "n_images": len(truth), "lever": lever_arm(gcps, truth)}


def _f(v, nd=3):
    return "-" if v is None else f"{v:.{nd}f}"


def claim_cells(r: dict) -> tuple[str, str, bool | None]:
    """The block's own claim (h / v, source) and whether it covers the truth (None: nothing to judge)."""
    from gtkit.evaluate.gt_report import claim_covers

    c, e = (r["geo"] or {}).get("claimed_accuracy"), r["errors"]
    if not c:
        return "-", "-", None
    claim = f"{c['h_m']:.3g} / {c['v_m']:.3g} ({c['source']}{', weak' if c.get('weak') else ''})"
    if not e:
        return claim, "-", None
    cov = claim_covers(e["horizontal_m"], e["vertical_m"], c)
    return claim, f"{'yes' if cov['covered'] else 'NO'} ({cov['ratio_h']:.2g} / {cov['ratio_v']:.2g})", cov["covered"]


def print_row(r: dict) -> None:
    geo, e = r["geo"], r["errors"] or {}
    verdict = _verdict(r["errors"], geo, r.get("lever"))
    if "error" in geo:
        fit = f"refused: {_short(geo['error'], 160)}"
    else:
        fit = f"{geo['fit'].get('mode')}: {_short(geo['fit'].get('why', ''))}"
        if geo.get("gcp_click_scale"):
            fit += f" [click scale x{geo['gcp_click_scale']['factor']:g} {'applied' if geo['gcp_click_scale'].get('applied') else 'found'}]"
    h, v = _claims(geo, r.get("lever")) if "error" not in geo else (None, None)
    print(f"| {r['variant']} | {r['seed']} | {r.get('n_registered')}/{r.get('n_images')} | {geo.get('used', '-')} | {fit} | "
          f"{_f(e.get('tilt_deg'), 3)} / {_f(e.get('heading_deg'), 3)} | {_f(e.get('horizontal_m'))} / {_f(e.get('vertical_m'))} | "
          f"{_f(e.get('shape_m'))} | {_f(h)} / {_f(v)} | {verdict} | {r['seconds']:.0f} | {' | '.join(claim_cells(r)[:2])} |",
          flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--variants", nargs="+", default=list(SAMPLE_VARIANTS) + list(FUNCTION_VARIANTS))
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--no-prior-ba", action="store_true", help="[sfm] hold_by_positions = false on every sample row")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    from gtkit.synth.generate import create_sample
    from gtkit.synth.settings import load_preset

    work = a.work or Path(tempfile.mkdtemp(prefix="bench_georeg_"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"tiny preset; seeds {a.seeds}; pose-prior BA {'off' if a.no_prior_ba else 'on (default)'}; work {work}")
    print("| variant | seed | photos | used | fit chosen: why | tilt / heading (deg) | horiz / vert (m) | shape (m) "
          "| claimed h / v (m) | verdict | s | block's own claim h / v (m, source) | claim covers truth (h / v sigmas) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for seed in a.seeds:
        base = work / f"base_{seed}"
        if any(v in SAMPLE_VARIANTS for v in a.variants) and not (base / "project.toml").is_file():
            shutil.rmtree(base, ignore_errors=True)
            create_sample(base, load_preset("tiny", seed=seed), quiet=True)
        for v in a.variants:
            r = sample_row(base, work, seed, v, not a.no_prior_ba) if v in SAMPLE_VARIANTS else function_row(seed, v)
            rows.append(r)
            print_row(r)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    n_wrong = sum(_verdict(r["errors"], r["geo"], r.get("lever")) == "WRONG" for r in rows)
    print(f"\n{len(rows)} rows: {sum(_verdict(r['errors'], r['geo'], r.get('lever')) == 'ok' for r in rows)} ok, "
          f"{sum('error' in r['geo'] for r in rows)} refused, {n_wrong} WRONG; the block's own claim covers the truth in "
          f"{sum(claim_cells(r)[2] is True for r in rows)} of {sum(claim_cells(r)[2] is not None for r in rows)} placed rows")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
