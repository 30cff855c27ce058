"""A sequence without metadata (no GPS, no attitude: photos from another camera or a phone, stripped
photos) placed without clicks: each photo matched keypoint to keypoint with the reference photos
that look like it, registered into the reference block by COLMAP's mapper with the reference poses
held (:func:`gtkit.sfm.extend_reference.register_into_reference`: what one SfM of all the photos
does for them), then the sequence placed by the Sim(3) those photos agree on
(:func:`gtkit.sfm.register.bootstrap.bootstrap_sequence`, its matches given).

Which reference photos: all of them where the block has at most ``max_exhaustive`` photos, else
the ``top_k`` a bag of visual words over their SIFT descriptors ranks first for each query photo
(:func:`rank_reference_photos`). Issue 55: before this, every such sequence was refused and asked
for clicks, where one SfM of all photos registers it at 4-14 mm.

A photo its sequence's SfM left out (or every photo of a sequence whose SfM made no model: two held-out
photos too far apart to start one) is registered the same way (:func:`keypoint_poses`) where it has
no GPS to guide its matching or that matching failed
(:meth:`gtkit.sfm.register.reference.ReferenceBlock.match_left_out`).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from ...pose import Pose
from ..crossmatch import photo_features
from ..extend_reference import register_into_reference
from ..geometry import model_cameras
from .bootstrap import Bootstrap, bootstrap_sequence

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


def _words(desc: np.ndarray, vocab: np.ndarray) -> np.ndarray:
    d2 = (desc ** 2).sum(1)[:, None] - 2 * desc @ vocab.T + (vocab ** 2).sum(1)[None]
    return np.argmin(d2, axis=1)


def sampled(desc: np.ndarray, n: int, rng) -> np.ndarray:
    """At most ``n`` of a photo's descriptors (float32), drawn at random: what the ranking uses of it."""
    desc = np.asarray(desc, np.float32)
    return desc[rng.choice(len(desc), n, replace=False)] if len(desc) > n else desc


def rank_reference_photos(query: dict[str, np.ndarray], reference: dict[str, np.ndarray], k: int, n_words: int,
                          seed: int = 0) -> dict[str, list[str]]:
    """{query photo: the ``k`` reference photos most alike}, by tf-idf histograms of visual words (a
    vocabulary of ``n_words`` k-means centres over the reference photos' descriptors: each photo's
    already :func:`sampled`, so a large block's descriptors are never all in memory at once)."""
    from scipy.cluster.vq import kmeans2

    ref_names = sorted(reference)
    pool = np.vstack([reference[n] for n in ref_names])
    vocab, _ = kmeans2(pool, min(n_words, len(pool)), seed=seed, minit="++", iter=10)

    def hist(d):
        return np.bincount(_words(d, vocab), minlength=len(vocab)).astype(float)

    R = np.array([hist(reference[n]) for n in ref_names])
    idf = np.log(len(R) / (1.0 + (R > 0).sum(0)))
    Rn = R * idf
    Rn /= np.linalg.norm(Rn, axis=1, keepdims=True) + 1e-12
    out = {}
    for q, d in query.items():
        h = hist(d) * idf
        s = Rn @ (h / (np.linalg.norm(h) + 1e-12))
        out[q] = [ref_names[i] for i in np.argsort(-s)[:k]]
    return out


def keypoint_poses(ref, names: list[str], cams: dict, db: Path, settings, work: Path
                   ) -> tuple[dict[str, tuple[Pose, np.ndarray, np.ndarray]], str]:
    """({photo: (pose, the reference 3D points it sees (n, 3), its keypoint indices)}, with which
    reference photos) for the photos ``names`` (cameras ``cams``, features in ``db``) registered into
    the reference block ``ref`` by keypoint matches, in folder ``work``: with every reference photo where
    the block has at most ``unguided.max_exhaustive`` photos, else the ``top_k`` ranked first; and with
    each other. A photo keeps its pose
    where at least ``cross.min_inliers`` of its keypoints are reference points."""
    u = settings.unguided
    refs = sorted(im.name for im in ref.rec.images.values() if im.has_pose)
    if len(refs) <= u.max_exhaustive:
        near = {n: refs for n in names}
        how = f"all {len(refs)} reference photos"
    else:
        rng = np.random.default_rng(0)
        query = {n: sampled(f[1], u.sample_per_photo, rng) for n in names if (f := photo_features(db, n)) is not None}
        reference = {r: sampled(photo_features(ref.db, r)[1], u.sample_per_photo, rng) for r in refs}
        near = rank_reference_photos(query, reference, u.top_k, u.words)
        how = f"the {u.top_k} of {len(refs)} reference photos ranked first by visual words"
    pairs = [(n, r) for n in names for r in near.get(n, [])]
    pairs += [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    ext = register_into_reference(ref.rec, ref.db, {n: (cams[n], db) for n in names}, pairs,
                                  ref.P.images, work, num_threads=settings.num_threads,
                                  reproducible=settings.reproducible)
    found: dict[str, tuple[Pose, np.ndarray, np.ndarray]] = {}
    if ext is not None:
        for n in names:
            im = ext.find_image_with_name(n)
            if im is None or not im.has_pose:
                continue
            X, kk = [], []
            for k, p in enumerate(im.points2D):
                if p.has_point3D() and any(ext.images[e.image_id].name.startswith("reference/")
                                           for e in ext.points3D[p.point3D_id].track.elements):
                    X.append(ext.points3D[p.point3D_id].xyz)
                    kk.append(k)
            if len(kk) >= settings.cross.min_inliers:
                found[n] = (Pose.from_pycolmap(im.cam_from_world()), np.array(X).reshape(-1, 3), np.array(kk, int))
    return found, how


def place_unguided(ref, seq: str, qrec: pycolmap.Reconstruction, db: Path, settings,
                   why: str = "no GPS and no attitude") -> Bootstrap:
    """The sequence (its block ``qrec``, its feature database ``db``) placed in the reference block
    ``ref`` (:class:`gtkit.sfm.register.reference.ReferenceBlock`) without any metadata; ``why`` it is
    matched so, for its log line and its photos' reasons."""
    names = sorted(im.name for im in qrec.images.values() if im.has_pose)
    if not settings.unguided.enabled:
        return Bootstrap(None, "its photos have no GPS and no attitude, and matching them to every reference "
                               "photo is off ([register.unguided] enabled)", {})
    found, how = keypoint_poses(ref, names, model_cameras(qrec), db, settings,
                                ref.P.stage("register") / "unguided" / seq)
    log.info("sequence %s (%s): %d of %d photos registered into the reference block by keypoint "
             "matches with %s", seq, why, len(found), len(names), how)

    def priors(name):
        return [(f"keypoint matches with {how}", found[name][0])] if name in found else []

    def match(name, prior, wider=True):
        return found[name] if name in found else (None, np.zeros((0, 3)), np.zeros(0, int))

    out = bootstrap_sequence(qrec, priors, match, settings)
    for n, r in out.photos.items():
        if n not in found and "reason" in r:
            r["reason"] = (f"{why}, and fewer than {settings.cross.min_inliers} keypoint matches "
                           f"registered it into the reference block ({how})")
    return out
