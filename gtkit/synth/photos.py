"""Rendering the photos of a sample site and writing them as DJI-like JPEGs.

A photo = the true world rendered through the shot's true camera and pose (plus the moving
targets at the shot's time, composited by depth), sky where nothing is seen, then the
camera's degradations (exposure, tint, blur, sensor noise, JPEG). Distorted cameras are
rendered as a larger pinhole image and resampled, so no border is lost. Photos larger than the
renderer's framebuffer (``Renderer.MAX_FBO`` px a side: the full-size preset's 24 MP reference and
20 MP zoom photos) are rendered in tiles, each a crop of the same pinhole camera drawn with the
whole view's near / far planes, and pasted together.
"""
from __future__ import annotations

import datetime as dt
import warnings

import numpy as np

from ..camera import Camera
from ..conventions import index_to_pixel, pixel_to_index, rotation_to_dji, wrap_deg
from ..io.exif import write_jpeg_with_meta
from ..io.mesh import Mesh
from ..pose import Pose
from ..render.frustum import near_far
from ..render.renderer import Lighting, Renderer, union_box

SENSOR_WIDTH_MM = {"reference": 13.2, "wide": 6.17, "zoom": 7.6}


def sun_lighting(azimuth_deg: float, elevation_deg: float, ambient: float, gain: float) -> Lighting:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = (float(np.sin(az) * np.cos(el)), float(np.cos(az) * np.cos(el)), float(np.sin(el)))
    return Lighting(d, ambient, gain)


_MAPS: dict = {}


def _distortion_maps(cam: Camera):
    """(padded pinhole camera, remap source map) for a distorted camera; cached per camera."""
    if cam not in _MAPS:
        h, w = cam.height, cam.width
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        xn = cam.image_to_world(index_to_pixel(np.stack([jj, ii], axis=-1)))
        pad_x = int(np.ceil(max(0.0, np.abs(xn[..., 0]).max() * cam.fx - w / 2))) + 2
        pad_y = int(np.ceil(max(0.0, np.abs(xn[..., 1]).max() * cam.fy - h / 2))) + 2
        pin = Camera.pinhole(w + 2 * pad_x, h + 2 * pad_y, cam.fx, cam.fy, cam.cx + pad_x, cam.cy + pad_y)
        _MAPS[cam] = (pin, pixel_to_index(pin.world_to_image(xn)).astype(np.float32))
    return _MAPS[cam]


def _tile_edges(n: int, side: int) -> list[int]:
    """Edges of ceil(n / side) tiles of at most ``side`` px, inner edges on even pixels (so the
    2 x 2 pixel quads the shader's derivatives come from are never split)."""
    k = -(-n // side)
    step = -(-n // k)
    step += step % 2
    return [min(i * step, n) for i in range(k)] + [n]


def render_tiled(r: Renderer, cam: Camera, pose: Pose, lighting: Lighting, side: int | None = None):
    """(rgb, depth) of a pinhole camera of any size: one render where it fits the renderer's
    framebuffer, else tiles of at most ``side`` (default ``Renderer.MAX_FBO``) px a side."""
    side = side or Renderer.MAX_FBO
    if cam.width <= side and cam.height <= side:
        res = r.render(cam, pose, lighting=lighting)
        return res.rgb, res.depth
    near, far = near_far(union_box(r.boxes()), pose) if len(r.boxes()) else (None, None)
    rgb = np.zeros((cam.height, cam.width, 3), np.uint8)
    depth = np.full((cam.height, cam.width), np.nan, np.float32)
    xs, ys = _tile_edges(cam.width, side), _tile_edges(cam.height, side)
    for y0, y1 in zip(ys[:-1], ys[1:]):
        for x0, x1 in zip(xs[:-1], xs[1:]):
            tile = Camera.pinhole(x1 - x0, y1 - y0, cam.fx, cam.fy, cam.cx - x0, cam.cy - y0)
            res = r.render(tile, pose, lighting=lighting, near=near, far=far)
            rgb[y0:y1, x0:x1] = res.rgb
            depth[y0:y1, x0:x1] = res.depth
    return rgb, depth


def _render_pinhole_padded(r: Renderer, cam: Camera, pose: Pose, lighting: Lighting):
    """Render a distorted camera without losing the corners: a padded pinhole, then resample."""
    import cv2

    pin, src = _distortion_maps(cam)
    res_rgb, res_depth = render_tiled(r, pin, pose, lighting)
    rgb = cv2.remap(res_rgb, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    depth = cv2.remap(res_depth, src[..., 0], src[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=np.nan)
    return rgb, depth


def render_view(world_r: Renderer, cam: Camera, pose: Pose, lighting: Lighting,
                target_r: Renderer | None = None, target_mesh: Mesh | None = None):
    """(rgb uint8, depth float32 NaN = sky, target mask) of the true scene."""
    def one(r):
        if cam.has_distortion:
            return _render_pinhole_padded(r, cam, pose, lighting)
        return render_tiled(r, cam, pose, lighting)

    rgb, depth = one(world_r)
    mask = np.zeros(depth.shape, bool)
    if target_r is not None and target_mesh is not None:
        target_r.clear()
        target_r.add_mesh(target_mesh)
        trgb, tdepth = one(target_r)
        mask = np.isfinite(tdepth) & ~(np.isfinite(depth) & (depth < tdepth))
        rgb = rgb.copy()
        rgb[mask] = trgb[mask]
        depth = depth.copy()
        depth[mask] = tdepth[mask]
    sky = ~np.isfinite(depth)
    if sky.any():
        rows = np.linspace(0.0, 1.0, rgb.shape[0])[:, None, None]
        sky_rgb = (np.array([150, 180, 215]) * (1 - 0.3 * rows) + np.array([200, 205, 210]) * 0.3 * rows)
        sky_img = np.broadcast_to(sky_rgb, rgb.shape)
        rgb = rgb.copy()
        rgb[sky] = sky_img[sky].astype(np.uint8)
    return rgb, depth, mask


def degrade(rgb: np.ndarray, rng: np.random.Generator, *, tint=(1.0, 1.0, 1.0), gain: float = 1.0,
            blur_sigma: float = 0.0, noise_sigma: float = 0.0) -> np.ndarray:
    """Exposure/tint, optical blur and sensor noise of a camera."""
    import cv2

    img = rgb.astype(np.float32) * (np.asarray(tint, np.float32) * gain)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if noise_sigma > 0:
        img += rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def exif_time(date_iso: str, seconds: float) -> str:
    t = dt.datetime.fromisoformat(date_iso) + dt.timedelta(seconds=float(seconds))
    return t.strftime("%Y:%m:%d %H:%M:%S")


def photo_meta(frame, pose: Pose, flight_yaw: float, takeoff_z: float, rng: np.random.Generator, *,
               gps_sigma: float, alt_sigma: float, angle_sigma: float, gps: bool = True) -> dict:
    """Noisy priors as a drone writes them: dict of lat, lon, alt, dji tags (and the noise used)."""
    C = pose.center
    Cn = C + np.array([rng.normal(0, gps_sigma), rng.normal(0, gps_sigma), rng.normal(0, alt_sigma)])
    lon, lat, h = frame.local_to_wgs84(Cn)
    with warnings.catch_warnings():  # exact nadir: yaw and roll are not separable (roll := 0)
        warnings.simplefilter("ignore", UserWarning)
        yaw, pitch, roll = rotation_to_dji(pose.R)
    n = rng.normal(0, angle_sigma, 4)
    dji = {"GimbalYawDegree": float(wrap_deg(yaw + n[0])), "GimbalPitchDegree": float(pitch + n[1]),
           "GimbalRollDegree": float(wrap_deg(roll + n[2])), "FlightYawDegree": float(wrap_deg(flight_yaw + n[3])),
           "FlightPitchDegree": 0.0, "FlightRollDegree": 0.0,
           "AbsoluteAltitude": float(h),
           "RelativeAltitude": float(Cn[2] - takeoff_z)}
    out = {"dji": dji, "alt": float(h)}
    if gps:
        out.update(lat=float(lat), lon=float(lon))
    return out


def write_photo(path, rgb, meta: dict, *, timestamp: str, model: str, camera: Camera, sensor_width_mm: float,
                quality: int):
    """The JPEG with EXIF GPS, time, focal length (true and 35 mm equivalent) and DJI XMP."""
    return write_jpeg_with_meta(path, rgb, lat=meta.get("lat"), lon=meta.get("lon"), alt=meta.get("alt"),
                                dji=meta["dji"], timestamp=timestamp, make="DJI", model=model,
                                focal_mm=round(camera.fx * sensor_width_mm / camera.width, 3),
                                focal_35mm=camera.fx * 36.0 / camera.width, quality=quality)
