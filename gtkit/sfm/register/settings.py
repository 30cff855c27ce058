"""The registration stage's settings (``[register]`` in project.toml) and its name."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ...errors import GtkitError
from ...project import PROJECT_FILE
from ..crossmatch import CrossMatchSettings
from ..extend_reference import ExtendSettings
from ..guided_clicks import GuidanceSettings
from ..tie_surface import SmoothSurfaceSettings
from .real_photo_terms import SigmaSettings

STAGE = "register"


@dataclass
class BootstrapSettings:
    """``[register.bootstrap]``: a query sequence without 3 usable clicked tie points is placed by its
    photos' automatic matches to the reference block's 3D points (:func:`bootstrap_sequence`)."""
    enabled: bool = True
    # how far (px) a reference point may project from its match around a photo's metadata pose:
    # consumer GPS (5-15 m) and gimbal (1-3 deg) errors move the projections by 30-150 px; a photo
    # that finds nothing is tried again at twice this
    radius_px: float = 200.0
    # photos whose matches must agree on one Sim(3) (one photo alone is not checked by another)
    min_photos: int = 2
    max_pairs: int = 2000          # query-reference 3D point pairs the Sim(3) RANSAC draws from
    # a matched photo's pose farther than this from the prior that guided it is a false match
    max_offset_m: float = 60.0
    # a matched photo agrees with the Sim(3) where its block pose, so moved, is within these of the
    # pose its own matches gave it (a false match is tens of metres off)
    agree_m: float = 3.0
    agree_deg: float = 2.0
    # photos with GPS but no gimbal attitude (and no usable block pose): attitudes searched at their
    # GPS position, on up to ``search_photos`` photos of the sequence until one matches
    search_photos: int = 3
    search_yaw_step_deg: float = 20.0
    # (nadir last: a mapping flight's photos held out of it, when the oblique attitudes found nothing)
    search_pitches_deg: list = field(default_factory=lambda: [-25.0, -45.0, -65.0, -90.0])
    # a clicked Sim(3) with fewer inlier tie points than this, or with all of them in one photo, is
    # checked against the photos' automatic matches (where they place the block): farther than
    # ``agree_m`` apart, the automatic placement wins and the report says so (small seed 13: its first
    # 4 clicks, all in one photo, one of them grossly wrong, put seq1 116 m off; checked: 0.056 m). 0: off
    check_clicks_below: int = 8


@dataclass
class UnguidedSettings:
    """``[register.unguided]``: sequences whose photos have no GPS and no attitude."""
    enabled: bool = True
    max_exhaustive: int = 60     # reference photos up to this many: each query photo matched with all
    top_k: int = 12              # else with this many, ranked by visual words
    words: int = 256             # visual words of the ranking's vocabulary (k-means over reference SIFT)
    sample_per_photo: int = 500  # descriptors a photo contributes to the ranking


@dataclass
class CoestimateSettings:
    """``[register.coestimate]``: the query photos co-estimated with a small reference block
    (:mod:`gtkit.sfm.register.coestimate`)."""
    enabled: bool = True
    up_to_photos: int = 40   # reference blocks of at most this many photos (the whole block's BA runs again)
    neighbours: int = 8      # reference photos each query photo is matched with (nearest views)


@dataclass
class RegisterSettings:
    tie_max_px: float = 4.0          # a click farther than this from its triangulated point is a mistake
    sim3_max_error_m: float = 1.5    # Sim(3) RANSAC inlier threshold, metres in the reference frame
    ba_max_tie_px: float = 3.0       # tie observations above this after the robust BA pass are dropped
    # Automatic tie points are plentiful (hundreds a photo, each a SIFT match), so they must fit tighter.
    # Measured against truth on the medium sample: matches on tree canopies (lit from another sun
    # angle in the query and the reference photos) are 1-2 m off in 3D yet within 3 px (median 1.7 px),
    # the others are unbiased with a median of 0.6 px.
    ba_max_auto_px: float = 1.5
    ba_loss_scale_px: float = 2.0    # Cauchy loss scale of the first BA pass
    refine_query_intrinsics: bool = False  # let the joint BA refine every query camera's focal/distortion
    # A query camera its few-photo SfM had to calibrate itself (no cameras.txt, no reference calibration
    # of the same camera: gtkit.sfm.block_cameras) is calibrated in the joint BA from the reference's 3D
    # points its photos see (focal, principal point, distortion; the BA's covariance then holds the
    # calibration's uncertainty) where they hold this many automatic ties a photo (median); 0: never.
    # Issue 55, entry-P10 held out with RTK positions: self-calibrated from 3 photos 92 mm (principal
    # point 22 px off), calibrated from 563 ties 16 mm, the reference's calibration 11 mm
    calibrate_from_ties: int = 50
    # ... and a camera the sequence's SfM took for the reference's by image size alone (no EXIF camera
    # identity, gtkit.sfm.block_cameras) is calibrated from the ties only where that lowers its tie
    # residuals by more than this share (a wrong guess: pixels; the right one: a few %). fountain-P11 /
    # entry-P10 held out: kept 3.8 / 15.8 mm, calibrated from the ties anyway 4.5 / 16.9 mm
    calibration_gain: float = 0.2
    min_tiepoints: int = 3
    ba_max_iterations: int = 100
    num_threads: int = 2
    # the joint BA and the extension's mapper on one thread: the same inputs give the same pseudo-GT bit
    # for bit (gtkit.determinism; [sfm] reproducible does the same for the blocks). Cost: docs/benchmarks.md,
    # "Reproducible poses (issue 49)"
    reproducible: bool = True
    # automatic SIFT tie points between query and reference photos, added to the clicks
    cross: CrossMatchSettings = field(default_factory=CrossMatchSettings)
    # ... kept only where the reference model is a smooth surface (their spot moves with the sun
    # elsewhere; gtkit.sfm.tie_surface)
    smooth_surface: SmoothSurfaceSettings = field(default_factory=SmoothSurfaceSettings)
    # Each photo's reported covariance = the final BA's + a systematic tilt of this many pixels about
    # each image axis, about the ground it sees (the centre shifted so that its median scene point
    # stays put). The BA's covariance holds only what the residuals show; matches between photos
    # under different light shift together, which no residual shows (a spatial jackknife over the
    # ties moved the sequences by 0.2-1.2 cm where they were 3-14 cm off). Calibrated against truth on
    # medium seed 6 (position errors within 2 sigma 82 -> 99 %, rotation 75 -> 95 %), checked on
    # medium seed 5 (85 -> 96 %, 94 -> 100 %). 0: the BA's alone.
    systematic_swing_px: float = 0.15
    # ... added to the sequences whose automatic ties on rough surface the smooth-surface test found
    # biased ("biased"; every medium sequence of seeds 5 and 6), or to every sequence ("all", as
    # before issue 35). Where the test finds no bias the BA's covariance alone already matches the
    # errors: small seeds 13-15, RMS error per camera axis 0.025 / 0.026 / 0.015 m against BA sigmas
    # of 0.023 / 0.025 / 0.013 m; the swing on top (0.03 m an axis at their 0.2 m a pixel) doubled it.
    systematic_swing_where: str = "biased"
    # what else each photo's sigma holds (issue 48): the reference block's own uncertainty where the
    # photo sees it, and the BA's covariance scaled by the measured residual field (real photos)
    sigma: SigmaSettings = field(default_factory=SigmaSettings)
    # the next clicks suggested per sequence (work/register/guided_clicks.json, the GT report, the annotator)
    guidance: GuidanceSettings = field(default_factory=GuidanceSettings)
    # sequences without enough usable clicks: placed by automatic matches to the reference points
    bootstrap: BootstrapSettings = field(default_factory=BootstrapSettings)
    # sequences whose photos have no GPS and no attitude: matched with the reference photos (all, or
    # those ranked first by visual words) and registered into the reference block
    unguided: UnguidedSettings = field(default_factory=UnguidedSettings)
    # photos placed on their own (left out by their sequence's SfM): registered into the reference
    # block by keypoint matches with the reference photos, its points joining as automatic ties
    extend: ExtendSettings = field(default_factory=ExtendSettings)
    # on a small reference block held by its positions: the registered query photos and the reference
    # block adjusted together, as one SfM of all the photos would (gtkit.sfm.register.coestimate)
    coestimate: CoestimateSettings = field(default_factory=CoestimateSettings)


def check_settings(settings: RegisterSettings, root: Path) -> None:
    """The enum-like settings' values, each refused with what it expects (``root``: the project's folder)."""
    if settings.systematic_swing_where not in ("biased", "all"):
        raise GtkitError(f'[register] systematic_swing_where = "{settings.systematic_swing_where}": '
                         'expected "biased" or "all"', root / PROJECT_FILE)
    if settings.smooth_surface.choose not in ("test", "smooth"):
        raise GtkitError(f'[register.smooth_surface] choose = "{settings.smooth_surface.choose}": '
                         'expected "test" or "smooth"', root / PROJECT_FILE)
    if settings.smooth_surface.test_on not in ("both", "footprint", "centre"):
        raise GtkitError(f'[register.smooth_surface] test_on = "{settings.smooth_surface.test_on}": '
                         'expected "both", "footprint" or "centre"', root / PROJECT_FILE)
