"""``gtkit sfm DIR --block reference|queries``: structure from motion of one kind of block.
Settings: flag > project.toml [sfm] > default (gtkit.settings)."""
from __future__ import annotations


def register(sub):
    from .render_db import _executor_args

    p = sub.add_parser("sfm", help="SfM of the reference block (georegistered) or of each query sequence")
    p.add_argument("project")
    p.add_argument("--block", choices=["reference", "queries"], required=True)
    p.add_argument("--max-image-size", type=int, default=None, help="px for SIFT (default 1600)")
    p.add_argument("--max-features", type=int, default=None, help="SIFT keypoints per image (default 3000)")
    p.add_argument("--refine-intrinsics", choices=["auto", "yes", "no"], default=None,
                   help="auto (default): cameras.txt fixed, EXIF focal refined with GPS priors, no focal: "
                        "self-calibrated; yes: refine all; no: refine none")
    p.add_argument("--exhaustive-max", type=int, default=None,
                   help="exhaustive pairs up to this many photos (default 25; 80 when photos lack GPS)")
    p.add_argument("--gps-inlier-m", type=float, default=None,
                   help="Sim(3) threshold on GPS camera centres without a stated accuracy, metres (default 2)")
    p.add_argument("--gcp-accuracy", type=float, default=None, metavar="M",
                   help="the GCPs' accuracy (1 sigma, metres); default: from their own scatter")
    p.add_argument("--checkpoints", default=None, metavar="NAMES",
                   help="comma-separated GCP names used only as check points")
    p.add_argument("--georegister-with", choices=["gps", "gcp", "gps+gcp"], default=None)
    p.add_argument("--mapper", choices=["incremental", "global", "seeded", "auto"], default=None,
                   help="incremental (COLMAP), global (GLOMAP), seeded (reference block: photos start at their "
                        "RTK position + gimbal attitude, see sfm.seeded) or auto (default: seeded where the photos "
                        "allow it, else incremental)")
    _executor_args(p, None, "run feature extraction and matching as tasks there (default: in this process)")
    p.add_argument("--force", action="store_true", help="recompute even if a finished run matches")
    p.set_defaults(func=run)


def _print_reference(r: dict) -> None:
    from ..sfm.reference_report import by_reason

    geo = r.get("georegistration", {})
    print(f"reference: {r['n_registered']}/{r['n_images']} registered in {r.get('n_models', 1)} model(s), "
          f"{r.get('n_points3D')} points, mean reprojection {r.get('mean_reproj_px', float('nan')):.2f} px")
    for m in r.get("models", []) if r.get("n_models", 1) > 1 else []:
        print(f"  model {m['model']}: {m['n_registered']} photos, {m['n_points3D']} points, "
              + ("kept" if m.get("kept") else m.get("reason", "")))
    fit, q = geo.get("fit") or {}, geo.get("gps_quality") or {}
    line = (f"georegistration: fitted to {geo.get('fitted_to') or geo.get('used')}, "
            f"RMSE {geo.get('rmse_inliers_m', float('nan')):.3f} m")
    if fit.get("mode") == "gravity-held":
        line += f"; tilt held by gravity ({fit.get('tilt_from')})"
    elif fit.get("mode") == "combined":
        line += f"; tilt from the positions and gravity together ({fit.get('tilt_from')})"
    if (geo.get("gcp_click_scale") or {}).get("line"):
        line += f"; GCP clicks: {geo['gcp_click_scale']['line']}"
    if geo.get("gcp_median_err_m") is not None:
        line += f"; GCP median error {geo['gcp_median_err_m']:.3f} m"
    if geo.get("checkpoint_median_err_m") is not None:
        line += f"; check points {geo['checkpoint_median_err_m']:.3f} m"
    print(line)
    mapping = r.get("mapping") or {}
    if mapping.get("reused"):
        moved = mapping.get("largest_move_m") or {}
        print("  mapping reused (photos, cameras.txt, [sfm] unchanged): georegistration only"
              + (f"; positions moved since the mapping: {mapping.get('positions_moved_since_mapping')}, largest "
                 f"{moved['m']:.3f} m ({moved['photo']})" if moved.get("m") else ""))
    claim = geo.get("claimed_accuracy")   # the georegistration's record (gtkit.sfm.georegister.accuracy_claim)
    if q and not geo.get("n_gcp_in_fit"):
        print(f"  GPS: {q.get('n_inliers')}/{q.get('n_positions')} positions kept, residual median "
              f"{q.get('horizontal_residual_median_m') or 0:.2f} m horizontal / {q.get('vertical_residual_median_m') or 0:.2f} m vertical"
              + (f", altitude drift {q['altitude_drift_m']:+.1f} m" if q.get("altitude_drift_m") else "")
              + ("" if claim else f"; absolute accuracy ~{q.get('absolute_accuracy_h_m') or 0:.1f} m horizontal, "
                 f"~{q.get('absolute_accuracy_v_m') or 0:.1f} m vertical"))
    if claim:
        print(f"  {claim['line']}")
    for name, g in (geo.get("gcp_residuals") or {}).items():
        kind = "check point" if g.get("check") else ("GCP (outlier)" if g.get("outlier") else "GCP")
        print(f"  {kind} {name}: " + (f"{g['err_m']:.3f} m (dx {g['dx_m']:+.3f} dy {g['dy_m']:+.3f} dz {g['dz_m']:+.3f})"
                                      if g["status"] == "ok" else g["reason"]))
    for gname, photos in (r.get("gcp_clicks_outside_block") or {}).items():
        print(f"  GCP {gname}: clicked in photos that are not reference photos: {', '.join(photos)}")
    for why, names in by_reason(r["unregistered"]):
        print(f"  not registered ({len(names)}): {why}: {', '.join(names)}")


def run(args):
    from ..project import Project
    from ..sfm.blocks import run_queries, run_reference
    from ..stages import STAGE, settings_for
    from .render_db import executor_settings

    project = Project.load(args.project)
    s = settings_for(f"sfm_{args.block}", project, {
        "features.max_image_size": args.max_image_size, "features.max_num_features": args.max_features,
        "refine_intrinsics": args.refine_intrinsics, "matching.exhaustive_max_images": args.exhaustive_max,
        "georegister.gps_inlier_m": args.gps_inlier_m, "georegister.gcp_accuracy_m": args.gcp_accuracy,
        "georegister.checkpoints": args.checkpoints.split(",") if args.checkpoints else None,
        "georegister.use": args.georegister_with, "mapper": args.mapper})
    ex = executor_settings(args)
    STAGE[f"sfm_{args.block}"].check_inputs(project)      # every bad photo named at once
    if args.block == "reference":
        _print_reference(run_reference(project, s, force=args.force, executor=ex))
    else:
        from ..sfm.reference_report import by_reason

        res = run_queries(project, s, force=args.force, executor=ex)
        bad = 0
        for seq, r in res.items():
            if "error" in r and r.get("unregistered"):
                # photos that match no other (held out of a flight, far apart): not a failure of the
                # project; the registration resects each photo on its own against the reference block
                print(f"{seq}: no model of its own ({r['error']}); `gtkit register` places each of its "
                      f"{len(r['unregistered'])} photos on its own against the reference block")
                for why, names in by_reason(r["unregistered"]):
                    print(f"  ({len(names)}) {why}: {', '.join(names)}")
                continue
            if "error" in r:
                bad += 1
                print(f"{seq}: ERROR {r['error']}")
                continue
            print(f"{seq}: {r['n_registered']}/{r['n_images']} registered, mean reprojection {r['mean_reproj_px']:.2f} px")
            for why, names in by_reason(r["unregistered"]):
                print(f"  not registered ({len(names)}): {why}: {', '.join(names)}")
        return 1 if bad else 0
