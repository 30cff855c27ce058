"""Register each query block to the georegistered reference block through tie points, then
refine everything in one joint bundle adjustment with the reference block held fixed.

Per sequence:
1. place every tie point in the reference block (fixed, georegistered poses) and in the query
   block (its SfM poses): triangulated from its clicks where it has two or more (a click that
   disagrees with the others by more than ``tie_max_px`` is dropped as a gross mistake), else
   its one click is lifted to 3D with the depth of the block's own 3D points around it.
2. robust Sim(3) (LO-RANSAC) from query-block to reference positions; tie points off the fit by
   more than ``sim3_max_error_m`` are outliers. Fewer than 3 usable tie points, collinear ones,
   or a failed fit: the sequence is an error with its reason (never a prior pose).
3. transform the query block.
A sequence without 3 usable clicks (no ``tiepoints.json`` is no clicks) is placed without them
(:func:`bootstrap_sequence`, ``[register.bootstrap]``): each of its photos is matched to the
reference block's 3D points around the pose its metadata claims (GPS + gimbal; else its pose in
the block's own GPS georegistration; else, with GPS alone, a grid of attitudes at its GPS
position) within a radius that covers consumer GPS (:func:`gtkit.sfm.crossmatch.match_photo_wide`),
and the Sim(3) most matched photos agree with places the block. A sequence this cannot hold is an
error that names why and asks for clicks there (``needs_clicks`` in the record, the GT report's
"Sequences that need clicks").
Automatic tie points (SIFT matches between each query photo and the reference photos looking the
same way, see :mod:`gtkit.sfm.crossmatch`) join the clicks from pass b on; they are not listed.
Then one joint bundle adjustment (the reference photos holding tie clicks keep their poses and
intrinsics fixed; each registered query block enters with its own 3D points; each tie point is
a 3D point observed in both blocks and so ties them together), in passes:
a. robust (Cauchy) BA with the Sim(3) inliers;
b. every tie point of the registered sequences is re-triangulated from all its clicks with the
   refined poses; clicks off by more than ``ba_max_tie_px`` are dropped (listed as mistakes),
   the rest (Sim(3) outliers of step 2 included, when now consistent) re-enter;
c. final least-squares BA; its covariance gives each query photo's pose uncertainty.

The package, module by module: :mod:`.settings` (``[register]``), :mod:`.clicked` (step 1-2: tie points
placed from their clicks, the clicked Sim(3)), :mod:`.bootstrap` (a sequence placed without clicks),
:mod:`.reference` (the reference block as the stage matches photos to it), :mod:`.sequences` (each
sequence placed, or its error), :mod:`.joint` (the joint model and passes a-c), :mod:`.tie_bias` (the
smooth-surface test), :mod:`.uncertainty` (each photo's covariance), :mod:`.record` (registration.json
and the other outputs) and :mod:`.stage` (:func:`run`).
"""
from ..crossmatch import CrossMatchSettings
from ..extend_reference import ExtendSettings
from ..guided_clicks import COVARIANCE_FILE, GUIDANCE_FILE, GuidanceSettings
from ..tie_surface import SmoothSurfaceSettings
from .bootstrap import Bootstrap, bootstrap_sequence
from .clicked import TieStatus, depth_from_model, register_sequence, sim3_disagreement, weak_click_support
from .joint import Joint, build_joint, point_reprojection_errors, retriangulate_ties
from .settings import STAGE, BootstrapSettings, RegisterSettings
from .stage import run
from .tie_bias import _without, choose_smooth, solution_shift, tie_test_words
from .uncertainty import swing_covariance

__all__ = ["COVARIANCE_FILE", "GUIDANCE_FILE", "STAGE", "Bootstrap", "BootstrapSettings", "CrossMatchSettings",
           "ExtendSettings", "GuidanceSettings", "Joint", "RegisterSettings", "SmoothSurfaceSettings", "TieStatus",
           "_without", "bootstrap_sequence", "build_joint", "choose_smooth", "depth_from_model",
           "point_reprojection_errors", "register_sequence", "retriangulate_ties", "run", "sim3_disagreement",
           "solution_shift", "swing_covariance", "tie_test_words", "weak_click_support"]
