"""What the joint BA's covariance leaves out on real photos (issue 48), each term measured on the
project's own blocks (never on truth):

- **The reference block's own uncertainty where a query photo sees it.** The joint BA holds the
  reference photos fixed, so a query photo's covariance says how well it sits on the reference block,
  not how well the block itself is known. :func:`reference_shape` takes the reference block's BA
  covariance (pycolmap, points eliminated; the lens parameters the SfM refined left free, so their
  uncertainty, the lens model's, is in it), carries it to the camera centres and into the block's
  similarity datum (an S-transform over all its centres: what stays after the best similarity, as
  a held-out check or a GPS / GCP fit sees it), scaled by the block's own residual field (below)
  where it exceeds 1. Of each reference photo's centre covariance it keeps
  the part its ground points carry (minus the photo's own resection given the points, which a query
  photo does not inherit). A query photo's term is the mean of that over the reference photos its
  tie points are observed in, weighted by their observations (neighbours' errors taken as moving
  together, so nothing averages out). Checked on Brighton (18 real photos, every 5th held out, two
  splits): the 14-photo blocks' and the all-photo block's covariances at 1 px (0.028 / 0.023 and
  0.020 m RMS a camera) would put their misfit on the photos both hold at 0.034 / 0.030 m, it
  measures 0.060 / 0.063 m; each scaled by its own residual field (1.98 / 3.25 and 4.03) they put it
  at 0.056 / 0.057 m.
- **Feature noise at the size the features were found.** The BA takes every observation for an
  independent 1-px measurement, in the photo's own pixels. The SfM finds its features on the photo
  shrunk to ``[sfm] features.max_image_size`` (1600 px): on a larger photo a feature's 1 px there is
  ``long side / 1600`` px of the photo (24 MP reference: 3.75, 12 MP wide: 2.5).
  :func:`feature_noise_px` is that factor (1 for a photo not shrunk); both covariances are scaled by
  its square (measured on the full-size sample, seeds 0 and 1: the reference block's covariance at 1
  photo px put its cameras 0.004 m from where they are, they were 0.014 m off the truth after the best
  similarity; the query photos' stated sigma 0.010 m against errors of 0.029 m; at 1 px of the
  1600-px features both agree with the truth as the 1-MP sample's do, where nothing is shrunk).
- **Feature noise and correlated residuals.**  :func:`residual_variance_factor` measures, over the query photos of a sequence,
  the variance of the residuals' mean in cells of a 4 x 4 image grid, ``n |mean|^2`` per axis (px^2):
  1 px independent noise gives 1, smaller noise less, residuals that move together in a cell (lens
  or rolling-shutter model error, automatic ties of one texture) more. The BA's covariance is scaled
  by it where it exceeds the features' own noise (``feature_noise_px`` squared). It is measured on fitted residuals, which the points and poses have
  partly absorbed (independent 1-px noise on tracks of 2-4 photos reads about 0.6), so it errs
  towards the smaller sigma. Sample sites' sequences: 0.13-0.30 (residuals 0.41 px and nearly
  independent, so unchanged); Brighton: 2.3-3.3 (0.5 px residuals, cell means 10-13x what
  independence gives).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ...pose import Pose, skew
from ...project import read_stage_record
from ..accuracy_claim import SURVEY_GRADE_M
from ..prior_ba import options_refining
from ..database import FeatureSettings

log = logging.getLogger(__package__)


@dataclass
class SigmaSettings:
    """``[register.sigma]``: the terms added to the joint BA's covariance (:mod:`.real_photo_terms`)."""
    reference_shape: bool = True     # the reference block's own uncertainty where the photo sees it
    residual_field: bool = True      # the BA's covariance scaled by the measured cell-mean residual variance
    feature_size: bool = True        # covariances at 1 px of the shrunk image the features were found in
    grid: int = 4                    # cells per image side for the residual field
    min_per_cell: int = 5            # observations a cell needs to count
    # a reference block larger than this: its covariance on the photos the queries tie to and those
    # sharing points with them (a dense covariance of every photo grows as the square of the block)
    max_photos: int = 400


@dataclass
class ReferenceShape:
    ground: dict[str, np.ndarray] = field(default_factory=dict)   # photo -> 3x3 centre covariance (m^2)
    variance_factor: float | None = None   # the block's a-posteriori sigma0^2 (px^2 per axis), stated
    field_factor: float | None = None      # its residual field (:func:`residual_variance_factor`), applied where > 1
    n_photos: int = 0
    seconds: float = 0.0
    # the block's centres against its photos' positions (:func:`position_misfit`): k^2 (the residuals'
    # squared sum, less what the positions' stated accuracy accounts for, over the predicted centre
    # variances), its upper bound at 84 % (:func:`k2_upper`: 5-30 photos measure it loosely), the
    # positions' robust scatter (median |r|, m) and the photos it is measured on; where ``k2_applied``
    # the block's term (and a query sequence's own BA term, features at the same size) is multiplied by
    # ``k2_factor``; where not, the features' pixel is taken no finer than the default's (:func:`sigma_side`)
    k2: float | None = None
    k2_factor: float = 1.0
    k2_scatter_m: float | None = None
    k2_n: int = 0
    k2_applied: bool = False
    k2_reason: str = ""


# k^2 from the positions scales the reference term only where they can test the block's shape: fewer than
# K2_MAX_PHOTOS of them (with more, a fit |r|^2 = a pred + b would separate the positions' noise from the
# block's shape: not done), scattering under K2_MAX_SCATTER_M after the similarity (GPS: Brighton 0.54 m,
# gets none), and their stated accuracy accounting for under half of the residuals
K2_MAX_SCATTER_M = SURVEY_GRADE_M   # positions scattering more are GPS-grade (the accuracy claim's own line)
K2_MIN_PHOTOS = 4
K2_MAX_PHOTOS = 30
K2_CONFIDENCE = 0.84
# the feature size the sigma's pixel is never taken finer than, where k^2 cannot check it: the default's
# (on the real-truth sets at 3200 px the BA's covariance at 1 px was 2-3x too small in sigma, k^2 5-8;
# at 1600 px the factor (3072 / 1600)^2 = 3.69 covered it: docs/benchmarks.md, stop 61)
SIGMA_MIN_FEATURE_SIDE = FeatureSettings().max_image_size


def sigma_side(feature_side: int | None) -> int | None:
    """The feature size a covariance's pixel is taken at where k^2 does not check it: the size the
    features were found at, but no finer than the default's (:data:`SIGMA_MIN_FEATURE_SIDE`)."""
    return min(feature_side, SIGMA_MIN_FEATURE_SIDE) if feature_side else feature_side


def position_misfit(C: np.ndarray, G: np.ndarray, pred: np.ndarray, acc: np.ndarray | None = None
                    ) -> tuple[float | None, float, float]:
    """``C`` (N x 3) the block's centres, ``G`` their photos' positions, ``pred`` each centre's predicted
    variance (trace, the block's units, in its similarity datum), ``acc`` each position's stated
    accuracy (m, 0 where none: one sigma per axis, N values, or N x 2 horizontal and vertical): (k^2,
    median |r| in m, the share of sum |r|^2 the stated accuracy accounts for), r = G minus the best
    similarity of C onto G; k^2 = (sum |r|^2 - (1 - 7 / 3N) sum (2 h^2 + v^2)) / (s^2 sum pred), None
    where pred sums to 0."""
    mc, mg = C.mean(0), G.mean(0)
    A, B = C - mc, G - mg
    U, S, Vt = np.linalg.svd(B.T @ A)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / max(np.sum(A ** 2), 1e-300))
    r = G - (s * (R @ A.T).T + mg)
    rr = np.sum(r ** 2, 1)
    n = len(C)
    noise = 0.0
    if acc is not None:
        a = np.asarray(acc, np.float64).reshape(n, -1)
        hv = a[:, :2] if a.shape[1] >= 2 else np.repeat(a[:, :1], 2, axis=1)
        noise = (1.0 - 7.0 / (3 * n)) * float(np.sum(2.0 * hv[:, 0] ** 2 + hv[:, 1] ** 2))
    den = s ** 2 * float(np.sum(pred))
    share = noise / max(float(rr.sum()), 1e-300)
    return (float((rr.sum() - noise) / den) if den > 0 else None), float(np.median(np.sqrt(rr))), share


def k2_upper(k2: float, n: int, confidence: float = K2_CONFIDENCE) -> float:
    """The upper bound of k^2 at ``confidence`` measured on ``n`` centres (3N - 7 degrees of freedom
    after the similarity): a chi-square's spread, wide on few photos (5 photos: x 1.8, 7: x 1.6)."""
    from scipy.stats import chi2

    dof = max(3 * n - 7, 1)
    return float(k2 * dof / chi2.ppf(1.0 - confidence, dof))


def feature_noise_px(cam, feature_side: int | None) -> float:
    """One pixel of the features, in the photo's own pixels: ``long side / feature_side`` where the
    SfM shrank the photo to ``feature_side`` px to find them, 1 where it did not (or unknown)."""
    if not feature_side:
        return 1.0
    return max(1.0, max(int(cam.width), int(cam.height)) / float(feature_side))


def variance_scale(noise_px: float, field_factor: float | None) -> float:
    """What a covariance computed at 1 px is multiplied by: the features' own pixel squared
    (:func:`feature_noise_px`), or the measured residual field where that is larger."""
    return max(noise_px ** 2, field_factor or 1.0)


def feature_side_of(stage_dir: Path) -> int | None:
    """The long side an SfM block found its features at (its record's ``features.max_image_size``),
    None where it has no record saying so."""
    r = read_stage_record(stage_dir)
    v = ((r.settings.get("features") or {}).get("max_image_size")) if r is not None else None
    return int(v) if isinstance(v, (int, float)) and v > 0 else None


def _similarity_datum(C: np.ndarray, Sc: np.ndarray) -> np.ndarray:
    """``Sc`` (3N x 3N centre covariance) carried into the datum of the best similarity over the
    centres ``C`` (N x 3): the part a translation, rotation and scale of all of them explain removed."""
    n = len(C)
    m = C.mean(0)
    A = np.zeros((3 * n, 7))
    for a in range(n):
        A[3 * a:3 * a + 3, :3] = np.eye(3)
        A[3 * a:3 * a + 3, 3:6] = -skew(C[a] - m)
        A[3 * a:3 * a + 3, 6] = C[a] - m
    P = np.eye(3 * n) - A @ np.linalg.pinv(A)
    return P @ Sc @ P.T


def _own_center_cov(rec, im, pose: Pose) -> np.ndarray | None:
    """A photo's centre covariance from its own observations with the points held (1 px)."""
    cam = rec.cameras[im.camera_id]
    f = cam.mean_focal_length()
    H = np.zeros((6, 6))
    for p in im.points2D:
        if not p.has_point3D():
            continue
        X = rec.points3D[p.point3D_id].xyz
        Xc = pose.R @ X + pose.t
        z = Xc[2]
        if z <= 0:
            continue
        Jproj = f * np.array([[1 / z, 0, -Xc[0] / z ** 2], [0, 1 / z, -Xc[1] / z ** 2]])
        Jr = Jproj @ pose.point_jacobian(X)
        H += Jr.T @ Jr
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    Jc = pose.center_jacobian()
    return Jc @ Hi @ Jc.T


def _sub_block(rec, ids: list[int], names: set[str] | None, max_photos: int) -> list[int]:
    """The photos whose covariance is computed: all, or for a large block the ones named and those
    sharing points with them."""
    if len(ids) <= max_photos or not names:
        return ids
    core = {i for i in ids if rec.images[i].name in names}
    near = set(core)
    for i in core:
        for p in rec.images[i].points2D:
            if p.has_point3D():
                near.update(e.image_id for e in rec.points3D[p.point3D_id].track.elements)
    return sorted(near)


def _centre_covariance(rec, cov, ids: list[int]) -> tuple[list[int], list[Pose], np.ndarray]:
    """The photos with a finite covariance, their poses and their centres' joint covariance (3N x 3N)."""
    # pycolmap's pose covariance is in Ceres' quaternion tangent: its rotation rows are half the
    # rotation vector's (Pose.from_pycolmap)
    D = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])

    def block(i, j):
        try:
            c = cov.get_cam_cov_from_world(i) if i == j else cov.get_cam_cross_cov_from_world(i, j)
        except Exception:  # noqa: BLE001 - a photo pycolmap gives none: left out below
            return None
        c = None if c is None else np.asarray(c, np.float64)
        return c if c is not None and c.shape == (6, 6) and np.all(np.isfinite(c)) else None

    ok = [i for i in ids if block(i, i) is not None]
    poses = [Pose.from_pycolmap(rec.images[i].cam_from_world()) for i in ok]
    Jc = [p.center_jacobian() @ D for p in poses]
    n = len(ok)
    Sc = np.zeros((3 * n, 3 * n))
    for a, i in enumerate(ok):
        Sc[3 * a:3 * a + 3, 3 * a:3 * a + 3] = Jc[a] @ block(i, i) @ Jc[a].T
        for b in range(a + 1, n):
            c = block(i, ok[b])
            c = np.zeros((3, 3)) if c is None else Jc[a] @ c @ Jc[b].T
            Sc[3 * a:3 * a + 3, 3 * b:3 * b + 3] = c
            Sc[3 * b:3 * b + 3, 3 * a:3 * a + 3] = c.T
    return ok, poses, Sc


def _variance_factor(rec, n_poses: int) -> float:
    """The block's a-posteriori variance factor: residual sum of squares over the redundancy."""
    ss, n = 0.0, 0
    for p in rec.points3D.values():
        for e in p.track.elements:
            im = rec.images[e.image_id]
            pr = im.project_point(p.xyz)
            if pr is None:
                continue
            ss += float(np.sum((np.asarray(pr) - im.points2D[e.point2D_idx].xy) ** 2))
            n += 2
    dof = n - 3 * rec.num_points3D() - 6 * n_poses + 7
    return ss / dof if dof > 0 else 1.0


def refined_intrinsics(model_dir: Path) -> dict[int, list[str]]:
    """What the reference SfM refined of each camera (``block.json`` beside its model: "focal",
    "principal point", "distortion"); none where it does not say."""
    f = Path(model_dir).parent / "block.json"
    if not f.is_file():
        return {}
    intr = json.loads(f.read_text()).get("intrinsics", {})
    return {int(c): list(v.get("refined", [])) for c, v in intr.items()}


def block_covariance(rec: pycolmap.Reconstruction, ids: list[int], refined: dict[int, list[str]]):
    """pycolmap's BA covariance (at 1 px) of the block ``rec`` over its photos ``ids`` (points
    eliminated, the gauge held by three points), with the lens parameters of ``refined`` ({camera id:
    "focal", "principal point", "distortion"}) free, the other cameras' held; taken at the block's
    solution (one BA step, one thread: the same covariance run to run). ``rec`` is adjusted in place.
    None where it cannot be computed (the reason logged)."""
    cfg = pycolmap.BundleAdjustmentConfig()
    for i in ids:
        cfg.add_image(i)
    for cid in rec.cameras:
        if not refined.get(cid):
            cfg.set_constant_cam_intrinsics(cid)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    opts = options_refining(refined)
    opts.ceres.solver_options.max_num_iterations = 1
    opts.ceres.solver_options.num_threads = 1    # the same covariance run to run (threads sum in any order)
    ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
    ba.solve()
    try:
        return pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), rec, ba)
    except Exception as e:  # noqa: BLE001 - pycolmap raises for some degenerate problems; None is the answer
        log.warning("block covariance failed: %s", e)
        return None


def reference_shape(ref_model: Path, names: set[str] | None = None, settings: SigmaSettings = SigmaSettings(),
                    feature_side: int | None = None, positions_of=None) -> ReferenceShape | None:
    """The reference block's own uncertainty, per photo (the part its ground points carry, in the
    block's similarity datum; see the module's docstring), from the SfM model in ``ref_model`` with
    the intrinsics free that the SfM refined (``block.json``: their uncertainty is the lens model's).
    ``names``: the photos the queries tie to (a block over ``settings.max_photos`` is cut to them and
    their neighbours); ``feature_side``: the long side its features were found at (:func:`feature_noise_px`);
    ``positions_of``: a function of the photos' names returning their positions (project frame, m) and
    their stated accuracy (m, one value or horizontal and vertical; or None), called only for a block
    k^2 can test (:data:`K2_MIN_PHOTOS` to :data:`K2_MAX_PHOTOS` photos: a large block's positions are
    never read):
    the upper bound of k^2 of the centres against them (:func:`position_misfit`, :func:`k2_upper`)
    scales every ground part where they can test the block (see :data:`K2_MAX_SCATTER_M`); elsewhere
    the features' pixel is taken at :func:`sigma_side`.
    None where the block's covariance cannot be computed."""
    t0 = time.time()
    rec = pycolmap.Reconstruction(str(ref_model))
    ids = _sub_block(rec, sorted(rec.reg_image_ids()), names, settings.max_photos)
    if len(ids) < 3:
        return None
    cov = block_covariance(rec, ids, refined_intrinsics(ref_model))
    if cov is None:
        return None
    n_all = len(ids)
    ids, poses, Sc = _centre_covariance(rec, cov, ids)
    n = len(ids)
    if n < 3:
        return None
    try:
        Sd = _similarity_datum(np.array([p.center for p in poses]), Sc)
    except np.linalg.LinAlgError as e:   # a block whose covariance is numerically broken: no term
        log.warning("reference block covariance unusable (%s): its own uncertainty is left out", e)
        return None
    vf = _variance_factor(rec, n) if n == n_all == rec.num_reg_images() else None
    field_factor = residual_variance_factor(rec, ids, settings) if settings.residual_field else None
    ground = {}
    scales = [variance_scale(feature_noise_px(rec.cameras[rec.images[i].camera_id], feature_side), field_factor)
              for i in ids]
    k2 = k2_scatter = None
    share = 0.0
    positions = accuracy = None
    if positions_of is not None and K2_MIN_PHOTOS <= n < K2_MAX_PHOTOS:
        positions, accuracy = positions_of([rec.images[i].name for i in ids])
    keep = [a for a, i in enumerate(ids) if positions and rec.images[i].name in positions]
    if len(keep) >= K2_MIN_PHOTOS:
        C = np.array([poses[a].center for a in keep])
        G = np.array([np.asarray(positions[rec.images[ids[a]].name], np.float64) for a in keep])
        acc = np.array([np.broadcast_to(np.asarray((accuracy or {}).get(rec.images[ids[a]].name) or 0.0, float), 2)
                        for a in keep])
        pred = np.array([np.trace(Sd[3 * a:3 * a + 3, 3 * a:3 * a + 3]) * scales[a] for a in keep])
        if np.all(np.isfinite(G)) and np.all(np.isfinite(pred)):
            k2, k2_scatter, share = position_misfit(C, G, pred, acc)
    if n >= K2_MAX_PHOTOS:
        why = f"{n} photos in the block (a fit over {K2_MAX_PHOTOS} or more is not made)"
    elif n < K2_MIN_PHOTOS:
        why = f"{n} photos in the block (needs {K2_MIN_PHOTOS} with positions)"
    elif k2 is None:
        why = f"{len(keep)} photos with positions (needs {K2_MIN_PHOTOS})"
    elif k2_scatter >= K2_MAX_SCATTER_M:
        why = f"positions scatter {k2_scatter:.2f} m after the similarity (too coarse to test the block)"
    elif share >= 0.5:
        why = f"the positions' stated accuracy accounts for {100 * share:.0f} % of their residuals"
    else:
        why = ""
    k2_applied = not why
    k2_factor = max(1.0, k2_upper(k2, len(keep))) if k2_applied else 1.0
    if not k2_applied:   # the features' pixel no finer than the default's (sigma_side)
        scales = [variance_scale(feature_noise_px(rec.cameras[rec.images[i].camera_id], sigma_side(feature_side)),
                                 field_factor) for i in ids]
    for a, i in enumerate(ids):
        im = rec.images[i]
        scale = scales[a] * k2_factor
        own = _own_center_cov(rec, im, poses[a])
        g = Sd[3 * a:3 * a + 3, 3 * a:3 * a + 3] - (own if own is not None and np.all(np.isfinite(own)) else 0.0)
        if not np.all(np.isfinite(g)):
            continue
        try:
            w, V = np.linalg.eigh(0.5 * (g + g.T))
        except np.linalg.LinAlgError:   # seen on the tiny sample: the photo's term is left out (logged)
            log.warning("reference term of %s left out: its covariance does not decompose", im.name)
            continue
        ground[im.name] = scale * (V * np.clip(w, 0.0, None)) @ V.T
    if not ground:
        return None
    out = ReferenceShape(ground, vf, field_factor, n, time.time() - t0, k2, k2_factor, k2_scatter, len(keep),
                         k2_applied, why)
    log.info("reference block against its %d positions: k^2 %s, scatter %s m, %s", len(keep), _f(k2),
             "-" if k2_scatter is None else f"{k2_scatter:.3f}",
             f"its term x {k2_factor:.2f} (k^2's upper bound at {100 * K2_CONFIDENCE:.0f} %)" if k2_applied
             else f"not applied: {why}")
    log.info("reference block's own uncertainty: %d photos, residual field %s, variance factor %s, median %.3f m, "
             "in %.1f s", n, _f(field_factor), _f(vf),
             float(np.median([np.sqrt(np.trace(g)) for g in ground.values()])), out.seconds)
    return out


def _f(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def reference_term(rec, iid: int, tie_pids: set[int] | None, shape: ReferenceShape) -> np.ndarray | None:
    """A query photo's 3x3 centre covariance from the reference block: the reference photos that
    observe its points (joint model ``rec``; ``tie_pids``: only these points, None: all), their
    ground parts averaged by observations."""
    w: dict[str, int] = {}
    for p in rec.images[iid].points2D:
        if not p.has_point3D() or (tie_pids is not None and p.point3D_id not in tie_pids):
            continue
        for e in rec.points3D[p.point3D_id].track.elements:
            n = rec.images[e.image_id].name
            if n in shape.ground:
                w[n] = w.get(n, 0) + 1
    tot = sum(w.values())
    return sum(v * shape.ground[n] for n, v in w.items()) / tot if tot else None


def residual_variance_factor(rec, image_ids, settings: SigmaSettings = SigmaSettings()) -> float | None:
    """The measured variance (px^2 per axis) of the residuals' mean over cells of a grid on each of
    ``image_ids``, times the cell's count: 1 for independent 1-px noise (the BA's assumption). None
    without a cell to measure."""
    g = settings.grid
    z = []
    for iid in image_ids:
        im = rec.images[iid]
        cam = rec.cameras[im.camera_id]
        r, xy = [], []
        for p in im.points2D:
            if not p.has_point3D():
                continue
            pr = im.project_point(rec.points3D[p.point3D_id].xyz)
            if pr is not None:
                r.append(np.asarray(pr) - p.xy)
                xy.append(p.xy)
        if not r:
            continue
        r, xy = np.array(r), np.array(xy)
        cell = (np.minimum((xy[:, 0] / cam.width * g).astype(int), g - 1) * g
                + np.minimum((xy[:, 1] / cam.height * g).astype(int), g - 1))
        for c in np.unique(cell):
            m = cell == c
            if m.sum() >= settings.min_per_cell:
                z.append(m.sum() * float(np.mean(r[m].mean(0) ** 2)))
    return float(np.mean(z)) if z else None
