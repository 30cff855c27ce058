"""DSM coverage over the flown area, the gap fill's error and the orthophoto's seams (issue 57).

For each site: the reference SfM, a model built from the photos (the sample's own model removed),
``gtkit export dsm`` and ``gtkit export ortho`` with their defaults, then a table of what their
records say (valid share inside the flown area before / after filling, the share filled,
seam_difference before / after blending) and, on samples, the DSM against the true surface
(``truth/world.ply`` drawn on the DSM's grid; this script is evaluation code, it reads truth/).

Sites: ``tiny`` (the tiny sample as generated), ``plain`` (its ``plain-grass`` variant: a square of
grass without detail), ``plain-cut`` (the plain variant's DSM with the surface inside the square
removed before filling, as a model build that gives up on textureless ground leaves it: the fill's
error against truth over a 37 m gap), ``brighton`` (the 18 shared real photos, no truth).

    .venv/bin/python benchmarks/bench_dsm_coverage.py --work /tmp/dsmcov [--preset tiny] [--seed 0]
        [--sites tiny,plain,plain-cut,brighton]

Projects already built under --work are reused (delete them to rebuild).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
BRIGHTON = ROOT.parent / "shared" / "data" / "brighton_beach"


def gtkit(*args) -> None:
    r = subprocess.run([sys.executable, "-m", "gtkit.cli", *map(str, args)], cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"gtkit {' '.join(map(str, args))} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")


def build(site: Path) -> float:
    """Reference SfM, model, DSM and orthophoto of ``site`` (skipped when its DSM and ortho exist)."""
    t = time.perf_counter()
    if not (site / "exports" / "ortho.tif").is_file():
        gtkit("sfm", site, "--block", "reference")
        gtkit("model", "build", site)
        gtkit("export", "dsm", site)
        gtkit("export", "ortho", site)
    return time.perf_counter() - t


def sample(work: Path, preset: str, seed: int) -> Path:
    base = work / f"{preset}{seed}_generated"
    if not base.is_dir():
        gtkit("sample", "create", base, "--preset", preset, "--seed", seed, "-q")
    return base


def site_copy(work: Path, base: Path, name: str, variant: str | None) -> Path:
    site = work / name
    if not site.is_dir():
        shutil.copytree(base, site)
        if variant:
            from gtkit.synth.variants import apply_variant

            apply_variant(site, variant)
        else:
            shutil.rmtree(site / "model")       # a model built from the photos, as for the variant
    return site


def records(site: Path) -> tuple[dict, dict]:
    from gtkit.project import read_stage_record

    return (read_stage_record(site / "work" / "export_dsm").summary,
            read_stage_record(site / "work" / "export_ortho").summary)


def given_up(site: Path) -> str:
    """What the model build's texture test gave up (its record), as a note."""
    from gtkit.project import read_stage_record

    t = read_stage_record(site / "work" / "model").summary.get("textureless")
    return "texture test off / not recorded" if not t else f"{100 * t['share']:.1f} % of the depth given up as textureless"


def truth_dsm(site: Path, grid):
    from gtkit.export.surface import MeshSurface
    from gtkit.synth.truth import read_world_ply

    return MeshSurface(read_world_ply(site / "truth" / "world.ply")).rasterize(grid, False).height.astype(float)


def square_mask(site: Path, grid, inset: float = 0.0):
    info = json.loads((site / "truth" / "plain_area.json").read_text())
    (cx, cy), half = info["square_centre_xy"], info["half_side_m"] - inset
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    return (np.abs(X - cx) < half) & (np.abs(Y - cy) < half)


def err_stats(e) -> str:
    e = np.abs(np.asarray(e, float))
    e = e[np.isfinite(e)]
    return "-" if not len(e) else f"{np.median(e):.2f} / {np.percentile(e, 90):.2f}"


def flown(site: Path, grid):
    from gtkit.export.gapfill import flown_area, project_cameras
    from gtkit.project import Project

    cams = project_cameras(Project.load(site))
    return flown_area(grid, cams.centres) if cams is not None else np.zeros(grid.shape, bool)


def fill_errors(dsm, true, fl) -> str:
    """Fill error on the filled cells inside the flown area / on all filled cells."""
    return f"{err_stats((dsm.heights - true)[dsm.filled & fl])} (flown) {err_stats((dsm.heights - true)[dsm.filled])} (all)"


def row(name, d, o, fill_err="-", extra="") -> dict:
    pct = (lambda v: "-" if v is None else f"{100 * v:.1f}")
    f1 = (lambda v: "-" if v is None else f"{v:.1f}")
    return {"site": name, "flown_before": pct(d.get("valid_share_flown_before")),
            "flown_after": pct(d.get("valid_share_flown_after")), "filled": pct(d.get("filled_share")),
            "fill_err": fill_err, "seam": f"{f1(o.get('seam_difference_before'))} -> {f1(o.get('seam_difference_after'))}"
            if o else "-", "seam_within": f1(o.get("seam_difference_within")) if o else "-",
            "seam_photos": f"{f1(o.get('seam_photo_difference_before'))} -> {f1(o.get('seam_photo_difference_after'))}"
            if o else "-", "note": extra}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", default="/tmp/dsm_coverage", help="folder for the projects")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sites", default="tiny,plain,plain-cut,brighton")
    args = ap.parse_args(argv)
    from gtkit.export.dsm import Dsm
    from gtkit.export.gapfill import fill_gaps, project_cameras
    from gtkit.project import Project

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    sites = args.sites.split(",")
    rows, seconds = [], {}
    if {"tiny", "plain", "plain-cut"} & set(sites):
        base = sample(work, args.preset, args.seed)
    if "tiny" in sites:
        site = site_copy(work, base, f"{args.preset}{args.seed}", None)
        seconds["tiny"] = build(site)
        d, o = records(site)
        dsm = Dsm.for_project(site)
        true = truth_dsm(site, dsm.grid)
        rows.append(row(f"{args.preset} seed {args.seed}", d, o, fill_errors(dsm, true, flown(site, dsm.grid)),
                        f"DSM vs truth on measured cells {err_stats((dsm.heights - true)[~dsm.filled])} m; {given_up(site)}"))
    if "plain" in sites or "plain-cut" in sites:
        site = site_copy(work, base, f"{args.preset}{args.seed}_plain", "plain-grass")
        seconds["plain"] = build(site)
        d, o = records(site)
        dsm = Dsm.for_project(site)
        true = truth_dsm(site, dsm.grid)
        sq = square_mask(site, dsm.grid, inset=2.0)
        if "plain" in sites:
            rows.append(row(f"{args.preset} seed {args.seed} plain-grass", d, o,
                            fill_errors(dsm, true, flown(site, dsm.grid)),
                            f"DSM vs truth in the plain square {err_stats((dsm.heights - true)[sq])} m "
                            f"({100 * dsm.filled[sq].mean():.0f} % of it filled), elsewhere "
                            f"{err_stats((dsm.heights - true)[~sq & ~dsm.filled])} m; {given_up(site)}"))
        if "plain-cut" in sites:
            cut = square_mask(site, dsm.grid)
            h = np.where(cut | dsm.filled, np.nan, dsm.heights).astype(np.float32)
            gf = fill_gaps(h, dsm.grid, project_cameras(Project.load(site)))
            e = (gf.height - true)[cut]
            ground = cut & (true < np.median(true[cut]) + 2.0)       # not the trees inside the cut
            rows.append(row(f"{args.preset} seed {args.seed} plain-grass, square cut", gf.summary, None, err_stats(e),
                            f"{cut.sum()} cells cut ({2 * json.loads((site / 'truth' / 'plain_area.json').read_text())['half_side_m']:.0f} m square); "
                            f"ground cells only (the trees in it cannot be known): {err_stats((gf.height - true)[ground])} m"))
    if "brighton" in sites and (BRIGHTON / "images").is_dir():
        site = work / "brighton"
        if not site.is_dir():
            ref = work / "brighton_photos"
            ref.mkdir(exist_ok=True)
            for p in sorted((BRIGHTON / "images").glob("*.JPG")):
                if not (ref / p.name).exists():
                    (ref / p.name).symlink_to(p)
            gtkit("init", site, "--reference", ref)
        seconds["brighton"] = build(site)
        d, o = records(site)
        rows.append(row("Brighton (18 real nadir photos)", d, o, extra=given_up(site)))
    cols = [("site", "site"), ("flown_before", "valid in flown area before %"), ("flown_after", "after %"),
            ("filled", "filled % of DSM"), ("fill_err", "fill error vs truth, median / p90 m (filled cells in the flown area; all filled cells)"),
            ("seam", "seam_difference before -> after"), ("seam_within", "within one photo"),
            ("seam_photos", "photos at seams before -> after"), ("note", "note")]
    print("| " + " | ".join(c[1] for c in cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(str(r[c[0]]) for c in cols) + " |")
    print("\nbuild seconds (sfm + model + dsm + ortho; 0 = reused): " + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()))
    (work / "bench_dsm_coverage.json").write_text(json.dumps({"rows": rows, "seconds": seconds}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
