"""``gtkit sfm DIR --block reference|queries``: structure from motion of one kind of block."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("sfm", help="SfM of the reference block (georegistered) or of each query sequence")
    p.add_argument("project")
    p.add_argument("--block", choices=["reference", "queries"], required=True)
    p.add_argument("--max-image-size", type=int, default=None, help="px for SIFT (default 1600)")
    p.add_argument("--max-features", type=int, default=None, help="SIFT keypoints per image (default 4000)")
    p.add_argument("--gps-inlier-m", type=float, default=None,
                   help="Sim(3) RANSAC threshold on GPS camera centres, metres (default 2)")
    p.add_argument("--georegister-with", choices=["gps", "gcp", "gps+gcp"], default=None)
    p.add_argument("--force", action="store_true", help="recompute even if a finished run matches")
    p.set_defaults(func=run)


def run(args):

    from ..sfm.blocks import SfmSettings, run_queries, run_reference

    s = SfmSettings()
    if args.max_image_size:
        s.features.max_image_size = args.max_image_size
    if args.max_features:
        s.features.max_num_features = args.max_features
    if args.gps_inlier_m:
        s.georegister.gps_inlier_m = args.gps_inlier_m
    if args.georegister_with:
        s.georegister.use = args.georegister_with
    if args.block == "reference":
        r = run_reference(args.project, s, force=args.force)
        geo = r.get("georegistration", {})
        print(f"reference: {r['n_registered']}/{r['n_images']} registered, {r.get('n_points3D')} points, "
              f"mean reprojection {r.get('mean_reproj_px', float('nan')):.2f} px")
        print(f"georegistration ({geo.get('used')}): {geo.get('n_inliers')} inliers, "
              f"RMSE {geo.get('rmse_inliers_m', float('nan')):.3f} m; GCP median error "
              f"{geo.get('gcp_median_err_m')} m")
        for name, g in (geo.get("gcp_residuals") or {}).items():
            print(f"  GCP {name}: " + (f"{g['err_m']:.3f} m (dx {g['dx_m']:+.3f} dy {g['dy_m']:+.3f} dz {g['dz_m']:+.3f})"
                                        if g["status"] == "ok" else g["reason"]))
        for n, why in r["unregistered"].items():
            print(f"  not registered: {n}: {why}")
    else:
        res = run_queries(args.project, s, force=args.force)
        bad = 0
        for seq, r in res.items():
            if "error" in r:
                bad += 1
                print(f"{seq}: ERROR {r['error']}")
                continue
            print(f"{seq}: {r['n_registered']}/{r['n_images']} registered, mean reprojection {r['mean_reproj_px']:.2f} px")
            for n, why in r["unregistered"].items():
                print(f"  not registered: {n}: {why}")
        return 1 if bad else 0
