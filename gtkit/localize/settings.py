"""Settings of the localize stage (its features and retrieval), apart from the stage so that
render-db can read the priors that choose its views without importing the stage."""
from __future__ import annotations

from dataclasses import dataclass

from .pnp import PnPSettings


@dataclass(frozen=True)
class FeatureSettings:
    extractor: str = "sift"
    max_keypoints: int = 4000          # per query image
    # Per database view. SIFT on a 640 x 480 view costs ~55 ms of detection (OpenCV's first octave is
    # the view doubled) + ~25 us a descriptor (1 thread): 3000 -> 2000 keypoints is 132 -> 109 ms CPU.
    # Small seeds 1, 2, 6 (28 queries each): 3000 and 2000 both localize 100 / 100 / 100 %; 1500 loses
    # a query at (1m,1deg) on seeds 1 and 6 (seed 6's seq3/0008, vegetation: 35 inliers at 3000, 33 at
    # 2000, not localized at 1500).
    max_keypoints_db: int = 2000
    # query images are resized to this longer side for features; at the fullsize sample's 12 MP wide
    # photos 1024 px localizes 100 %, median 0.022 m, at small's CPU (the database views are 640 px)
    max_side: int = 1024
    contrast_threshold: float = 0.02


# XFeat is not scale invariant: queries are resized to the database views' size (640 px), which on
# the small sample gives R@1 82 % (57 % at 1024 px) and recall(1m,1deg) 89 % (79 %). 1024 keypoints
# a query and a view: LighterGlue's cost grows with the square of the keypoint count (per pair,
# 1 thread, loaded 2-core machine: 1024 -> 0.4 s, 2048 -> 1.5 s, 4000 -> 6.7 s); 2048 lowers the
# median position error from 0.31 to 0.23 m at 3x the CPU time a query.
XFEAT_FEATURES = FeatureSettings(extractor="xfeat", max_keypoints=1024, max_keypoints_db=1024, max_side=640)


@dataclass(frozen=True)
class LocalizeSettings:
    features: FeatureSettings = FeatureSettings()
    matcher: str = "nn-ratio"
    ratio: float = 0.85                # Lowe's ratio for nn-ratio
    descriptor: str = "vlad"
    vlad_words: int = 64
    rotation_prior: bool = True        # filter database views by the IMU prior (paper: on)
    gamma_o: float = 30.0              # deg, per angle (paper)
    gps_radius_m: float | None = None  # keep views whose camera centre lies within this radius of the GPS prior
    # Position prior (not in the paper, which is GPS-denied; ablation 'no-gps' switches it off), used
    # when the photo has GPS + altitude + gimbal angles: "overlap" ranks the candidates by the overlap
    # predicted from the sensors + prior_vlad_weight x descriptor score (see the module doc);
    # "footprint" ranks first the views whose look-at point (optical axis meets the database's
    # ground level) lies within gps_footprint_radius_m of the query's; None = off.
    position_prior: str | None = "overlap"
    # Weight of the descriptor score next to the predicted overlap (both about 0-1). Measured on the
    # small sample (seed 0, 28 queries, offline over all candidates): R@1 100 % at 0 and 0.25, 96 % at
    # 0.5-1, 79 % at 4; 0.25 keeps the appearance as a tie-break between views of equal predicted overlap.
    prior_vlad_weight: float = 0.25
    # The predicted overlap counts a ground point fully when the view sees it within the first angle
    # (deg) of the query's direction, not at all beyond the second (prior.predicted_overlap). Without
    # it (None) far views at the 70 deg level won the ranking on the medium sample (seed 5) and 27 of
    # 79 queries failed PnP on views 23-34 deg away.
    prior_angle_deg: tuple[float, float] | None = (15.0, 35.0)
    # 75 m = the largest grid interval alpha_t: every ground point lies within alpha_t/sqrt(2) = 53 m
    # of a grid position of every level, leaving ~20 m for GPS/altitude error (position_prior "footprint").
    gps_footprint_radius_m: float = 75.0
    # A photo with GPS but no gimbal angles (consumer cameras; the position prior "overlap" needs the
    # attitude): the views whose camera centre lies within 0.75 x their level's grid interval (every
    # point is within interval / sqrt(2) of a grid position) + this margin for the GPS error of the
    # query's GPS position (horizontally) come first, by descriptor score; None = off.
    no_attitude_radius_m: float | None = 20.0
    top_k: int = 3                     # retrieved views per query (paper)
    # When PnP fails on the top-k views, try the next top-k of the ranking, up to this many more times
    # (0 = the paper). Costs time only on queries that would otherwise fail (at most
    # (1 + fallback_rounds) * top_k matchings, ~0.2 s each). VLAD ranks the right view of repetitive
    # fields (the small sample's vegetation sequence) 5th-13th of ~20-40 rotation-prior candidates, so a
    # GPS-denied run needs up to 4 rounds there; with the GPS footprint prior none is needed.
    fallback_rounds: int = 5
    # A pose whose first-order position sigma (1-sigma radius, inflated as in PnPSettings) exceeds this
    # is not reported: it is a failed round (the next views are tried) and, if no round does better,
    # the query fails with the rejected pose kept in status.json. On the small sample (seeds 0, 1:
    # 56 localized queries) the largest sigma of a pose within 1.2 m of the truth was 1.5 m, and the
    # error was at most 3.8 sigma. None = report every PnP pose (the paper).
    max_sigma_pos_m: float | None = 2.5
    max_rel_jump: float = 0.03         # depth discontinuity test for lifting (relative)
    pnp: PnPSettings = PnPSettings()   # gravity_deg = gamma_eps (5 deg; paper 2); None = no check
    db_heights: tuple[float, ...] | None = None        # use only these database levels
    db_highest_only: bool = False                      # use only the highest database level
    db_paper_pitches: tuple[float, ...] | None = None  # use only these paper pitches (0 = nadir)
    # Which database views get local features and a global descriptor: "reachable" = only the views
    # some query's retrieval can rank within its top_k x (1 + fallback_rounds) from its sensor priors
    # alone (:func:`reachable_views`; a query without a position prior reaches every view its
    # rotation prior keeps), "all" = every view (the paper's offline step). The ranking of every
    # query is the same either way (the bound is exact for unit global descriptors); the VLAD codebook
    # is trained on a fixed spread of views (``codebook_views``) in both, so a query's result does
    # not depend on which other queries ran.
    db_features: str = "reachable"
    codebook_views: int = 1500         # at most this many views,
    codebook_share: float = 0.1        # and at most this share of the planned views
    # Which photos are queries is [sfm] query_pattern (gtkit.queries.query_photos); this only narrows
    # them to the names matching a glob (relative to images/, e.g. "queries/seq1/*"); None = all.
    query_subset: str | None = None
