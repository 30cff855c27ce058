"""``gtkit run DIR``: every stage that can run on what the project holds, then a summary
(see :mod:`gtkit.run_site`). A second run of a finished project only re-reads the outputs."""
from __future__ import annotations

import argparse

from ..sfm import registration_record as record


def register(sub):
    from ..run_site import STAGES
    from .render_db import _executor_args

    p = sub.add_parser(
        "run", help="run every stage that can run on a project (SfM, model, pseudo-GT, exports, overlays, "
        "localization, tracking, reports) and print a summary",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run, in order, the stages that can run on what the project holds; a stage whose input is\n"
                    "absent is skipped with the reason, a failing stage stops the run (exit 2) naming it;\n"
                    "a query sequence that could not be placed, or a failed check of the pseudo-GT (render_db,\n"
                    "localize: the later stages still run), is listed as a problem (exit 1).\n"
                    "The terminal shows one line per stage, warnings and the summary; each stage's log records\n"
                    "are in work/<stage>/log.txt (gtkit -v run: on the terminal).\n"
                    "Finished stages are up to date and only re-read. Stages: " + ", ".join(STAGES) + ".\n"
                    "Summary: printed and written to reports/run.json. --executor dask sends every stage that\n"
                    "splits into tasks to the cluster: the SfM's features and matching, the model's depth maps,\n"
                    "render-db, localize.")
    p.add_argument("project")
    p.add_argument("--from", dest="start", default=None, metavar="STAGE", choices=STAGES,
                   help="start at this stage (the earlier ones are not run; their outputs are read)")
    p.add_argument("--until", default=None, metavar="STAGE", choices=STAGES, help="stop after this stage")
    p.add_argument("--skip", default="", metavar="STAGE,...", help="comma-separated stages not to run")
    _executor_args(p)
    p.set_defaults(func=run)


def _f(v, fmt="{:.3f}", unit=""):
    return "-" if v is None else fmt.format(v) + unit


def query_block_line(b: dict, registered_by: str | None) -> str:
    """How a query sequence's own SfM ended, in words: its photos registered; or no model of its own
    and how the registration placed the sequence anyway (photo by photo against the reference: a
    normal outcome for a short sequence or photos held out far apart, issue 58); ERROR only where
    nothing placed it (also a problem of the run)."""
    if "error" not in b:
        return f"{b.get('n_registered')}/{b.get('n_images')} photos registered"
    if not registered_by:
        return f"ERROR {b['error']}"
    why = b["error"].replace("the mapper reconstructed nothing (no initial pair found)",
                             "the mapper found no initial pair")
    how = ("photo by photo against the reference block" if registered_by == record.SINGLE_PHOTOS
           else f"by {registered_by}")
    return f"no model of its own ({why}): placed {how} (pseudo-GT below)"


def print_summary(s: dict) -> None:
    ref, pg, loc, tr = (s.get(k) or {} for k in ("reference", "pseudo_gt", "localization", "tracking"))
    print(f"\n== gtkit run on {s['project']}")
    if ref:
        geo = f"georegistered to {ref.get('georegistered_with')}, RMSE {_f(ref.get('rmse_m'), unit=' m')}"
        if ref.get("tilt_from"):
            geo += f", tilt held by gravity ({ref['tilt_from']})"
        claim = ref.get("claimed_accuracy")
        if claim:
            geo += f"; {claim['short']}"
        elif ref.get("absolute_accuracy_h_m") is not None and not ref.get("gcp_median_err_m"):
            geo += (f"; absolute accuracy ~{ref['absolute_accuracy_h_m']:.1f} m horizontal / "
                    f"~{ref.get('absolute_accuracy_v_m') or 0:.1f} m vertical (GPS)")
        if ref.get("gcp_median_err_m") is not None:
            geo += f", GCP median {_f(ref['gcp_median_err_m'], unit=' m')}"
        if ref.get("checkpoint_median_err_m") is not None:
            geo += f", check points median {_f(ref['checkpoint_median_err_m'], unit=' m')}"
        if ref.get("gps_sigma_h_m") is not None:
            geo += (f"; GPS sigma {_f(ref['gps_sigma_h_m'])} m horizontal / {_f(ref.get('gps_sigma_v_m'))} m vertical, "
                    f"median residual {_f(ref.get('gps_residual_median_m'))} m")
        print(f"reference     {ref.get('n_registered')}/{ref.get('n_images')} photos registered, "
              f"reprojection {_f(ref.get('mean_reproj_px'), '{:.2f}')} px; {geo}")
    m = s.get("model") or {}
    source = {"built": "built from the photos", "imported": "imported or delivered", "none": "none"}.get(
        m.get("source"), m.get("source"))
    print(f"model         {source}" + (f" ({m['path']})" if m.get("path") else ""))
    placed = pg.get("registered_by") or {}
    for seq, b in (s.get("query_blocks") or {}).items():
        print(f"query block   {seq}: {query_block_line(b, placed.get(seq))}")
    if pg:
        print(f"pseudo-GT     {pg.get('n_registered')}/{pg.get('n_images')} query photos registered, median sigma "
              f"{_f(pg.get('median_sigma_pos_m'))} m / {_f(pg.get('median_sigma_rot_deg'))} deg, reprojection "
              f"{_f(pg.get('median_reproj_px'), '{:.2f}')} px"
              + (f"; {pg['n_unverified']} UNVERIFIED (a pose without a usable sigma is not a result: reports/gt_report.md)"
                 if pg.get("n_unverified") else ""))
        for seq, how in (pg.get("registered_how") or pg.get("registered_by") or {}).items():
            print(f"              {seq}: registered by {how}")
        for seq, e in (pg.get("errors") or {}).items():
            print(f"              {seq}: not registered: {e}")
    ov = s.get("overlays") or {}
    if ov:
        print(f"overlays      {ov.get('n_images')} photos, median misalignment "
              f"{_f(ov.get('median_misalignment_px'), '{:.2f}')} px")
    if loc:
        print(f"localization  {loc.get('n_localized')}/{loc.get('n_queries')} query photos localized "
              f"against {loc.get('database_views')} database views")
    if tr:
        print(f"tracking      {tr.get('n_located')}/{tr.get('n_detections')} detections located, median sigma "
              f"{_f(tr.get('median_sigma_h_m'), '{:.2f}')} m horizontal")
    if s.get("exports"):
        print("exports       " + ", ".join(s["exports"]))
    print("stages        " + ", ".join(f"{k} {v['status']}" + (f" ({v['seconds']} s)" if v["status"] in ("ran", "up to date") else "")
                                       for k, v in s["stages"].items() if v["status"] != "not selected"))
    print(f"reports       {s['project']}/reports (run.json, reference.md, gt_report.md)")
    for p in s.get("problems") or []:
        print(f"problem       {p}")


def stage_starting(name: str) -> None:
    """``[stage] ...`` while a stage runs: ended by a carriage return, so the stage's result line (or a
    progress bar, or a warning) takes its place: one line per stage on the terminal and in a log."""
    print(f"[{name}] ...", end="\r", flush=True)


def stage_done(r) -> None:
    """A stage's one line: ``[stage] ran in 3.2 s``, ``up to date``, ``skipped: why``, a validation
    stage's ``failed: why`` (the run goes on); another failed stage's line is the error the run stops with."""
    from ..stages import STAGE

    if r.status == "skipped":
        print(f"[{r.name}] skipped: {r.why}", flush=True)
    elif r.status != "failed":
        print(f"[{r.name}] {r.status} in {r.seconds} s", flush=True)
    elif STAGE[r.name].validation:
        print(f"[{r.name}] failed: {r.why}", flush=True)


def run(args):
    from ..run_site import RunOptions, run as run_site
    from .render_db import executor_settings

    opts = RunOptions(args.start, args.until, tuple(s for s in args.skip.split(",") if s),
                      executor_settings(args))
    s = run_site(args.project, opts, stage_done, stage_starting)
    print_summary(s)
    return 1 if s.get("problems") else 0
