"""Rig calibration on rendered wide/zoom pairs with a known relative rotation (issue 8)."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, zoom as nd_zoom
from scipy.spatial.transform import Rotation

from gtkit.camera import Camera
from gtkit.errors import GtkitError
from gtkit.io.mesh import Mesh, MeshPart
from gtkit.pose import Pose
from gtkit.render.renderer import Renderer
from gtkit.track.rig import RigCalibrationSettings, Rig, ZoomSetting, calibrate_pairs, rig_errors


def textured_ground(size=400.0, tex=2048, seed=0):
    """A flat square of ``size`` metres with multi-scale random texture (features 0.5-20 m)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((tex, tex))
    for octave, amp in ((16, 1.0), (64, 0.8), (256, 0.8), (1024, 0.5)):
        n = rng.standard_normal((octave, octave))
        img += amp * nd_zoom(n, tex / octave, order=1)[:tex, :tex]
    img = gaussian_filter(img, 1.0)
    img = np.clip((img - np.percentile(img, 1)) / (np.percentile(img, 99) - np.percentile(img, 1)), 0, 1)
    rgb = (np.stack([img, img ** 1.3, img ** 0.8], -1) * 255).astype(np.uint8)
    h = size / 2
    v = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    return Mesh([MeshPart(v, np.array([[0, 1, 2], [0, 2, 3]]), uv=uv, texture=rgb)])


WIDE = Camera.from_hfov(640, 480, 82.0)
ZOOM_TRUE = Camera.pinhole(640, 480, 4.5 * WIDE.fx)
ZOOM2_TRUE = Camera.pinhole(640, 480, 1.6 * ZOOM_TRUE.fx)
R_ZW = Rotation.from_euler("xyz", [1.2, -1.8, 0.6], degrees=True).as_matrix()
OFFSET = np.array([0.06, 0.02, 0.0])


@pytest.fixture(scope="module")
def pairs():
    r = Renderer(textured_ground())
    rig_true = Rig(R_ZW, OFFSET, [ZoomSetting(ZOOM_TRUE)])
    rng = np.random.default_rng(1)
    images = {}
    for k in range(9):  # six pairs at the first zoom setting, three at a second (1.6x longer)
        C = np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(90, 140)])
        wide = Pose.from_dji(rng.uniform(-180, 180), rng.uniform(-90, -60), 0.0, C)
        images[f"{k}_W"] = r.render(WIDE, wide).rgb
        images[f"{k}_Z"] = r.render(ZOOM_TRUE if k < 6 else ZOOM2_TRUE, rig_true.zoom_pose(wide)).rgb
    r.release()
    return images


def test_rig_calibration_recovers_rotation_and_focal(pairs, tmp_path):
    # two focal settings (EXIF 10 mm and 16 mm); the nominal focal lengths are 10% off
    nominal = [ZoomSetting(Camera.pinhole(640, 480, ZOOM_TRUE.fx * 0.9), 10.0),
               ZoomSetting(Camera.pinhole(640, 480, ZOOM2_TRUE.fx * 0.9), 16.0)]
    names = [(f"{k}_W", f"{k}_Z") for k in range(9)]
    rig = calibrate_pairs(names, {w: WIDE for w, _ in names}, nominal, {z: int(z[0]) // 6 for _, z in names},
                          RigCalibrationSettings(offset_m=tuple(OFFSET)), pairs.__getitem__)
    err = rig_errors(rig, R_ZW, ZOOM_TRUE)
    f2 = rig.zoom_camera(640, 480, 16.0).fx
    print("rig errors", err, "setting 2 focal err %", 100 * (f2 / ZOOM2_TRUE.fx - 1), rig.info["median_px"])
    assert rig.info["n_pairs"] >= 7
    assert err["rotation_err_deg"] < 0.05
    assert abs(err["focal_err_pct"]) < 0.5
    assert abs(100 * (f2 / ZOOM2_TRUE.fx - 1)) < 0.5
    assert np.isclose(rig.zoom_camera(640, 480, 10.0).fx, rig.settings[0].camera.fx)
    # round trip through the file, and the zoom pose composes as documented
    rig.save(tmp_path / "rig.json")
    back = Rig.load(tmp_path / "rig.json")
    assert np.allclose(back.R_zw, rig.R_zw) and np.allclose(back.offset, OFFSET)
    assert np.isclose(back.zoom_camera(640, 480).fx, rig.zoom_camera(640, 480).fx)
    w = Pose.from_dji(30, -45, 0, [1, 2, 100])
    z = back.zoom_pose(w)
    assert np.allclose(z.center, w.center + w.R.T @ OFFSET)
    # a focal setting that was not calibrated: the nearest one scaled by the EXIF focal ratio
    assert np.isclose(rig.zoom_camera(640, 480, 32.0).fx, 2 * rig.zoom_camera(640, 480, 16.0).fx)


def test_rig_file_errors_name_the_file(tmp_path):
    p = tmp_path / "rig.json"
    with pytest.raises(GtkitError, match="not found"):
        Rig.load(p)
    p.write_text('{"zoom": []}')
    with pytest.raises(GtkitError, match="rig.json"):
        Rig.load(p)
