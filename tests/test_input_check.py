"""Every bad input at once (issue 49): `gtkit init` and the stages that read photos look at every
photo and every line of gcp_list.txt / geo.txt / cameras.txt, and name all problems in one line
(a count, each name with its true cause); `--skip-bad-photos` leaves bad photos out knowingly.
Real files throughout: JPEGs with EXIF GPS, an empty one, a text file named .jpg, a JPEG cut short."""
from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from gtkit.errors import GtkitError
from gtkit.geo import GeoFrame
from gtkit.input_check import photo_problem
from gtkit.io.exif import write_jpeg_with_meta
from gtkit.io.odm import read_gcp_list, read_geo_txt
from gtkit.io.poses import read_intrinsics

ROOT = Path(__file__).resolve().parents[1]
GTKIT = [sys.executable, "-m", "gtkit.cli"]
LAT, LON = 30.5, 114.3          # EPSG:32650


def _photo(path: Path, i: int) -> Path:
    rgb = np.random.default_rng(i).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    return write_jpeg_with_meta(path, rgb, lat=LAT + 1e-4 * i, lon=LON + 1e-4 * i, alt=100.0, focal_mm=4.5)


def _bad_three(folder: Path) -> None:
    (folder / "empty.jpg").write_bytes(b"")
    (folder / "notes.jpg").write_text("flight notes: battery 2 swapped at 10:42\n")
    whole = _photo(folder / "whole.tmp", 99).read_bytes()
    (folder / "cut.jpg").write_bytes(whole[: len(whole) // 2])
    (folder / "whole.tmp").unlink()


@pytest.fixture
def photos(tmp_path) -> Path:
    ref = tmp_path / "in" / "ref"
    ref.mkdir(parents=True)
    for i in range(4):
        _photo(ref / f"good_{i}.jpg", i)
    _bad_three(ref)
    return ref


def _gtkit(*args) -> subprocess.CompletedProcess:
    return subprocess.run(GTKIT + [str(a) for a in args], cwd=str(ROOT), capture_output=True, text=True, timeout=120)


def test_photo_problem_names_the_true_cause(photos):
    assert photo_problem(photos / "good_0.jpg") is None
    assert photo_problem(photos / "empty.jpg") == "empty file (0 bytes)"
    assert photo_problem(photos / "notes.jpg").startswith("not an image: a text file")
    assert photo_problem(photos / "cut.jpg").startswith("truncated JPEG (no end-of-image marker")
    assert photo_problem(photos / "absent.jpg") == "missing"
    (photos / "link.jpg").symlink_to(photos / "gone.jpg")
    assert photo_problem(photos / "link.jpg").startswith("a broken link")
    (photos / "gif.jpg").write_bytes(b"GIF89a" + bytes(40))
    assert photo_problem(photos / "gif.jpg") == "not an image gtkit reads: a GIF image"


def test_init_names_all_bad_photos_in_one_run_and_can_leave_them_out(photos, tmp_path):
    seq = tmp_path / "in" / "seq1"
    seq.mkdir()
    for i in range(2):
        _photo(seq / f"000{i}_W.jpg", 10 + i)
    (seq / "0002_W.jpg").write_bytes(b"")
    dst = tmp_path / "site"
    r = _gtkit("init", dst, "--reference", photos, "--queries", seq)
    err = r.stderr.strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "4 bad photos" in err, err
    for name, cause in (("reference/empty.jpg", "empty file (0 bytes)"), ("reference/notes.jpg", "not an image: a text file"),
                        ("reference/cut.jpg", "truncated JPEG"), ("queries/seq1/0002_W.jpg", "empty file")):
        assert f"{name}: {cause}" in err, (name, err)
    assert "--skip-bad-photos" in err and "good_" not in err
    assert not dst.exists()                                       # nothing written
    # knowingly left out: said, counted, listed in the project
    r = _gtkit("init", dst, "--reference", photos, "--queries", seq, "--skip-bad-photos")
    assert r.returncode == 0, r.stderr
    assert "left out 4 bad photos" in r.stdout and "reference/cut.jpg: truncated JPEG" in r.stdout
    conf = tomllib.loads((dst / "project.toml").read_text())
    left = conf["imports"]["photos"]["left_out"]
    assert sorted(left) == ["queries/seq1/0002_W.jpg", "reference/cut.jpg", "reference/empty.jpg", "reference/notes.jpg"]
    assert left["reference/empty.jpg"] == "empty file (0 bytes)"
    assert sorted(p.name for p in (dst / "images/reference").iterdir()) == [f"good_{i}.jpg" for i in range(4)]
    assert sorted(p.name for p in (dst / "images/queries/seq1").iterdir()) == ["0000_W.jpg", "0001_W.jpg"]


def test_every_bad_line_of_gcp_geo_cameras_listed_at_once(photos, tmp_path):
    gcp, geo, cams = tmp_path / "gcp_list.txt", tmp_path / "geo.txt", tmp_path / "cameras.txt"
    gcp.write_text("EPSG:32650\n"
                   "241873.0 3379486.0 10.0 100 200 good_0.jpg g1\n"
                   "241873.0 3379486.0 ten 100 200 good_1.jpg g1\n"          # line 3: not a number
                   "241880.0 3379490.0 10.0 100\n"                          # line 4: too few fields
                   "241999.0 3379486.0 10.0 100 200 good_2.jpg g1\n"        # line 5: g1 moved
                   "241873.0 3379486.0 10.0 100 nan good_3.jpg g2\n")       # line 6: not finite
    geo.write_text("EPSG:32650\ngood_0.jpg 241873.0 3379486.0 100\ngood_1.jpg 241873.0\n"
                   "good_2.jpg 241873.0 north 100\ngood_3.jpg 241873.0 3379486.0 100 0 0 0 0.02 0.03 extra fields\n")
    cams.write_text("# name MODEL W H params\ngood_0.jpg PINHOLE 64 48 50 50 32 24\ngood_1.jpg PINHOLE 64 x 50 50 32 24\n"
                    "good_2.jpg FISHEYE 64 48 50 32 24\ngood_3.jpg PINHOLE 64 48 50 50 32\n")
    frame = GeoFrame("EPSG:32650", (241873.0, 3379486.0, 0.0))
    with pytest.raises(GtkitError) as e:
        read_gcp_list(gcp, frame)
    msg = str(e.value)
    assert msg.startswith(f"{gcp}: 4 bad lines: line 3: geo_z 'ten' is not a number; line 4: expected") \
        and "line 5: GCP 'g1' has different coordinates" in msg and "line 6: py is nan" in msg, msg
    with pytest.raises(GtkitError) as e:
        read_geo_txt(geo, frame)
    assert "2 bad lines: line 3: expected 'image geo_x geo_y" in str(e.value) and "line 4: geo_y 'north'" in str(e.value)
    with pytest.raises(GtkitError) as e:
        read_intrinsics(cams)
    msg = str(e.value)
    assert "3 bad lines" in msg and "line 3 (good_1.jpg): width and height" in msg and "'FISHEYE'" in msg \
        and "line 5 (good_3.jpg): camera model PINHOLE needs 4 params" in msg, msg
    # gtkit init: the photos and all three files in one report, one line, nothing written
    r = _gtkit("init", tmp_path / "site", "--reference", photos, "--gcp", gcp, "--geo", geo, "--cameras", cams)
    err = r.stderr.strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert err.startswith("gtkit: error: 4 inputs have problems (nothing was written): 3 bad photos"), err
    for part in ("gcp_list.txt: 4 bad lines", "geo.txt: 2 bad lines", "cameras.txt: 3 bad lines", "line 6: py is nan",
                 "reference/notes.jpg"):
        assert part in err, (part, err)
    assert not (tmp_path / "site").exists()


def test_stages_name_every_bad_photo_before_reading_any(photos, tmp_path):
    """Photos spoilt after `gtkit init` (a copy cut short, a file emptied): `gtkit sfm` and `gtkit run`
    refuse before the first stage with every bad photo named, not the first one the SfM meets."""
    seq = tmp_path / "in" / "seq1"
    seq.mkdir()
    for i in range(2):
        _photo(seq / f"000{i}_W.jpg", 10 + i)
    dst = tmp_path / "site"
    assert _gtkit("init", dst, "--reference", photos, "--queries", seq, "--skip-bad-photos", "--copy").returncode == 0
    ref, q = dst / "images/reference", dst / "images/queries/seq1"
    (ref / "good_1.jpg").write_bytes(b"")
    data = (ref / "good_2.jpg").read_bytes()
    (ref / "good_2.jpg").write_bytes(data[:200])
    (q / "0001_W.jpg").write_text("not a photo\n")
    r = _gtkit("sfm", dst, "--block", "reference")
    err = r.stderr.strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "2 bad photos: reference/good_1.jpg: empty file" in err and "reference/good_2.jpg: truncated JPEG" in err, err
    r = _gtkit("run", dst)
    err = r.stderr.strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "3 bad photos" in err and "queries/seq1/0001_W.jpg: not an image: a text file" in err, err
    assert not (dst / "work" / "sfm_reference").exists()           # no stage started
    # each command that reads photos checks them first, alone too (not only inside `gtkit run`)
    for cmd, n in ((("render-db", dst), 1), (("overlay", dst), 3), (("model", "build", dst), 2),
                   (("track", "calibrate", dst), 1)):
        r = _gtkit(*cmd)
        err = r.stderr.strip()
        assert r.returncode == 2 and len(err.splitlines()) == 1 and "Traceback" not in r.stderr, (cmd, r.stderr)
        assert f"{n} bad photo" in err and ("queries/seq1/0001_W.jpg" in err or n == 2), (cmd, err)


def test_many_bad_photos_counted_named_and_all_in_a_file(tmp_path):
    from gtkit.input_check import SHOWN, BadInputs, require_good_photos
    from gtkit.project import Project

    proj = Project.create(tmp_path / "site", GeoFrame("EPSG:32650", (0.0, 0.0, 0.0)), "many")
    ref = proj.paths.reference_images
    ref.mkdir(parents=True)
    _photo(ref / "good.jpg", 0)
    for i in range(SHOWN + 5):
        (ref / f"bad_{i:02d}.jpg").write_bytes(b"")
    with pytest.raises(BadInputs) as e:
        require_good_photos(proj, ("reference",))
    report = proj.paths.work / "errors" / "bad_photos.txt"
    msg = str(e.value)
    assert f"{SHOWN + 5} bad photos (all {SHOWN + 5} in {report})" in msg and "... and 5 more" in msg, msg
    assert len(e.value.problems) == SHOWN + 5 and "good.jpg" not in msg
    lines = report.read_text().splitlines()
    assert len(lines) == SHOWN + 5 and lines[0] == "reference/bad_00.jpg\tempty file (0 bytes)"
