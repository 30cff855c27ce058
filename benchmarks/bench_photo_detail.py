"""Do the pixels of a full-size sample photo carry detail? (issue 48)

The same shots of the small site (seed 0) rendered at the small preset's and the fullsize preset's
sensor sizes (two reference eyes, a wide and two zoom photos), and for each: its ground sampling
(median depth / focal), the gradient energy a pixel of the clean render (Sobel, grey levels), the share
of it above half the pixel Nyquist (what a 2x down / up resample removes), and OpenCV SIFT keypoints
a megapixel of the degraded photo (noise, blur as the generator writes it). A world coarser than the
pixels shows as low gradient energy, a small fine share and few keypoints a megapixel.

    python benchmarks/bench_photo_detail.py [--micro auto|off|on] [--out DIR]

``--micro``: the grain below 3 cm (gtkit.synth.shading._MICRO): ``auto`` as the generator compiles it
(fullsize only), ``off`` / ``on`` for every preset (off = the world before issue 48).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gtkit.render.renderer import Renderer  # noqa: E402
from gtkit.synth import flights, photos  # noqa: E402
from gtkit.synth.settings import load_preset  # noqa: E402
from gtkit.synth.shading import MICRO_BELOW_M, finest_footprint_m, world_glsl  # noqa: E402
from gtkit.synth.targets import make_tracks  # noqa: E402
from gtkit.synth.world import build_world, true_mesh  # noqa: E402


def measures(rgb: np.ndarray, img: np.ndarray) -> dict:
    import cv2

    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)

    def energy(a):
        gx, gy = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3)
        return float(np.mean(gx * gx + gy * gy))
    h, w = g.shape
    up = cv2.resize(cv2.resize(g, (w // 2, h // 2), interpolation=cv2.INTER_AREA), (w, h),
                    interpolation=cv2.INTER_CUBIC)
    e = energy(g)
    kp = cv2.SIFT_create().detect(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), None)
    return {"grad_energy": round(e, 1), "fine_share": round(energy(g - up) / e, 3),
            "sift_per_mp": round(len(kp) / (w * h / 1e6))}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--micro", choices=("auto", "off", "on"), default="auto")
    ap.add_argument("--out", type=Path, help="write the photos and the rows (detail.json) here")
    a = ap.parse_args(argv)
    base = load_preset("small", seed=0)
    world = build_world(base, np.random.default_rng([0, 1]))
    mesh = true_mesh(world, base, np.random.default_rng([0, 11]))
    tracks = make_tracks(world, (base.targets.car_speed, base.targets.person_speed), np.random.default_rng([0, 12]))
    rows = []
    for preset in ("small", "fullsize"):
        s = load_preset(preset, seed=0)
        micro = {"on": True, "off": False}.get(a.micro, finest_footprint_m(s) < MICRO_BELOW_M)
        r = Renderer(mesh, world_glsl(world, micro=micro))
        ref = flights.reference_shots(world, s)
        q = flights.query_shots(world, tracks, s, np.random.default_rng([0, 2]))
        wide, zoom = [x for x in q if x.kind == "wide"], [x for x in q if x.kind == "zoom"]
        for sh in (ref[57], ref[58], wide[3], zoom[3], zoom[12]):
            c = s.reference if sh.kind == "reference" else s.queries
            light = photos.sun_lighting(c.sun_azimuth_deg, c.sun_elevation_deg, c.ambient, c.gain)
            t = time.time()
            rgb, depth, _ = photos.render_view(r, sh.camera, sh.pose, light)
            t_render = time.time() - t
            kw = {} if sh.kind == "reference" else {"tint": c.tint, "gain": c.gain}
            img = photos.degrade(rgb, np.random.default_rng(0), blur_sigma=c.blur_sigma_px, noise_sigma=c.noise_sigma, **kw)
            row = {"preset": preset, "micro": micro, "shot": sh.name, "size": f"{sh.camera.width}x{sh.camera.height}",
                   "gsd_m": round(float(np.nanmedian(depth)) / sh.camera.fx, 4), "render_s": round(t_render, 1),
                   **measures(rgb, img)}
            rows.append(row)
            print(json.dumps(row), flush=True)
            if a.out:
                import cv2

                a.out.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(a.out / f"{preset}_{sh.name.replace('/', '_')}"), img[..., ::-1],
                            [cv2.IMWRITE_JPEG_QUALITY, 92])
        r.release()
    if a.out:
        (a.out / "detail.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
