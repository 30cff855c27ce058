"""Reproducible poses (issue 49): the same photos and settings give the same poses, bit for bit.

Where the run-to-run spread came from (tiny sample, seeds 0-2, two main jobs each, then each stage
rerun from identical inputs; docs/benchmarks.md, "Reproducible poses (issue 49)"). Not the feature
databases (keypoints, matches and two-view geometries identical run to run: every RANSAC of gtkit's
and pycolmap's feature matching is seeded), nor the registration, localization or tracking run from
identical inputs (identical), nor NumPy / OpenCV generators (each estimator seeds its own). Three
things, all inside pycolmap:

- **Ceres bundle adjustments on more than one thread** sum the cost, gradient and Schur complement in
  the order the threads finish: the last bits differ run to run (tiny seed 1: the reference block
  1e-9 m apart). The SfM's discrete decisions (a point filtered or kept) can turn those bits into
  millimetres (tiny seed 0: the reference block 3.8 mm median / 30 mm worst apart, its pseudo-GT
  0.03 / 0.22 m). pycolmap runs a BA on one thread below 50,000 residuals, so only the larger ones.
- **the incremental mapper on more than one thread** (its RANSACs run in parallel, trials handed out
  to whichever thread asks): tiny seed 2's 3-photo sequence was mapped from either of two starting
  points, coin-flip, its block 0.8 m / 9.5 deg apart in its own frame (pseudo-GT 0.04 / 0.12 m).
- **an unseeded RANSAC**: the pose-prior BA's alignment (``PosePriorBundleAdjustmentOptions``,
  random_seed -1) draws from the calling thread's generator, whose state depends on what ran before
  in the process: each ``gtkit sfm`` in a fresh process gave the same block, three in one process
  three blocks. Seeded in :mod:`gtkit.sfm.prior_ba`.

What this module gives the stages (their ``reproducible`` setting):

- :func:`ba_threads`: the Ceres threads of a BA, 1 where ``reproducible``;
- :func:`single_thread_mapper`: pycolmap's incremental mapper on one thread (its BAs and RANSACs;
  feature extraction and matching have their own options and keep theirs);
The process-wide generators (NumPy's and Python's global ones, OpenCV's and pycolmap's per thread) are
not reset per stage: no stage draws from them (the registration alone and inside the main job gave
the same poses; the main job twice gives byte-identical poses, tests/test_reproducible_poses.py). A
library that starts to draw from them would show there as poses that differ between the two runs.
"""
from __future__ import annotations

ONE_THREAD_RESIDUALS = 2 ** 31 - 1   # pycolmap's "multi-threaded from this many residuals" made unreachable


def ba_threads(num_threads: int, reproducible: bool) -> int:
    """The Ceres threads of one bundle adjustment: 1 where the run must be reproducible bit for bit."""
    return 1 if reproducible else num_threads


def single_thread_mapper(options, reproducible: bool):
    """``options`` (pycolmap.IncrementalPipelineOptions) on one thread where ``reproducible``: its BAs
    and its RANSACs (``options.get_mapper()`` hands the pipeline's threads to the mapper's). Returned."""
    if reproducible:
        options.num_threads = 1
        options.mapper.num_threads = 1
        options.ba_min_num_residuals_for_cpu_multi_threading = ONE_THREAD_RESIDUALS
    return options
