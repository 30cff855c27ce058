"""A GCP predicted just outside a photo whose 2-sigma ellipse reaches into it is listed, marked
"near the edge" (issue 58: on a real GCP site 2 of 15 clicked GCPs fell just outside the photos
they were clicked in, their sigma 120-600 px there, and got no prediction). A synthetic nadir photo
100 m above flat ground, a block placed to 5 m (sigma ~28 px at fx 554): a GCP 20 px outside is
listed near the edge, one 200 px outside is not; placed to 100 m only (sigma ~550 px, over half the
photo's diagonal), the one 20 px outside is not listed either: nowhere to look. On the tiny sample
(tests/test_gcp_marking.py) 7 of 70 predictions are near the edge, each within 0.5 px of the truth."""
from __future__ import annotations

import numpy as np

from gtkit.camera import Camera
from gtkit.gcp.marking import Block, ellipse_meets_rect, predictions_csv, solve
from gtkit.io.gcp_points import GCPPoint
from gtkit.pose import Pose


def test_ellipse_meets_rect():
    cov = np.diag([30.0 ** 2, 10.0 ** 2])
    assert ellipse_meets_rect((50, 50), cov, 2, 640, 480)          # inside
    assert ellipse_meets_rect((-55, 100), cov, 2, 640, 480)        # 55 px out, 60 px at 2 sigma in x
    assert not ellipse_meets_rect((100, -25), cov, 2, 640, 480)    # 25 px out, 20 px at 2 sigma in y
    assert not ellipse_meets_rect((-45, -45), np.diag([30.0 ** 2] * 2), 2, 640, 480)  # corner: 63.6 px > 60
    assert ellipse_meets_rect((-40, -40), np.diag([30.0 ** 2] * 2), 2, 640, 480)      # corner: 56.6 px


def test_prediction_near_the_edge_is_listed_and_marked():
    cam = Camera.from_hfov(640, 480, 60.0)
    pose = Pose.from_dji(0.0, -90.0, 0.0, np.array([0.0, 0.0, 100.0]))
    block = Block({"a.jpg": pose}, {"a.jpg": cam}, {}, placed=True, sigma_h_m=5.0, sigma_v_m=5.0, how="test")

    def ground_at(u, v):        # the ground point (z = 0) seen at pixel (u, v)
        ray = pose.R.T @ cam.rays(np.array([[u, v]], float))[0]
        return pose.center + ray * (-pose.center[2] / ray[2])

    pts = [GCPPoint("in", ground_at(320, 240)), GCPPoint("edge", ground_at(660, 240)),
           GCPPoint("far", ground_at(840, 240))]
    sol = solve(block, pts, {})
    got = {p.gcp: p for p in sol.predictions}
    assert set(got) == {"in", "edge"}, got
    assert not got["in"].near_edge and got["edge"].near_edge
    assert got["edge"].x > 640 and 20 < got["edge"].sigma_px < 40, got["edge"]
    csv = predictions_csv(sol).splitlines()
    assert csv[0] == "gcp,photo,x,y,sigma_px,source,where"
    assert any(r.startswith("edge,a.jpg,") and r.endswith(",near the edge") for r in csv)
    assert any(r.startswith("in,a.jpg,") and r.endswith(",in the photo") for r in csv)
    block.sigma_h_m = block.sigma_v_m = 100.0
    assert {p.gcp for p in solve(block, pts, {}).predictions} == {"in"}
