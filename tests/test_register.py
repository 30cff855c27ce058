"""Tie-point registration + joint BA on a synthetic scene built by hand (pycolmap models with
known cameras), measured against the true poses. Runs in seconds: no images, no SIFT."""
from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest

from gtkit.camera import Camera
from gtkit.conventions import dji_to_rotation
from gtkit.evaluate.poses import medians, pose_errors
from gtkit.geo import GeoFrame
from gtkit.io.atomic import write_json
from gtkit.io.poses import read_covariances, read_poses, write_poses
from gtkit.io.tiepoints import Observation, TiePoint, write_tiepoints
from gtkit.pose import Pose
from gtkit.project import Project
from gtkit.evaluate import gt_report as report  # the report with its checks (gtkit report)
from gtkit.sfm import register
from gtkit.sfm.geometry import RegistrationError, robust_sim3, triangulate_clicks, triangulate_many
from conftest import stage_settings

CLICK_NOISE = 0.5
REF_CAM = Camera.pinhole(1600, 1200, 1400.0)
Q_CAM = Camera("SIMPLE_RADIAL", 1600, 1200, (920.0, 800.0, 600.0, -0.02))


def _ground(rng, n, half=60.0):
    xy = rng.uniform(-half, half, (n, 2))
    return np.c_[xy, 3.0 * np.sin(xy[:, 0] / 15.0) + rng.uniform(0, 8, n)]


def _visible(cam, pose, X, margin=5):
    uv, front = cam.project(pose.transform(X))
    return uv, front & cam.in_image(uv, margin)


def _model(cam: Camera, poses: dict[str, Pose], points=None, rng=None, noise_px=0.0):
    """A pycolmap Reconstruction holding ``poses`` (and ``points`` observed where visible)."""
    rec = pycolmap.Reconstruction()
    c = cam.to_pycolmap()
    c.camera_id = 1
    rec.add_camera_with_trivial_rig(c)
    pts = np.zeros((0, 3)) if points is None else np.asarray(points)
    tracks = [[] for _ in range(len(pts))]
    for k, (n, p) in enumerate(poses.items()):
        uv, ok = _visible(cam, p, pts)
        idx = np.flatnonzero(ok)
        kp = uv[idx] + (rng.normal(0, noise_px, (len(idx), 2)) if len(idx) else 0)
        for j, i in enumerate(idx):
            tracks[i].append((k + 1, j))
        im = pycolmap.Image(name=n, keypoints=kp.reshape(-1, 2), camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(im, p.to_pycolmap())
    for X, tr in zip(pts, tracks):
        if len(tr) >= 2:
            rec.add_point3D(X, pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in tr]))
    return rec


def make_site(tmp_path, seed=0, mistakes=0.0, n_ties=20, seqs=("seq1",), tie_override=None, one_query_click=False,
              left_out=()):
    """A project with a reference model, query models in arbitrary frames, clicks and truth."""
    rng = np.random.default_rng(seed)
    proj = Project.create(tmp_path, GeoFrame("EPSG:32650", (500000.0, 4000000.0, 0.0)))
    P = proj.paths
    ref = {}
    for i, x in enumerate(np.linspace(-50, 50, 4)):
        for j, y in enumerate(np.linspace(-50, 50, 4)):
            for eye, (yaw, pitch) in {"N": (0, -90), "F": (0, -45), "B": (180, -45)}.items():
                ref[f"reference/R{i}_{j}_{eye}.jpg"] = Pose.from_dji(yaw, pitch, 0.0, [x, y - 40 * np.sign(pitch + 60) * 0, 120.0]
                                                                   if eye == "N" else [x, y - (1 if yaw == 0 else -1) * 60, 120.0])
    _model(REF_CAM, ref, _ground(rng, 1500, 90.0), rng, 0.3).write(_mk(P.stage("sfm_reference") / "model"))
    truth, tie_list = {}, []
    clicks_bad = set()
    for s, seq in enumerate(seqs):
        qposes = {}
        for k in range(8):
            C = np.array([-35 + 10 * k, -70 + 5 * s, 80.0 + 3 * k])
            qposes[f"queries/{seq}/{k:04d}_W.jpg"] = Pose.from_center(dji_to_rotation(5 * s, -50 + k, 0.0), C)
        truth.update(qposes)
        pts = _ground(rng, 600)
        # the query block's own frame: a similarity away from the world, plus small SfM noise
        Rm = pycolmap.Rotation3d(rng.normal(size=3) * 0.8).matrix()
        scale, tr = 0.07, rng.normal(size=3) * 20
        to_block = lambda X: scale * X @ Rm.T + tr  # noqa: E731
        bposes = {}
        for n, p in qposes.items():
            Cb = to_block(p.center[None])[0] + rng.normal(0, 0.02 * scale, 3)
            bposes[n] = Pose.from_center(p.R @ Rm.T, Cb)
        qm = _model(Q_CAM, {n: p for n, p in qposes.items() if n not in left_out}, pts, rng, noise_px=0.5)
        if left_out:  # photos the sequence's SfM could not hold, as its block record lists them
            write_json(P.stage("sfm_queries") / seq / "block.json",
                       {"n_images": len(qposes),
                        "unregistered": {n: "no verified matches with any other image" for n in left_out}})
        # move the model (built in world) into the block frame
        qm.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(Rm), tr))
        (P.query_images / seq).mkdir(parents=True, exist_ok=True)
        for n in qposes:
            (P.images / n).write_bytes(b"")
        qm.write(_mk(P.stage("sfm_queries") / seq / "model"))
        tx = _ground(rng, 400, half=50.0) if tie_override is None else tie_override
        qnames = list(qposes)
        per_image = max(1, n_ties // len(qnames)) if one_query_click else n_ties
        for k_img, qn in enumerate(qnames if one_query_click else qnames[:1]):
            count = 0
            for X in tx[rng.permutation(len(tx))] if one_query_click else tx:
                qo = [(n, uv) for n, p in qposes.items() for uv, ok in [_visible(Q_CAM, p, X[None], 40)] if ok[0]]
                ro = [(n, uv) for n, p in ref.items() for uv, ok in [_visible(REF_CAM, p, X[None], 40)] if ok[0]]
                if len(qo) < 2 or len(ro) < 2 or (one_query_click and qn not in dict(qo)):
                    continue
                if one_query_click:  # as the sample generator clicks: one query photo, 1-3 reference photos
                    qo, ro = [(qn, dict(qo)[qn])], ro[:rng.integers(1, 4)]
                qo, ro = qo[:3], ro[:3]
                tid = f"{seq}_tp{len([t for t in tie_list if t.id.startswith(seq)]):02d}"
                obs = [Observation(n, *(uv[0] + rng.normal(0, CLICK_NOISE, 2))) for n, uv in qo + ro]
                if rng.uniform() < mistakes:  # a gross click mistake in one photo
                    o = obs[rng.integers(1 if one_query_click else 0, len(obs))]
                    o.x += rng.choice([-1, 1]) * rng.uniform(30, 80)
                    o.y += rng.choice([-1, 1]) * rng.uniform(30, 80)
                    clicks_bad.add(tid)
                tie_list.append(TiePoint(tid, obs, "simulated"))
                count += 1
                if count >= per_image:
                    break
    write_tiepoints(P.tiepoints, tie_list)
    write_poses(P.truth / "poses.txt", truth)
    return proj, truth, clicks_bad


def _mk(d):
    d.mkdir(parents=True, exist_ok=True)
    return d


def test_registration_meets_targets(tmp_path):
    proj, truth, _ = make_site(tmp_path, seed=1)
    res = register.run(proj, stage_settings("register", proj))
    assert res["n_registered"] == len(truth) == res["n_images"]
    est = read_poses(proj.paths.stage("register") / "poses.txt")
    m = medians(pose_errors(est, truth))
    assert m["median_pos_err_m"] < 0.15 and m["median_rot_err_deg"] < 0.1, m
    assert res["median_reproj_px"] < 1.0 and res["median_tiepoint_reproj_px"] < 1.5, res
    cov = read_covariances(proj.paths.stage("register") / "covariances.txt")
    assert set(cov) == set(truth)
    s = [res["images"][n]["sigma_pos_m"] for n in truth]
    assert 0 < np.median(s) < 0.5


def test_one_query_click_per_tiepoint(tmp_path):
    """The sample's click pattern: each tie point in one query photo and 1-3 reference photos,
    so block positions come from the blocks' depth; 20 % gross mistakes."""
    proj, truth, bad = make_site(tmp_path, seed=5, mistakes=0.2, n_ties=40, one_query_click=True)
    res = register.run(proj, stage_settings("register", proj))
    assert res["n_registered"] == 8
    est = read_poses(proj.paths.stage("register") / "poses.txt")
    m = medians(pose_errors(est, truth))
    # this scene's geometry allows ~0.1 m (the BA's own sigma): errors must agree with it
    sig = np.median([res["images"][n]["sigma_pos_ba_m"] for n in est])
    assert m["median_pos_err_m"] < 2.5 * sig and m["median_rot_err_deg"] < 0.15, (m, sig)
    # every gross mistake that reaches the BA is listed (one on a lone ref click may be undetectable
    # if along the epipolar line, but then it also does no harm)
    listed = set(res["bad_tiepoints"])
    assert len(bad & listed) >= 0.7 * len(bad), (bad, listed)
    assert res["median_tiepoint_reproj_px"] < 1.5


def test_a_photo_its_sequence_left_out_is_resected_from_its_clicks(tmp_path):
    lonely = "queries/seq1/0003_W.jpg"
    proj, truth, _ = make_site(tmp_path, seed=2, n_ties=96, one_query_click=True, left_out=(lonely,))
    res = register.run(proj, stage_settings("register", proj))
    assert res["n_registered"] == 8 == res["n_images"]
    rec = res["images"][lonely]["resected"]
    assert rec["resected"] and rec["n_inliers"] >= 6 and "no verified matches" in rec["sfm_reason"]
    assert res["sequences"]["seq1"]["left_out_by_sfm"][lonely]["resected"]
    est = read_poses(proj.paths.stage("register") / "poses.txt")
    e = pose_errors(est, truth, [lonely])[lonely]
    others = medians(pose_errors(est, truth, [n for n in truth if n != lonely]))
    # held by its own clicks only (no SfM points): within a few times the block's photos
    assert e["pos_err_m"] < max(0.3, 4 * others["median_pos_err_m"]) and e["rot_err_deg"] < 0.3, (e, others)


def test_report_reads_truth_and_review(tmp_path):
    proj, truth, _ = make_site(tmp_path, seed=6, seqs=("seq1", "seq2"), n_ties=12)
    names = sorted(truth)
    (proj.paths.review).write_text(json.dumps({names[0]: "accept", names[1]: "reject"}))
    reg = register.run(proj, stage_settings("register", proj))
    rep = report.run(proj, stage_settings("report", proj))
    saved = json.loads((proj.paths.reports / "gt_report.json").read_text())
    for k in ("median_reproj_px", "median_tiepoint_reproj_px", "n_registered", "n_images", "median_pos_err_m",
              "median_rot_err_deg"):
        assert saved[k] == rep[k] and saved[k] is not None, k
    assert saved["n_registered"] == saved["n_images"] == 16 == reg["n_registered"]
    est = read_poses(proj.paths.stage("register") / "poses.txt")
    assert saved["median_pos_err_m"] == pytest.approx(medians(pose_errors(est, truth))["median_pos_err_m"])
    assert saved["per_image"][names[0]]["review"] == "accept" and saved["review"]["reject"] == 1
    assert "pos_err_m" in saved["per_image"][names[3]]
    md = (proj.paths.reports / "gt_report.md").read_text()
    assert "median position error vs truth" in md and (proj.paths.reports / "gt_pos_err.svg").is_file()


def test_gross_click_mistakes_are_listed(tmp_path):
    proj, truth, bad = make_site(tmp_path, seed=2, mistakes=0.2, n_ties=20)
    assert len(bad) >= 2
    res = register.run(proj, stage_settings("register", proj))
    est = read_poses(proj.paths.stage("register") / "poses.txt")
    m = medians(pose_errors(est, truth))
    sig = np.median([res["images"][n]["sigma_pos_ba_m"] for n in est])
    assert m["median_pos_err_m"] < min(0.25, 2.5 * sig) and m["median_rot_err_deg"] < 0.1, (m, sig)
    assert bad <= set(res["bad_tiepoints"]), (bad, res["bad_tiepoints"].keys())
    assert res["median_tiepoint_reproj_px"] < 1.5


def test_too_few_and_collinear_tiepoints_fail_per_sequence(tmp_path):
    proj, truth, _ = make_site(tmp_path, seed=3, seqs=("seq1", "seq2"), n_ties=10)
    # seq2 keeps only two tie points: an error for seq2, seq1 still finishes
    from gtkit.io.tiepoints import read_tiepoints
    tps = read_tiepoints(proj.paths.tiepoints)
    seq2 = [t for t in tps if t.id.startswith("seq2")]
    write_tiepoints(proj.paths.tiepoints, [t for t in tps if t.id.startswith("seq1")] + seq2[:2])
    res = register.run(proj, stage_settings("register", proj))
    assert res["sequences"]["seq2"]["status"] == "error"
    assert "only 2 usable tie points" in res["sequences"]["seq2"]["error"]
    assert res["sequences"]["seq1"]["status"] == "registered"
    est = read_poses(proj.paths.stage("register") / "poses.txt")
    assert all(n.startswith("queries/seq1/") for n in est) and len(est) == 8
    assert res["n_images"] == 16 and res["n_registered"] == 8


def test_collinear_sim3_is_an_error():
    rng = np.random.default_rng(0)
    src = np.c_[np.linspace(0, 10, 6), 2 * np.linspace(0, 10, 6), np.zeros(6)]
    with pytest.raises(RegistrationError, match="collinear"):
        robust_sim3(src, src * 2 + 1, 0.5)
    with pytest.raises(RegistrationError, match="only 2"):
        robust_sim3(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), 0.5)


def test_triangulation_drops_a_bad_click():
    rng = np.random.default_rng(4)
    X = np.array([3.0, -2.0, 5.0])
    poses = [Pose.from_dji(0, -90, 0, [x, 0, 100]) for x in (-20, 0, 20, 35)]
    uv = np.array([REF_CAM.project(p.transform(X[None]))[0][0] for p in poses]) + rng.normal(0, 0.5, (4, 2))
    uv[2] += [60, -45]
    tri = triangulate_clicks([REF_CAM] * 4, poses, uv, max_px=3.0)
    assert tri.used.tolist() == [True, True, False, True]
    assert np.linalg.norm(tri.xyz - X) < 0.3


def _looking_at(target, C):
    z = (target - C) / np.linalg.norm(target - C)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Pose.from_center(np.array([x, np.cross(z, x), z]), C)


def test_triangulating_many_points_at_once_gives_what_one_at_a_time_gives():
    """The vectorised path (all the joint BA's tie points at once) returns, point by point, what
    triangulate_clicks returns: same position (1e-6 m), same clicks used, same failures."""
    rng = np.random.default_rng(7)
    cams = [Camera("OPENCV", 640, 480, (500.0, 505.0, 321.0, 238.0, -0.08, 0.02, 1e-3, -5e-4)), REF_CAM]
    tracks = []
    for k in range(60):
        X = rng.uniform([-40, -40, 0], [40, 40, 25])
        n = 2 + k % 4
        poses = [_looking_at(X + rng.uniform(-3, 3, 3), X + rng.uniform([-60, -60, 80], [60, 60, 120])) for _ in range(n)]
        cs = [cams[rng.integers(2)] for _ in range(n)]
        uv = np.array([c.project(p.transform(X[None]))[0][0] for c, p in zip(cs, poses)]) + rng.normal(0, 0.7, (n, 2))
        if k % 5 == 0:
            uv[k % n] += [40, -30]                      # a wrong click: the one-at-a-time path drops it
        if k % 17 == 0:
            poses = [Pose.from_dji(0, -90, 0, X + [dx, 0, 100]) for dx in np.linspace(0, 0.5, n)]  # parallel rays
            uv = np.array([REF_CAM.project(p.transform(X[None]))[0][0] for p in poses])
            cs = [REF_CAM] * n
        tracks.append((cs, poses, uv))
    many = triangulate_many(tracks, max_px=3.0, min_angle_deg=1.0)
    n_ok = n_dropped = 0
    for tr, m in zip(tracks, many):
        one = triangulate_clicks(*tr, max_px=3.0, min_angle_deg=1.0)
        assert (one.xyz is None) == (m.xyz is None) and one.used.tolist() == m.used.tolist()
        if one.xyz is not None:
            assert np.linalg.norm(one.xyz - m.xyz) < 1e-6
            np.testing.assert_allclose(one.residuals_px, m.residuals_px, atol=1e-4)
            n_ok += 1
            n_dropped += int((~one.used).sum())
    assert n_ok >= 45 and n_dropped >= 8


def test_systematic_swing_moves_the_centre_sideways_by_depth_times_tilt_and_keeps_the_scene_point():
    """The reported covariance's systematic term: the camera tilted by swing/focal about its x and y
    axes, its centre moved so that the scene point at its median depth stays where it is."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    R = dji_to_rotation(30.0, -45.0, 0.0)
    C = np.array([100.0, -50.0, 150.0])
    pose = Pose.from_center(R, C)
    depth, focal, swing = 200.0, 800.0, 0.15
    cov = register.swing_covariance(pose.t, depth, focal, swing)
    tilt = swing / focal
    # the centre moves sideways (camera x and y) by depth * tilt, not along the view
    cc = Pose(pose.R, pose.t, cov).center_covariance()
    np.testing.assert_allclose(pose.R @ cc @ pose.R.T, np.diag([(depth * tilt) ** 2] * 2 + [0.0]), atol=1e-12)
    # sampled perturbations keep the point `depth` ahead in place (to first order) and turn the camera
    X = pose.R.T @ (np.array([0.0, 0.0, depth]) - pose.t)
    w, V = np.linalg.eigh(cov)                              # rank 2: sampled by its eigenvectors
    L = V * np.sqrt(np.clip(w, 0.0, None))
    moved, turned = [], []
    for _ in range(200):
        d = L @ rng.standard_normal(6)
        R2 = Rotation.from_rotvec(d[:3]).as_matrix() @ pose.R
        t2 = pose.t + d[3:]
        moved.append(np.linalg.norm(R2 @ X + t2 - np.array([0.0, 0.0, depth])))
        turned.append(np.linalg.norm(d[:3]))
    assert max(moved) < 1e-2 * depth * tilt   # second order only: < 1 % of how far the centre moves
    assert np.sqrt(np.mean(np.square(turned))) == pytest.approx(np.sqrt(2) * tilt, rel=0.15)


def _pose_at(c: np.ndarray, R: np.ndarray, sigma_c: float) -> Pose:
    """A camera at centre ``c`` whose covariance is ``sigma_c`` m on the centre (isotropic) alone."""
    t = -R @ c
    cov = np.zeros((6, 6))
    cov[3:, 3:] = R @ (np.eye(3) * sigma_c ** 2 / 3) @ R.T   # dt = -R dC (rotation held)
    return Pose(R, t, cov)


def test_rough_surface_ties_are_dropped_only_for_the_sequences_they_bias():
    """choose_smooth: a sequence whose two solutions (all ties / smooth-surface ties only) differ by
    no more than their difference's spread if both were unbiased keeps all ties (they only add
    precision); one that moved by several times that spread drops the rough ones (they were biased),
    tested on the camera centre and on what the camera sees."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(0)
    sa, ss = 0.03, 0.05                  # sigma with all ties, with the smooth ones only
    spread = np.sqrt(ss ** 2 - sa ** 2)  # 0.04 m
    all_ties, smooth = {}, {}
    for q, shift in (("seqA", 0.0), ("seqB", 0.25)):   # seqB: the rough ties pulled it 25 cm
        for k in range(12):
            c = rng.normal(size=3) * 10 + np.array([0.0, 0.0, 100.0])
            R = dji_to_rotation(rng.uniform(0, 360), -45.0, 0.0)
            n = f"queries/{q}/{k:04d}_W.jpg"
            moved = c + np.array([shift, 0.0, 0.0]) + rng.normal(size=3) * spread / np.sqrt(3)
            all_ties[n] = (_pose_at(moved, R, sa), 104.0)
            smooth[n] = (_pose_at(c, R, ss), 104.0)
    for on in ("centre", "footprint", "both"):
        got = register.choose_smooth(all_ties, smooth, 2.0, on)
        assert not got["seqA"]["smooth_only"] and got["seqB"]["smooth_only"], got
        assert got["seqA"]["limit_m"] == pytest.approx(2 * spread)
    # a camera that swings about the ground it sees (turned 0.1 deg about that point: its centre
    # moves 18 cm, its view not at all) is no bias on its footprint, but it was on its centre
    swung = {}
    for n, (p, depth) in all_ties.items():
        X = p.center + p.R.T @ np.array([0.0, 0.0, depth])
        dR = Rotation.from_rotvec(np.radians(0.1) * np.array([0.0, 1.0, 0.0])).as_matrix()
        R2 = p.R @ dR
        swung[n] = (_pose_at(X - R2.T @ np.array([0.0, 0.0, depth]), R2, ss), depth)
    assert register.choose_smooth(all_ties, swung, 2.0, "centre")["seqA"]["smooth_only"]
    got = register.choose_smooth(all_ties, swung, 2.0, "footprint")["seqA"]
    assert not got["smooth_only"] and got["shift_m"] < 1e-6, got
    got = register.choose_smooth(all_ties, swung, 2.0, "both")["seqA"]   # the default
    assert not got["smooth_only"] and got["centre_shift_m"] > got["centre_limit_m"], got
    # the rough ties' clicks leave only the chosen sequences' photos
    clicks = {"auto_1": {"reference/R1.jpg": (1, 2), "queries/seqA/0001_W.jpg": (3, 4), "queries/seqB/0001_W.jpg": (5, 6)},
              "auto_2": {"reference/R1.jpg": (1, 2), "queries/seqB/0002_W.jpg": (7, 8)},
              "tp1": {"reference/R1.jpg": (1, 2), "queries/seqB/0002_W.jpg": (7, 8)}}
    out = register._without(clicks, {"auto_1", "auto_2"}, {"seqB"})
    assert out == {"auto_1": {"reference/R1.jpg": (1, 2), "queries/seqA/0001_W.jpg": (3, 4)},
                   "tp1": clicks["tp1"]}
