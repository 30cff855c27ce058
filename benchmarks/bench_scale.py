"""The scale table: every stage's wall time, CPU time, peak memory and disk, per site size, read
from finished projects, and how each grows with the site (fitted log-log exponent).

Each stage writes its cost into its record (``work/<stage>/stage.json`` -> ``summary.cost``:
wall_s, cpu_s (this process + its reaped children), peak_rss_gb (this process since the stage
began), children_peak_rss_gb (largest reaped child), disk_mb of its outputs); see
:func:`gtkit.project.mark_stage_done`. Older records lack CPU and memory: those cells show "-",
and the wall time then comes from what the stage wrote itself (block.json seconds, render-db
seconds, localize wall_s).

    python benchmarks/bench_scale.py PROJECT [PROJECT ...]            # read finished projects
    python benchmarks/bench_scale.py --preset small --seed 6 --work W  # create + run the main job, then read
    python benchmarks/bench_scale.py --preset large --seed 0 --work W --stop-after sample

With ``--preset`` the sample creation and the main job (``python -m pipelines.full``) run as
measured child processes (``nice``; the process tree's RSS polled every second, killed above
``--max-rss-gb``), their cost kept in ``PROJECT/reports/scale_run.json``. Projects are grouped by
preset (the size); with two sizes or more each stage gets its exponent: log(cost) against
log(photos | views | area), least squares over the sizes' medians. The load average is printed:
wall seconds on a loaded machine are upper bounds; CPU seconds are the figure to compare.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gtkit.project import disk_bytes  # noqa: E402  (the same measure as the stage records)

# stage -> (record folder(s) under work/, size driver for the exponent)
STAGES = [
    ("sample", None, "area_km2"),
    ("sfm_reference", "sfm_reference", "photos"),
    ("  features", None, "photos"),
    ("  matching", None, "photos"),
    ("  mapping", None, "photos"),
    ("sfm_queries", "sfm_queries/*", "queries"),
    ("register", "register", "queries"),
    ("exports", "export_*", "area_km2"),      # DSM, orthophoto, mesh, coordinates
    ("overlays", None, "queries"),            # reports/overlays/alignment.json
    ("model", "model", "photos"),
    ("render_db", "render_db", "views"),
    ("localize", "localize", "views"),
    ("  db features", None, "views"),
    ("track", "track", "queries"),
    ("  rig", "rig", "queries"),              # the zoom rig's calibration (its record's cost since issue 48)
    ("main job (one process)", None, "area_km2"),   # reports/scale_run.json: pipelines.full measured whole
    ("sample + main job", None, "area_km2"),
]


# --- measuring a child process -------------------------------------------------------------

def _tree_rss(pid: int) -> int:
    """Bytes resident in ``pid`` and all its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    page = os.sysconf("SC_PAGE_SIZE")
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                parts = f.read().rsplit(")", 1)[1].split()
            children.setdefault(int(parts[1]), []).append(int(d))
            rss[int(d)] = int(parts[21]) * page
        except (OSError, IndexError, ValueError):
            continue
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        todo += children.get(p, [])
    return total


def _nice_autogroup(pid: int, nice: int) -> None:
    """A new session is a new scheduler autogroup on Linux (CONFIG_SCHED_AUTOGROUP), and autogroups
    share the CPU equally whatever their processes' nice values: a niced run in its own session took
    about a third of this 2-core machine from the jobs beside it. The autogroup's own nice value
    restores the intent (best effort: no such file without autogroups)."""
    try:
        Path(f"/proc/{pid}/autogroup").write_text(str(nice))
    except OSError:
        pass


def run_measured(cmd: list[str], log_path: Path, env: dict | None = None, cwd: Path | None = None,
                 max_rss_gb: float = 6.0, nice: int = 10) -> dict:
    """Run ``cmd`` (niced) and measure it: wall, CPU of the whole tree, peak RSS of the tree
    (sum over processes, polled each second), load average before and after. Killed (process
    group) when the tree's RSS exceeds ``max_rss_gb``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load0 = os.getloadavg()
    t0 = time.time()
    with open(log_path, "w") as log:
        p = subprocess.Popen(["nice", "-n", str(nice), *cmd], stdout=log, stderr=subprocess.STDOUT, env=env,
                             cwd=cwd, start_new_session=True)
        _nice_autogroup(p.pid, nice)
        peak, killed = 0, False
        while p.poll() is None:
            peak = max(peak, _tree_rss(p.pid))
            if peak > max_rss_gb * 2**30 and not killed:
                os.killpg(p.pid, signal.SIGKILL)
                killed = True
            time.sleep(1.0)
    wall = time.time() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"cmd": " ".join(cmd), "rc": p.returncode, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
            "peak_tree_rss_gb": round(peak / 2**30, 2), "killed_over_rss_gb": max_rss_gb if killed else None,
            "load_before": [round(v, 2) for v in load0], "load_after": [round(v, 2) for v in os.getloadavg()],
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}


def create_and_run(preset: str, seed: int, work: Path, code: Path, stop_after: str | None,
                   max_rss_gb: float, nice: int = 10) -> Path:
    proj = work / f"{preset}_{seed}"
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(code), GTKIT_PROGRESS="0")
    runs = {}
    rec = proj / "reports" / "scale_run.json"
    if rec.is_file():
        runs = json.loads(rec.read_text())
    if not (proj / "project.toml").is_file():
        r = run_measured([sys.executable, "-m", "gtkit.cli", "sample", "create", str(proj), "--preset", preset,
                          "--seed", str(seed), "-q"], work / f"{preset}_{seed}.sample.log", env, code, max_rss_gb, nice)
        r["disk_mb"] = round(disk_bytes(proj) / 2**20, 1)
        runs["sample"] = r
        print(f"sample {preset} seed {seed}: {r}", flush=True)
        if proj.is_dir():
            (proj / "reports").mkdir(exist_ok=True)
            rec.write_text(json.dumps(runs, indent=1))
        if r["rc"]:
            raise SystemExit(f"sample creation failed (rc {r['rc']}), see {work / f'{preset}_{seed}.sample.log'}")
    if stop_after != "sample":
        r = run_measured([sys.executable, "-m", "pipelines.full", str(proj)], work / f"{preset}_{seed}.full.log",
                         env, code, max_rss_gb, nice)
        runs["full"] = r
        print(f"main job {preset} seed {seed}: {r}", flush=True)
        rec.parent.mkdir(parents=True, exist_ok=True)
        rec.write_text(json.dumps(runs, indent=1))
    return proj


# --- reading finished projects --------------------------------------------------------------

def _json(p: Path) -> dict:
    try:
        return json.loads(Path(p).read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def site_info(root: Path) -> dict:
    cfg = {}
    try:
        import tomllib

        cfg = tomllib.loads((root / "project.toml").read_text())
    except (OSError, ValueError):
        pass
    sample = cfg.get("sample", {})
    world = _json(root / "truth" / "world.json")
    size_m = ((world.get("settings") or {}).get("site") or {}).get("size_m")
    area = size_m ** 2 / 1e6 if size_m else None
    ref = root / "images" / "reference"
    photos = sum(1 for p in ref.rglob("*") if p.is_file()) if ref.is_dir() else None
    qdir = root / "images" / "queries"
    queries = sum(1 for p in qdir.rglob("*_W.*")) if qdir.is_dir() else None
    rdb = _json(root / "work" / "render_db" / "stage.json").get("summary", {})
    return {"project": str(root), "preset": sample.get("preset", "?"), "seed": sample.get("seed"),
            "area_km2": area, "photos": photos, "queries": queries, "views": rdb.get("n_views"),
            "views_rendered": rdb.get("n_on_disk", rdb.get("n_views")), "views_kept": rdb.get("n_kept")}


def _cost_of(summary: dict) -> dict:
    c = summary.get("cost") or {}
    peak = [v for v in (c.get("peak_rss_gb"), c.get("children_peak_rss_gb")) if v is not None]
    return {"wall_s": c.get("wall_s"), "cpu_s": c.get("cpu_s"), "peak_gb": max(peak) if peak else None,
            "disk_mb": c.get("disk_mb")}


def stage_costs(root: Path) -> dict[str, dict]:
    """{stage: {wall_s, cpu_s, peak_gb, disk_mb, old}} from the records (see module doc)."""
    work = root / "work"
    out: dict[str, dict] = {}
    runs = _json(root / "reports" / "scale_run.json")
    if "sample" in runs:
        s = runs["sample"]
        out["sample"] = {"wall_s": s["wall_s"], "cpu_s": s["cpu_s"], "peak_gb": s["peak_tree_rss_gb"],
                         "disk_mb": s.get("disk_mb"), "old": False}
    else:
        secs = (_json(root / "reports" / "summary.json").get("seconds") or {}).get("sample")
        out["sample"] = {"wall_s": secs, "cpu_s": None, "peak_gb": None, "old": True,
                         "disk_mb": round(disk_bytes(root / "images", root / "model", root / "truth") / 2**20, 1)}
    for name, folder, _drv in STAGES:
        if folder is None:
            continue
        dirs = sorted(work.glob(folder)) if "*" in folder else [work / folder]
        recs = [(d, _json(d / "stage.json")) for d in dirs if (d / "stage.json").is_file()]
        if not recs:
            continue
        costs = [_cost_of(r.get("summary", {})) for _d, r in recs]
        old = any(c["wall_s"] is None for c in costs)
        row = {"old": old}
        for k in ("wall_s", "cpu_s", "disk_mb"):
            vals = [c[k] for c in costs]
            row[k] = round(sum(vals), 1) if all(v is not None for v in vals) else None
        peaks = [c["peak_gb"] for c in costs]
        row["peak_gb"] = max(peaks) if all(v is not None for v in peaks) else None
        if row["disk_mb"] is None:  # measured now: the outputs are still there
            extra = [work / "localize_db"] if name == "localize" else []
            row["disk_mb"] = round(disk_bytes(*[d for d, _r in recs], *extra) / 2**20, 1)
        if row["wall_s"] is None:  # older records: what the stage timed itself
            row["wall_s"] = _old_wall(name, [r for _d, r in recs], [d for d, _r in recs])
        if row["peak_gb"] is None and name == "model":  # the model build measures its own peak
            pk = [max((r.get("summary", {}).get("peak_memory_gb") or {}).values(), default=None) for _d, r in recs]
            row["peak_gb"] = max(pk) if all(v is not None for v in pk) else None
        out[name] = row
    blk = _json(work / "sfm_reference" / "block.json")
    steps = blk.get("seconds") or {}
    cpu_steps = blk.get("cpu_seconds") or {}
    for k in ("features", "matching", "mapping"):
        if k in steps:
            out[f"  {k}"] = {"wall_s": round(steps[k], 1), "cpu_s": cpu_steps.get(k), "peak_gb": None,
                             "disk_mb": None, "old": False}
    ali = _json(root / "reports" / "overlays" / "alignment.json")
    secs = _json(root / "reports" / "summary.json").get("seconds") or {}
    if ali.get("cost"):
        out["overlays"] = {**_cost_of(ali), "old": False}
    elif secs.get("overlays") is not None:  # older overlays: the main job's wall time only
        out["overlays"] = {"wall_s": secs["overlays"], "cpu_s": None, "peak_gb": None, "old": True,
                           "disk_mb": round(disk_bytes(root / "reports" / "overlays") / 2**20, 1)}
    if "full" in runs:
        f = runs["full"]
        disk_mb = round(disk_bytes(root) / 2**20, 1)   # the whole project (one walk: it can hold 10+ GB)
        out["main job (one process)"] = {"wall_s": f["wall_s"], "cpu_s": f["cpu_s"], "peak_gb": f["peak_tree_rss_gb"],
                                         "disk_mb": disk_mb, "old": False}
        if "sample" in runs:
            s = runs["sample"]
            out["sample + main job"] = {"wall_s": round(s["wall_s"] + f["wall_s"], 1),
                                        "cpu_s": round(s["cpu_s"] + f["cpu_s"], 1),
                                        "peak_gb": max(s["peak_tree_rss_gb"], f["peak_tree_rss_gb"]),
                                        "disk_mb": disk_mb, "old": False}
    loc = _json(work / "localize" / "stage.json").get("summary", {})
    if loc.get("db_features_s") is not None and loc.get("db_features_views"):
        n = loc["db_features_views"]
        cpu = loc.get("db_features_cpu_s")   # records since issue 16: CPU of the extraction (workers' chunks)
        out["  db features"] = {"wall_s": loc["db_features_s"], "cpu_s": cpu, "peak_gb": None, "disk_mb": None,
                                "old": False, "views": n, "per_view_s": loc["db_features_s"] / n,
                                "cpu_per_view_s": None if cpu is None else cpu / n,
                                "global_wall_s": loc.get("db_global_s"), "global_cpu_s": loc.get("db_global_cpu_s"),
                                "kb_per_view": loc.get("db_features_kb_per_view"),
                                "load_avg_1m": (loc.get("cost") or {}).get("load_avg_1m")}
    return out


def _old_wall(name: str, recs: list[dict], dirs: list[Path]) -> float | None:
    total = 0.0
    for r, d in zip(recs, dirs):
        s = r.get("summary", {})
        if name in ("sfm_reference", "sfm_queries"):
            v = sum((_json(d / "block.json").get("seconds") or {}).values()) or None
        elif name == "render_db":
            v = s.get("seconds")
        elif name == "localize":  # with the database features, as the new records count it
            v = _json(d / "status.json").get("total_s") or s.get("wall_s")
        elif name == "model":
            v = sum((s.get("seconds") or {}).values()) or None
        else:
            v = None
        if v is None:
            return None
        total += v
    return round(total, 1)


def _photo_sizes(root: Path) -> dict[str, tuple[int, int]]:
    """(width, height) of the first reference, wide and zoom photo (their JPEG headers)."""
    from PIL import Image

    out = {}
    for kind, pattern in (("reference", "reference/**/*.jpg"), ("wide", "queries/**/*_W.jpg"),
                          ("zoom", "queries/**/*_Z.jpg")):
        first = next(iter(sorted((root / "images").glob(pattern))), None)
        if first is not None:
            with Image.open(first) as im:
                out[kind] = im.size
    return out


def working_resolutions(root: Path) -> list[tuple[str, str, str]]:
    """(stage, what it works on, long side it works at) from the stage records (issue 48): each stage's
    working resolution beside the photos' own size."""
    work = root / "work"
    sizes = _photo_sizes(root)
    side = {k: max(v) for k, v in sizes.items()}

    def settings(folder):
        return (_json(work / folder / "stage.json").get("settings") or {}) if folder else {}

    def at(value, photo):
        if value is None:
            return "-"
        full = side.get(photo)
        if not full or not value or value >= full:
            return f"full ({full or '?'} px)"
        return f"{value} px of {full} ({value / full:.2f})"
    rows = []
    sfm = settings("sfm_reference").get("features", {}).get("max_image_size")
    rows.append(("sfm_reference", "SIFT of the reference photos", at(sfm, "reference")))
    qdirs = sorted(work.glob("sfm_queries/*/stage.json"))
    q = (_json(qdirs[0]).get("settings") or {}).get("features", {}).get("max_image_size") if qdirs else None
    rows.append(("sfm_queries", "SIFT of the wide photos", at(q, "wide")))
    m = settings("model").get("max_image_size")
    rows.append(("model", "depth maps and texture views", at(m, "reference") if m else "- (model delivered)"))
    ali = _json(root / "reports" / "overlays" / "alignment.json")
    ov = (ali.get("settings") or {}).get("max_side")
    meas = (ali.get("working_resolution") or {}).get("measure_side")
    rows.append(("overlays", "render + photo (PNG) / the measures",
                 f"{at(ov, 'reference')} / {meas or 768} px"))
    rd = settings("render_db")
    rows.append(("render_db", "database views (rendered)",
                 f"{rd.get('width')} x {rd.get('height')}" if rd else "-"))
    loc = settings("localize").get("features", {}).get("max_side")
    rows.append(("localize", "query features (wide)", at(loc, "wide")))
    rig = settings("rig")
    rows.append(("track (rig)", "wide photo for the zoom match",
                 at(rig.get("wide_max_side"), "wide") if rig and "wide_max_side" in rig else
                 ("full (no working size)" if rig else "-")))
    return rows


def working_resolution_lines(projects: list[Path]) -> str:
    out = []
    for p in projects:
        rows = working_resolutions(p)
        sizes = ", ".join(f"{k} {w} x {h}" for k, (w, h) in _photo_sizes(p).items())
        out += ["", f"working resolution, {p.name} (photos: {sizes})", "",
                "| stage | works on | working size (long side) |", "|---|---|---|"]
        out += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(out)


# --- the table ------------------------------------------------------------------------------

def fit_exponent(x: list[float], y: list[float]) -> float | None:
    """Least-squares slope of log y against log x (None with fewer than two distinct x)."""
    pts = [(a, b) for a, b in zip(x, y) if a and b and a > 0 and b > 0]
    if len({a for a, _ in pts}) < 2:
        return None
    lx, ly = np.log([a for a, _ in pts]), np.log([b for _, b in pts])
    return float(np.polyfit(lx, ly, 1)[0])


def _f(v, fmt="{:.0f}"):
    return "-" if v is None else fmt.format(v)


def _merge(sites: list[dict], costs: list[dict]) -> tuple[list[dict], list[dict]]:
    """Projects of the same preset and seed are one site (e.g. a pristine sample beside a copy that
    ran some stages): each stage from the first project that has it with a wall time; the sample
    row from the one with the most disk (a complete sample)."""
    out_s, out_c, index = [], [], {}
    for s, c in zip(sites, costs):
        k = (s["preset"], s["seed"])
        if k not in index:
            index[k] = len(out_s)
            out_s.append(dict(s))
            out_c.append(dict(c))
            continue
        ms, mc = out_s[index[k]], out_c[index[k]]
        for key, v in s.items():
            if ms.get(key) is None:
                ms[key] = v
        for stage, row in c.items():
            have = mc.get(stage)
            if stage == "sample" and have and row.get("disk_mb") and (have.get("disk_mb") or 0) < row["disk_mb"] \
                    and have.get("cpu_s") is None:
                mc[stage] = row
            elif have is None or (have.get("wall_s") is None and row.get("wall_s") is not None):
                mc[stage] = row
    return out_s, out_c


def _cell(rows: list[dict]) -> str:
    """Median over the seeds of wall / CPU s, peak GB, disk GB (n seeds with the figure)."""
    def med(key):
        v = [r[key] for r in rows if r.get(key) is not None]
        return (float(np.median(v)), len(v)) if v else (None, 0)
    (w, nw), (c, nc), (pk, _), (d, _) = med("wall_s"), med("cpu_s"), med("peak_gb"), med("disk_mb")
    old = "*" if any(r.get("old") for r in rows) else ""
    n = f" (n={max(nw, nc)})" if max(nw, nc) > 1 else ""
    return (f"{_f(w)} / {_f(c)} s, {_f(pk, '{:.2f}')} GB, {_f(d if d is None else d / 1024, '{:.2f}')} GB"
            f"{old}{n}")


def table(projects: list[Path], per_site: bool = False) -> tuple[str, dict]:
    sites, costs = _merge([site_info(p) for p in projects], [stage_costs(p) for p in projects])
    lines = ["| site | area km² | reference photos | query photos (wide) | database views planned / rendered / kept |",
             "|---|---|---|---|---|"]
    for s in sites:
        lines.append(f"| {s['preset']} seed {s['seed']} | {_f(s['area_km2'], '{:.3g}')} | {_f(s['photos'])} | "
                     f"{_f(s['queries'])} | {_f(s['views'])} / {_f(s['views_rendered'])} / {_f(s['views_kept'])} |")
    by_preset: dict[str, list[int]] = {}
    for i, s in enumerate(sites):
        by_preset.setdefault(s["preset"], []).append(i)
    groups = ({f"{s['preset']} {s['seed']}": [i] for i, s in enumerate(sites)} if per_site else
              {f"{p} (seeds {', '.join(str(sites[i]['seed']) for i in idx)})": idx for p, idx in by_preset.items()})
    lines += ["", "| stage | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups)]
    for name, _folder, _drv in STAGES:
        cells = []
        for idx in groups.values():
            rows = [costs[i][name] for i in idx if name in costs[i]]
            cells.append(_cell(rows) if rows else "")
        label = "↳ " + name.strip() if name.startswith("  ") else name
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    fits = {}
    if len(by_preset) >= 2:
        lines += ["", "| stage | grows with | exponent wall | exponent CPU | exponent peak memory | exponent disk |",
                  "|---|---|---|---|---|---|"]
        for name, _folder, drv in STAGES:
            row = {}
            for key in ("wall_s", "cpu_s", "peak_gb", "disk_mb"):
                xs, ys = [], []
                for idx in by_preset.values():
                    x = [sites[i][drv] for i in idx if sites[i][drv]]
                    y = [costs[i][name][key] for i in idx if costs[i].get(name) and costs[i][name].get(key)]
                    if x and y:
                        xs.append(float(np.median(x)))
                        ys.append(float(np.median(y)))
                row[key] = fit_exponent(xs, ys)
            fits[name.strip()] = {"driver": drv, **row}
            lines.append(f"| {name.strip()} | {drv} | " + " | ".join(_f(row[k], "{:.2f}") for k in
                                                                    ("wall_s", "cpu_s", "peak_gb", "disk_mb")) + " |")
    lines += ["", db_feature_lines(sites, costs)]
    lines += [working_resolution_lines(projects)]
    return "\n".join(lines), {"sites": sites, "costs": costs, "exponents": fits,
                              "working_resolution": {str(p): working_resolutions(p) for p in projects}}


def db_feature_lines(sites: list[dict], costs: list[dict]) -> str:
    """Database features a view, per site: CPU and wall seconds (the issue-16 target is 0.1 s a view
    on an idle 2-core machine), the VLAD codebook + global descriptors, and the disk a view."""
    rows = ["| site | db views | features CPU s a view | features wall s a view | VLAD CPU / wall s | kB a view | "
            "load (1 min) |", "|---|---|---|---|---|---|---|"]
    for s, c in zip(sites, costs):
        r = c.get("  db features")
        if not r:
            continue
        load = r.get("load_avg_1m")
        rows.append(f"| {s['preset']} {s['seed']} | {r['views']} | {_f(r.get('cpu_per_view_s'), '{:.3f}')} | "
                    f"{_f(r['per_view_s'], '{:.3f}')} | {_f(r.get('global_cpu_s'), '{:.1f}')} / "
                    f"{_f(r.get('global_wall_s'), '{:.1f}')} | {_f(r.get('kb_per_view'))} | "
                    f"{'-' if not load else ' -> '.join(f'{x:.1f}' for x in load)} |")
    return "\n".join(rows) if len(rows) > 2 else ""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("projects", nargs="*", type=Path, help="finished project folders")
    ap.add_argument("--preset", help="create a sample of this preset and run the main job on it")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, help="where --preset creates its project (WORK/PRESET_SEED)")
    ap.add_argument("--code", type=Path, default=ROOT, help="the gtkit checkout to run (default: this one)")
    ap.add_argument("--stop-after", choices=("sample",), help="only create the sample (measured)")
    ap.add_argument("--max-rss-gb", type=float, default=6.0, help="kill a measured run whose processes exceed this")
    ap.add_argument("--nice", type=int, default=10, help="niceness of the measured runs (0: an equal share of a "
                    "machine others use too)")
    ap.add_argument("--per-site", action="store_true", help="one column a site instead of the median per preset")
    ap.add_argument("--json", type=Path, help="also write the rows and fits here")
    a = ap.parse_args(argv)
    projects = list(a.projects)
    if a.preset:
        if not a.work:
            ap.error("--preset needs --work")
        projects.append(create_and_run(a.preset, a.seed, a.work, a.code.resolve(), a.stop_after, a.max_rss_gb,
                                        a.nice))
    for p in projects:
        if not (p / "project.toml").is_file():
            ap.error(f"not a gtkit project: {p}")
    load = os.getloadavg()
    text, data = table(projects, a.per_site)
    print(text)
    print(f"\ncells: wall / CPU seconds (CPU = process + reaped children), peak RSS of one process, disk of the "
          f"stage's outputs; median over a preset's seeds; * = an older record (no CPU/memory; wall from the stage's own timing). "
          f"Load average now {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f}: wall seconds taken under load are "
          f"upper bounds.")
    if a.json:
        a.json.write_text(json.dumps({**data, "load_now": load}, indent=1, default=str))


if __name__ == "__main__":
    main()
