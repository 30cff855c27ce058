"""Settings of ``gtkit model build`` (one dataclass; each field's default documented)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ModelSettings:
    # which path makes the depth maps: "auto" (COLMAP's PatchMatch on an NVIDIA GPU where pycolmap's CUDA
    # build is installed, else SGBM on the CPU), "sgbm" or "patchmatch" (gtkit.model.patchmatch)
    depth_method: str = "auto"
    max_image_size: int = 1024        # px, longest side of the working images (photos are scaled down to it)
    neighbours: int = 3               # source photos matched against each photo (best first)
    min_neighbours: int = 2           # a photo with fewer usable neighbours is skipped (with its reason)
    max_angle_deg: float = 30.0       # neighbours look within this angle of the photo's viewing direction
    min_baseline_angle_deg: float = 55.0  # angle between a neighbour's baseline and the viewing direction
    baseline_ratio: tuple[float, float] = (0.07, 0.75)  # baseline / scene depth of a usable neighbour
    target_ratio: float = 0.2         # preferred baseline / scene depth
    max_disparities: int = 384        # SGBM search range cap (px); the range comes from the sparse points
    block_size: int = 5               # SGBM matching block (px)
    # OpenCV's SGBM rounds its sub-pixel disparity with an integer division that truncates toward zero,
    # so a negative parabola offset is rounded up: its disparities are too large by this much on average
    # (measured: a photo shifted by every 1/32 px fraction, both orientations averaged as pair_depth does,
    # +0.021 to +0.026 px on 3 sample photos; theory 15/32 of 1/16 px = 0.029 px), which put every
    # surface a few centimetres too high (medium: depth maps 2.4e-4 short, 6 cm at 250 m)
    sgbm_disparity_bias_px: float = 0.024
    # the texture test (a test of the photos, before fusion): a pixel's depth is given up where the photo's
    # grey contrast around it (standard deviation over texture_window x texture_window px of the working
    # picture smoothed by 1.5 px, which leaves ~0.2 of white sensor noise) is below texture_min_contrast DN.
    # On plain ground SGBM's smoothness term spreads disparities over the whole field and the pairs and
    # photos still agree on that false surface (plain-grass variant, tiny: 0.82 / 5.70 m median / p90 off the
    # truth, as dense as elsewhere); given up, the DSM's gap fill interpolates it and marks it. Measured on the
    # tiny plain-grass sample's working pictures (w 15): plain grass 0.18-0.29 DN (1st-10th percentile),
    # textured ground 0.97 / 2.4 DN (1st / 5th percentile). 0 turns the test off.
    texture_min_contrast: float = 1.0
    texture_window: int = 15          # px, side of the window of the texture test (odd)
    # px around a plain area given up with it: SGBM's block and smoothness carry the disparity of a textured
    # edge (a tree's crown) onto the plain ground beside it, ~4.8 m high on the tiny plain-grass square. The
    # plain mask stops ~window/2 + 3 px short of the edge; false fused points over the square's ground
    # (|dz| > 1 m) with margin 0 / 8 / 16 / 20 px: 8623 / 5080 / 585 / 269 (no test: 10193), fused points
    # elsewhere lost 1.1 / 2.6 / 3.9 / 4.5 % (their error vs truth p90 0.371 m without the test -> 0.332 m)
    texture_margin_px: int = 20
    pair_agree: float = 0.01          # relative depth agreement between pairs / between photos
    min_pair_agree: int = 1           # pairs that must agree on a pixel's depth (fusion checks it against other photos)
    min_view_agree: int = 1           # other photos' depth maps that must agree at fusion
    region_margin: float = 0.5        # model the camera centres' box grown by this x the median scene depth
    fusion_stride: int = 2            # back-project every n-th pixel of each depth map
    voxel_m: float = 0.25             # fused points are averaged per voxel of this size
    fusion_cell_m: float = 100.0      # fusion keeps its points on disk in cells of this size (memory: one cell)
    poisson_depth: int = 0            # octree depth of the Poisson surface (0: cells of about 2 voxels)
    # surface farther than this from every fused point is cut away. Where the texture test gave ground up,
    # the Poisson surface goes on beyond the last points and bulges: the DSM took that band for measured and
    # the gap fill started from it. Plain-grass square (tiny, after the gap fill), DSM error vs truth median /
    # p90 with 3.0 / 2.0 / 1.5 / 1.0 m: 1.20 / 1.70, 0.79 / 1.34, 0.63 / 1.18, 0.56 / 1.13 m; the DSM
    # elsewhere 0.055 / 0.233, 0.053 / 0.189, 0.052 / 0.175, 0.050 / 0.162 m
    trim_m: float = 1.5
    max_triangles: int = 600_000      # simplification budget (pymeshlab quadric edge collapse), per surface tile
    tile_m: float = 350.0             # a site wider than this is reconstructed (and written) in tiles of at most this size
    tile_overlap_m: float = 20.0      # points this far around a tile go into its surface too
    colour_balance: bool = True       # per-photo, per-channel gains that even out the colours at texture seams
    texture_size: int = 1024          # px, longest side of the photos the texture is cut from
