"""The tracking stage on a small synthetic project: DSM GeoTIFF, rig, poses, detections (issue 8)."""
import csv
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gtkit.camera import Camera
from gtkit.cli import main
from gtkit.errors import GtkitError
from gtkit.export.geotiff import write_geotiff
from gtkit.export.grid import Grid
from gtkit.geo import GeoFrame
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.io.poses import read_poses, write_poses
from gtkit.pose import Pose
from gtkit.project import Project
from gtkit.track.rig import Rig, ZoomSetting
from gtkit.track.smoothing import SmoothingSettings, smooth_track
from gtkit.track.targets import read_detections
from gtkit.track.tracker import TrackSettings, run

ZOOM = Camera.pinhole(640, 480, 2000.0)
RIG = Rig(Rotation.from_rotvec(np.radians([0.3, -0.2, 0.1])).as_matrix(), [0.03, -0.02, 0.01], [ZoomSetting(ZOOM)])


def ground(x, y):
    """Gentle slope plus a 25 m block at x in [30, 60], y in [-20, 20]."""
    z = 0.02 * x + 0.01 * y
    return np.where((x >= 30) & (x <= 60) & (np.abs(y) <= 20), z + 25.0, z)


@pytest.fixture()
def project(tmp_path):
    frame = GeoFrame("EPSG:32650", (500000.0, 4000000.0, 50.0))
    proj = Project.create(tmp_path / "site", frame)
    P = proj.paths
    grid = Grid(-200.0, 200.0, 1.0, 400, 400)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    write_geotiff(P.dsm, (ground(X, Y) + frame.origin[2]).astype(np.float32), grid, frame.crs, frame.origin,
                  nodata=-9999.0)
    RIG.save(P.rig)
    rng = np.random.default_rng(3)
    poses, rows, truth = {}, [], {}
    targets = [np.array([x, y, 0.0]) for x, y in ((-40, 10), (-10, -30), (20, 5), (45, 0), (-60, -60))]
    for k, X in enumerate(targets):
        X[2] = float(ground(X[0], X[1]))
        # wide camera 120 m up, 45 deg down, aimed so the zoom sees the target near its centre
        yaw = rng.uniform(-180, 180)
        R = Pose.from_dji(yaw, -45.0, 0.0, [0, 0, 0]).R
        fwd = R.T @ np.array([0, 0, 1.0])
        C = X - fwd * (120 / np.sin(np.radians(45))) + rng.normal(0, 2, 3)
        wide = Pose.from_center(R, C)
        name = f"queries/seq1/{k:04d}"
        poses[name + "_W.jpg"] = wide
        uv, _ = ZOOM.project(RIG.zoom_pose(wide).transform(X[None])[0:1])
        rows.append([name + "_Z.jpg", *uv[0], "car", f"{100.0 + 2 * k}"])
        truth[name + "_Z.jpg"] = X
    # one zoom photo pointing above the horizon, one whose wide photo was not localized
    up = Pose.from_dji(0.0, 10.0, 0.0, [0, 0, 120.0])
    poses["queries/seq1/0005_W.jpg"] = up
    rows.append(["queries/seq1/0005_Z.jpg", 320.0, 240.0, "car", "110"])
    rows.append(["queries/seq1/0006_Z.jpg", 320.0, 240.0, "car", "112"])
    for k in range(7):
        for s in "WZ":
            write_jpeg_with_meta(P.query_images / "seq1" / f"{k:04d}_{s}.jpg", np.zeros((480, 640, 3), np.uint8),
                                 timestamp=f"2026:05:14 16:30:{k:02d}")
    write_poses(P.stage("localize") / "poses.txt", poses)
    # truth as the sample generator writes it (for the evaluation test)
    lines = ["target,time_s,datetime,x,y,z"]
    shots = []
    for k, X in enumerate(truth.values()):
        lines.append(f"car,{100 + 2 * k}.00,2026-05-14T16:31:{40 + 2 * k}.000,{X[0]},{X[1]},{X[2]}")
        shots.append({"name": f"queries/seq1/{k:04d}_Z.jpg", "time_s": 100 + 2 * k})
    lines.append("car,120.00,2026-05-14T16:32:00.000,0,0,0")
    (P.truth).mkdir()
    (P.truth / "targets.csv").write_text("\n".join(lines) + "\n")
    (P.truth / "shots.json").write_text(json.dumps({"shots": shots}))
    (P.truth / "rig.json").write_text(json.dumps({"R": RIG.R_zw.tolist(), "t": (-RIG.R_zw @ RIG.offset).tolist(),
                                                  "zoom": ZOOM.to_line()}))
    with open(P.detections, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "x", "y", "label", "time"])
        w.writerows(rows)
    return proj, truth


def _read(path):
    return list(csv.DictReader(line for line in open(path) if not line.startswith("#")))


def test_track_stage_places_targets_and_reports_misses(project):
    proj, truth = project
    summary = run(proj, TrackSettings())
    P = proj.paths
    rows = {r["image"]: r for r in _read(P.tracks)}
    assert summary["n_located"] == 5 and summary["status"]["miss_sky"] == 1 and summary["status"]["no_pose"] == 1
    for name, X in truth.items():
        r = rows[name]
        est = np.array([float(r["x"]), float(r["y"]), float(r["z"])]) - np.array(proj.frame.origin)
        assert np.linalg.norm(est - X) < 0.03, (name, est, X)
        assert 0.05 < float(r["sigma_h_m"]) < 10
        lon, lat = float(r["lon"]), float(r["lat"])
        assert np.allclose(proj.frame.wgs84_to_local(lon, lat, float(r["h"])), est, atol=0.01)
    sky = rows["queries/seq1/0005_Z.jpg"]
    assert sky["status"] == "miss_sky" and "horizon" in sky["message"] and sky["x"] == "" and sky["lon"] == ""
    nop = rows["queries/seq1/0006_Z.jpg"]
    assert nop["status"] == "no_pose" and "0006_W.jpg" in nop["message"] and nop["x"] == ""
    gj = json.loads(P.tracks.with_suffix(".geojson").read_text())
    pts = [f for f in gj["features"] if f["geometry"]["type"] == "Point"]
    assert len(pts) == 5 and all(-180 < f["geometry"]["coordinates"][0] < 180 for f in pts)
    # the block's roof is hit where the target stands on it (first crossing, not the ground behind)
    roof = rows["queries/seq1/0003_Z.jpg"]
    assert float(roof["z"]) - proj.frame.origin[2] > 24
    # second run resumes; the CLI works and errors name the file
    assert run(proj, TrackSettings())["n_located"] == 5
    assert main(["track", str(P.root), "--force", "--no-smooth"]) == 0
    # evaluation against the truth: exact poses -> centimetres; misses counted as failures
    assert main(["track", "evaluate", str(P.root)]) == 0
    rep = json.loads(P.tracking_report.read_text())
    assert rep["n_targets"] == 7 and rep["n_failed"] == 2
    assert rep["median_err_h_m"] < 0.03 and rep["median_err_3d_m"] < 0.03
    assert rep["recall_h"]["1m"] == pytest.approx(5 / 7)
    assert rep["rig"]["rotation_err_deg"] < 1e-6 and abs(rep["rig"]["focal_err_pct"]) < 1e-9
    assert (P.reports / "tracking.png").stat().st_size > 10_000
    assert main(["evaluate", str(P.root), "--what", "tracking"]) == 0  # the shared evaluate command
    # a pose covariance file beside the poses is used: 2 m per axis on one pose, viewed 45 deg down ->
    # horizontal variance 4 (across) + 4 + 4 (along: the height error slides the point) -> sigma 3.46 m
    from gtkit.io.poses import write_covariances

    write_covariances(P.stage("localize") / "covariances.txt",
                      {"queries/seq1/0001_W.jpg": np.diag([1e-10] * 3 + [4.0] * 3)})
    run(proj, TrackSettings(smooth=False))
    rows = {r["image"]: r for r in _read(P.tracks)}
    assert 3.1 < float(rows["queries/seq1/0001_Z.jpg"]["sigma_h_m"]) < 3.8
    assert float(rows["queries/seq1/0000_Z.jpg"]["sigma_h_m"]) < 2.0  # the others keep the default sigmas
    (P.stage("localize") / "covariances.txt").unlink()
    # a box around the image of a 1.5 m tall car's centre: cast at half its height above the DSM,
    # the ground point below is the footprint centre (the default foot point); the bottom centre is off
    name, X = "queries/seq1/0002_Z.jpg", truth["queries/seq1/0002_Z.jpg"]
    zp = RIG.zoom_pose(read_poses(P.stage("localize") / "poses.txt")["queries/seq1/0002_W.jpg"])
    c = ZOOM.project(zp.transform((X + [0, 0, 0.75])[None]))[0][0]
    box = P.root / "boxes.csv"
    box.write_text(f"image,xmin,ymin,xmax,ymax,label\n{name},{c[0] - 40},{c[1] - 25},{c[0] + 40},{c[1] + 25},car\n")
    for foot, lo, hi in (("centre", 0.0, 0.05), ("bottom_centre", 0.3, 50.0)):
        run(proj, TrackSettings(detections=str(box), foot_point=foot, smooth=False))
        r = _read(P.tracks)[0]
        est = np.array([float(r["x"]), float(r["y"]), float(r["z"])]) - np.array(proj.frame.origin)
        assert lo <= np.linalg.norm(est - X) < hi, (foot, est, X)


def test_bad_detection_input_names_the_file(tmp_path):
    p = tmp_path / "dets.csv"
    p.write_text("image,x\nqueries/a_Z.jpg,3\n")
    with pytest.raises(GtkitError, match="dets.csv"):
        read_detections(p)
    p.write_text("image,xmin,ymin,xmax,ymax\nqueries/a_Z.jpg,10,20,5,40\n")
    with pytest.raises(GtkitError, match="dets.csv: line 2"):
        read_detections(p)
    p.write_text("image,x,y,label,time\nqueries/a_Z.jpg,10,20,car,yesterday\n")
    with pytest.raises(GtkitError, match="time"):
        read_detections(p)
    j = tmp_path / "a.json"
    j.write_text("{not json")
    with pytest.raises(GtkitError, match="a.json"):
        read_detections(j)
    j.write_text(json.dumps({"imagePath": "a_Z.jpg", "shapes": [
        {"label": "person", "points": [[10, 20], [30, 80]], "shape_type": "rectangle"},
        {"label": "car", "points": [[5, 6]], "shape_type": "point"}]}))
    d = read_detections(j)
    assert (d[0].u, d[0].v, d[0].label) == (20.0, 50.0, "person")  # box centre (default)
    assert (d[1].u, d[1].v) == (5.0, 6.0)
    assert read_detections(j, "bottom_centre")[0].v == 80.0


def test_rts_smoother_reduces_noise_on_a_constant_velocity_track():
    rng = np.random.default_rng(0)
    t = np.arange(0, 40, 2.0)
    true = np.column_stack([5 * t, -3 * t, np.zeros_like(t)])
    meas = true + rng.normal(0, 2.0, true.shape)
    meas[7] += [40, 0, 0]  # a gross outlier is gated
    sm = smooth_track(t, meas, [np.eye(3) * 4.0] * len(t), SmoothingSettings(accel_sigma=0.3))
    raw = np.median(np.linalg.norm((meas - true)[:, :2], axis=1))
    smo = np.median(np.linalg.norm((sm["points"] - true)[:, :2], axis=1))
    assert sm["outlier"][7] and sm["outlier"].sum() == 1
    assert smo < 0.6 * raw


def test_uncertainty_matches_the_analytic_propagation_for_a_nadir_view():
    """Nadir camera 100 m over flat ground, covariance sigma_t = 0.5 m, sigma_rot = 1 mrad:
    ground sigma per axis = sqrt(0.5^2 + (100 * 0.001)^2) = 0.51 m, height sigma ~ 0."""
    from gtkit.track.raycast import dsm_from_array
    from gtkit.track.uncertainty import UncertaintySettings, ground_point_covariance

    dsm = dsm_from_array(np.zeros((400, 400)), -200, 200, 1.0)
    cov = np.diag([1e-6, 1e-6, 1e-6, 0.25, 0.25, 0.25])
    wide = Pose(Pose.from_dji(0, -90, 0, [0, 0, 100]).R, Pose.from_dji(0, -90, 0, [0, 0, 100]).t, cov)
    rig = Rig(np.eye(3), np.zeros(3), [ZoomSetting(ZOOM)])
    u = ground_point_covariance(dsm, wide, rig, ZOOM, (320, 240), UncertaintySettings(samples=4000, sigma_px=0.0))
    sx, sy, sz = np.sqrt(np.diag(u["cov"]))
    assert u["hit_share"] == 1.0
    assert abs(sx - 0.51) < 0.03 and abs(sy - 0.51) < 0.03 and sz < 0.01
    # without a covariance the stated default sigmas are used (0.5 m, 0.2 deg -> 0.61 m per axis)
    u2 = ground_point_covariance(dsm, Pose(wide.R, wide.t), rig, ZOOM, (320, 240),
                                 UncertaintySettings(samples=4000, sigma_px=0.0))
    expect = np.hypot(0.5, 100 * np.radians(0.2))
    assert abs(np.sqrt(u2["cov"][0, 0]) - expect) < 0.04


def test_tracking_reports_name_paths_inside_the_project(project, tmp_path):
    """`gtkit track` and `gtkit track evaluate` store paths relative to the project: a copy of the
    project names no file of the folder they ran in (reports/tracking.json named the tracks and
    the plot by absolute path)."""
    import shutil

    proj, _ = project
    root = proj.paths.root
    assert main(["track", str(root)]) == 0
    assert main(["track", "evaluate", str(root)]) == 0
    rep = json.loads(proj.paths.tracking_report.read_text())
    assert rep["tracks"] == "exports/tracks.csv" and rep["plot"] == "reports/tracking.png"
    copy = tmp_path / "elsewhere" / "site"
    shutil.copytree(root, copy)
    text = [p for p in copy.rglob("*") if p.is_file() and p.suffix in (".json", ".md", ".toml", ".csv", ".geojson")]
    assert [str(p.relative_to(copy)) for p in text if str(root) in p.read_text(errors="replace")] == []
