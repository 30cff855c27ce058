"""Overlay compositing, the alignment measure, review.json and `gtkit overlay` (headless)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gtkit.cli import main as cli_main
from gtkit.errors import GtkitError
from gtkit.pose import Pose
from gtkit.project import Project
from gtkit.render import overlay as ov
from gtkit.review import read_review, set_status, summary


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from gui.demo import make_demo_project

    return make_demo_project(tmp_path_factory.mktemp("demo") / "site", n_query=2)


def test_compositing_modes_put_render_and_photo_where_they_belong():
    rng = np.random.default_rng(0)
    photo = rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)
    render = rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)
    valid = np.ones((60, 80), bool)
    valid[:, 70:] = False
    assert np.array_equal(ov.blend(photo, render, 0.0, valid), photo)
    assert np.array_equal(ov.blend(photo, render, 1.0, valid)[:, :70], render[:, :70])
    assert np.array_equal(ov.blend(photo, render, 1.0, valid)[:, 70:], photo[:, 70:])  # no model: photo
    s = ov.swipe(photo, render, 0.5, valid)
    assert np.array_equal(s[:, :39], render[:, :39]) and np.array_equal(s[:, 41:], photo[:, 41:])
    c = ov.checkerboard(photo, render, 10, valid)
    assert np.array_equal(c[:10, :10], render[:10, :10]) and np.array_equal(c[:10, 10:20], photo[:10, 10:20])
    e = ov.edges(photo, render, valid)
    assert e.shape == photo.shape and e.dtype == np.uint8
    with pytest.raises(GtkitError):
        ov.compose("nope", photo, render)
    with pytest.raises(GtkitError):
        ov.blend(photo, render[:50])


def _perturbed(pose: Pose, metres=0.0, degrees=0.0) -> Pose:
    if degrees:
        R = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 1.0, 0.0])).as_matrix() @ pose.R
        return Pose.from_center(R, pose.center)
    return Pose.from_center(pose.R, pose.center + np.array([metres, 0.0, 0.0]))


def test_alignment_near_zero_at_true_pose_and_larger_when_off(demo):
    scene = ov.OverlayScene(demo, demo.paths.truth / "poses.txt")
    rows = []
    for name in ("queries/seq1/0000_W.jpg", "reference/R01_000_F.jpg"):
        photo, _, _, s = scene.render(name, 640)
        pose = scene.poses[name]
        row = []
        for p in (pose, _perturbed(pose, metres=1.0), _perturbed(pose, degrees=1.0)):
            _, rgb, valid, _ = scene.render(name, 640, pose=p)
            row.append(ov.alignment(photo, rgb, valid, scale=s))
        rows.append(row)
    for true, off_m, off_deg in rows:
        assert true.misalignment_px < 0.3 and true.edge_distance_px < 0.5
        assert off_m.misalignment_px > 2.0 and off_deg.misalignment_px > 5.0
        assert off_m.edge_distance_px > 1.5 and off_deg.edge_distance_px > 1.5


def test_review_file_roundtrip_and_errors(tmp_path):
    f = tmp_path / "review.json"
    assert read_review(f) == {}
    set_status(f, "queries/a.jpg", "accept", misalignment_px=0.4)
    set_status(f, "queries/b.jpg", "needs-work", "pose off")
    set_status(f, "queries/a.jpg", "reject")
    r = read_review(f)
    assert r["queries/a.jpg"]["status"] == "reject" and r["queries/b.jpg"]["note"] == "pose off"
    assert summary(r) == {"accept": 0, "reject": 1, "needs-work": 1}
    set_status(f, "queries/b.jpg", None)
    assert list(read_review(f)) == ["queries/a.jpg"]
    with pytest.raises(GtkitError):
        set_status(f, "x.jpg", "maybe")
    f.write_text('{"a.jpg": "accept", "b.jpg": "needs-work"}')  # a plain hand-written mapping
    assert {k: v["status"] for k, v in read_review(f).items()} == {"a.jpg": "accept", "b.jpg": "needs-work"}
    f.write_text('{"format": "gtkit-review", "images": {"a": {"status": "meh"}}}')
    with pytest.raises(GtkitError, match="review.json"):
        read_review(f)


def test_gtkit_overlay_command_writes_pngs_and_measures(demo, tmp_path, capsys):
    import cv2

    out = tmp_path / "ov"
    rc = cli_main(["overlay", str(demo.paths.root), "--poses", str(demo.paths.truth / "poses.txt"),
                   "--out", str(out), "--max-side", "400", "--images", "queries/seq1/0001_W.jpg"])
    assert rc == 0
    for m in ov.MODES:
        img = cv2.imread(str(out / f"queries__seq1__0001_W_{m}.png"))
        assert img is not None and img.shape[:2] == (300, 400)
    s = json.loads((out / "alignment.json").read_text())
    assert s["images"]["queries/seq1/0001_W.jpg"]["misalignment_px"] < 0.5
    # without poses: a clear one-line error naming where the poses were expected
    assert cli_main(["overlay", str(demo.paths.root)]) == 2
    assert "register" in capsys.readouterr().err


def test_overlays_resume_image_by_image_and_redo_only_what_changed(demo, tmp_path):
    """A stopped run keeps what it finished; a re-run renders only images whose pose (or settings,
    model, photo) changed, and reports the same measures."""
    from gtkit.io.poses import read_poses, write_poses

    poses = read_poses(demo.paths.truth / "poses.txt")
    names = [*sorted(n for n in poses if n.startswith("queries/"))[:2],
             *sorted(n for n in poses if n.startswith("reference/"))[:1]]
    pf = tmp_path / "poses.txt"
    write_poses(pf, {n: poses[n] for n in names})
    out, st = tmp_path / "ov", ov.OverlaySettings(max_side=320, modes=("blend",))
    seen = []

    def stop_after_two(k, n, name, a):
        seen.append(name)
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ov.write_overlays(demo.paths.root, pf, out, st, progress=stop_after_two)
    assert not (out / "alignment.json").is_file() and len((out / ov.PARTIAL).read_text().splitlines()) == 2
    s = ov.write_overlays(demo.paths.root, pf, out, st)
    assert s["n_rendered"] == 1 and sorted(s["images"]) == names and not (out / ov.PARTIAL).exists()
    full = ov.write_overlays(demo.paths.root, pf, tmp_path / "ov_fresh", st)
    for n in names:   # reused measures equal a fresh run's
        assert s["images"][n]["misalignment_px"] == pytest.approx(full["images"][n]["misalignment_px"], abs=1e-6)
    assert ov.write_overlays(demo.paths.root, pf, out, st)["n_rendered"] == 0
    # one pose moved by 0.5 m: that image alone is redone, and its misalignment grows
    moved = dict((n, poses[n]) for n in names)
    p0 = moved[names[0]]
    moved[names[0]] = Pose(p0.R, p0.t + np.array([0.5, 0.0, 0.0]))
    write_poses(pf, moved)
    s2 = ov.write_overlays(demo.paths.root, pf, out, st)
    assert s2["n_rendered"] == 1
    assert s2["images"][names[0]]["misalignment_px"] > s["images"][names[0]]["misalignment_px"] + 0.5
    assert s2["images"][names[1]] == s["images"][names[1]]
    # other settings: everything is redone
    assert ov.write_overlays(demo.paths.root, pf, out, ov.OverlaySettings(max_side=256, modes=("blend",)))[
        "n_rendered"] == 3


def test_default_poses_are_the_register_stage_plus_reference_block(demo, tmp_path):
    import shutil

    from gtkit.io.poses import read_intrinsics, read_poses, write_intrinsics, write_poses

    root = tmp_path / "site"
    shutil.copytree(demo.paths.root, root)
    poses, cams = read_poses(root / "truth/poses.txt"), read_intrinsics(root / "truth/intrinsics.txt")
    for stage, prefix in (("register", "queries/"), ("sfm_reference", "reference/")):
        sel = {n: p for n, p in poses.items() if n.startswith(prefix)}
        write_poses(root / "work" / stage / "poses.txt", sel)
        write_intrinsics(root / "work" / stage / "intrinsics.txt", {n: cams[n] for n in sel})
    scene = ov.OverlayScene(Project.load(root))
    assert scene.pose_file == root / "work/register/poses.txt"
    assert set(scene.images()) == set(poses)
