"""Placing a query sequence without clicks (``[register.bootstrap]``): its photos matched to the
reference block's 3D points around the poses their metadata claims, and the Sim(3) most matched photos
agree with (:func:`bootstrap_sequence`)."""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pycolmap

from ...pose import Pose
from ..geometry import RegistrationError, robust_sim3
from .settings import RegisterSettings


@dataclass
class Bootstrap:
    """What :func:`bootstrap_sequence` found: the Sim(3) (None when the sequence cannot be held),
    the reason, and one record per photo."""
    sim: pycolmap.Sim3d | None
    reason: str
    photos: dict[str, dict]
    n_pairs: int = 0
    n_inliers: int = 0
    rmse_m: float | None = None
    fit_from: str = ""
    metadata_failed: str = ""    # why matching around the metadata poses failed, where this is the fallback

    def record(self) -> dict:
        matched = [n for n, r in self.photos.items() if r.get("n_matches")]
        return {"n_photos": len(self.photos), "n_photos_matched": len(matched),
                "n_photos_agreeing": sum(1 for r in self.photos.values() if r.get("agrees")),
                "n_point_pairs": self.n_pairs, "n_sim3_inliers": self.n_inliers, "sim3_rmse_m": self.rmse_m,
                "sim3_from": self.fit_from,
                "photos": self.photos, **({"reason": self.reason} if self.reason else {}),
                **({"metadata_guided_failed": self.metadata_failed} if self.metadata_failed else {})}


def bootstrap_sequence(qrec: pycolmap.Reconstruction, priors, match, settings: RegisterSettings,
                       search=None) -> Bootstrap:
    """Place one query block in the reference frame without clicks.

    Each registered photo is matched to the reference block's 3D points around the poses
    ``priors(name) -> [(label, Pose)]`` gives (its GPS + gimbal metadata, its pose in the block's own
    GPS georegistration); ``match(name, prior, wider) -> (Pose | None, reference xyz (n, 3), query
    keypoint indices)`` (:func:`gtkit.sfm.crossmatch.match_photo_wide`; ``wider``: a photo that finds
    nothing is searched again at twice the radius). Photos with no prior, or none that
    matched, are tried again around their block pose moved by a first Sim(3) from the matched ones.
    Where no photo matched at all, ``search(name) -> [(label, Pose)]`` (a photo's GPS position with
    a grid of attitudes: no gimbal tags) is tried on up to ``bootstrap.search_photos`` photos, the
    first that matches ending the search. A match farther than ``bootstrap.max_offset_m`` from the
    pose that guided it is taken for a false one.
    Each match whose query keypoint is a 3D point of the block is a pair (block point, reference
    point); a robust Sim(3) (LO-RANSAC, ``sim3_max_error_m``) over all pairs is one candidate, the
    Sim(3)s from the matched photos' poses (:func:`_sim3_from_poses`, each pair of photos) the
    others: the one most photos agree with wins (their block poses so moved within ``agree_m`` /
    ``agree_deg`` of the poses their own matches gave them), refitted on them. A short sequence's
    own 3D points can be metres off in depth (tiny seed 0's seq3 at 150 m: its point Sim(3) 13 m and
    4.7 deg from all three photos' own poses), its relative poses are not. It holds only where
    ``bootstrap.min_photos`` photos or more agree."""
    b = settings.bootstrap
    p = _Matches(qrec, match, settings)
    for n in p.names:
        cands = priors(n)
        if not cands:
            p.photos[n] = {"reason": "no GPS + gimbal metadata and no GPS georegistration of its block"}
            continue
        if not p.try_photo(n, cands):
            p.photos[n] = {"reason": f"fewer than {settings.cross.min_inliers} consistent matches to the reference "
                                     "points around its metadata pose"}
    if not p.pairs and search is not None:   # no attitude to guide any photo: searched at its GPS position
        p.search(search)
    p.retry_through_first_sim3()
    n_matched, names, photos = len(p.pairs), p.names, p.photos
    if n_matched < b.min_photos:
        whys = [r["reason"] for r in photos.values() if r.get("reason")]
        common = max(set(whys), key=whys.count) if whys else ""
        return Bootstrap(None, f"only {n_matched} of {len(names)} photos matched the reference points "
                               f"({b.min_photos} needed" + (f"; {whys.count(common)} with {common}" if common else "")
                         + ")", photos)
    sim, how, ok, f, point_err = p.choose()
    if sim is None:
        return Bootstrap(None, f"{n_matched} of {len(names)} photos matched the reference points but {point_err}",
                         photos)
    out = p.outcome(sim, how, ok, f)
    if len(ok) < b.min_photos:
        out.sim = None
        out.reason = (f"{n_matched} of {len(names)} photos matched the reference points, but only {len(ok)} agree on "
                      f"one Sim(3) ({b.min_photos} needed)")
    return out


class _Matches:
    """The state :func:`bootstrap_sequence` builds up: each photo's record, its (block point, reference
    point) pairs and the pose its own matches gave it."""

    def __init__(self, qrec: pycolmap.Reconstruction, match, settings: RegisterSettings):
        self.qrec, self.match, self.settings, self.b = qrec, match, settings, settings.bootstrap
        self.names = sorted(im.name for im in qrec.images.values() if im.has_pose)
        self.photos: dict[str, dict] = {n: {} for n in self.names}
        self.pairs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.matched_pose: dict[str, Pose] = {}     # each matched photo's own pose from its matches (PnP)

    def pairs_of(self, name, X_ref, kk):
        qrec = self.qrec
        im = qrec.find_image_with_name(name)
        src, tgt, pid = [], [], []
        for X, k in zip(X_ref, kk):
            p2 = im.points2D[int(k)]
            if p2.has_point3D():
                src.append(qrec.points3D[p2.point3D_id].xyz)
                tgt.append(X)
                pid.append(p2.point3D_id)
        return np.array(src).reshape(-1, 3), np.array(tgt).reshape(-1, 3), np.array(pid, np.int64)

    def try_photo(self, name, cands, wider=True):
        best = None
        for label, prior in cands:
            pose, X_ref, kk = self.match(name, prior, wider)
            if pose is not None and np.linalg.norm(pose.center - prior.center) > self.b.max_offset_m:
                pose = None   # matched far from where its metadata put it: a false match
            if pose is not None and (best is None or len(kk) > len(best[2])):
                best = (label, X_ref, kk, pose)
            if best is not None and label != "block GPS":   # the metadata pose found it: enough
                break
        if best is None:
            return False
        self.photos[name] = {"n_matches": int(len(best[2])), "guided_by": best[0]}
        self.pairs[name] = self.pairs_of(name, best[1], best[2])
        self.matched_pose[name] = best[3]
        return True

    def search(self, search):
        """Photos searched at their GPS position with a grid of attitudes, until one matches."""
        photos, tried = self.photos, 0
        for n in self.names:
            cands = search(n)
            if not cands or tried >= self.b.search_photos:
                continue
            tried += 1
            if self.try_photo(n, cands, wider=False):
                break
            photos[n] = {"reason": (photos[n]["reason"] + "; " if photos[n].get("reason") else "")
                         + f"no match around its GPS position at any of {len(cands)} searched attitudes"}

    def retry_through_first_sim3(self):
        """Photos not matched around their own priors: around their block pose through a first Sim(3)."""
        missing = [n for n in self.names if n not in self.pairs]
        if not (self.pairs and missing):
            return
        first = self.choose()[0]
        if first is None:
            return
        for n in missing:
            im = self.qrec.find_image_with_name(n)
            C = np.asarray(first * im.projection_center())
            R = Pose.from_pycolmap(im.cam_from_world()).R @ np.asarray(first.rotation.matrix()).T
            if self.try_photo(n, [("matched photos of its block", Pose.from_center(R, C))]):
                self.photos[n].pop("reason", None)

    def fit(self):
        pairs, b = self.pairs, self.b
        src = np.vstack([pairs[n][0] for n in pairs]) if pairs else np.zeros((0, 3))
        tgt = np.vstack([pairs[n][1] for n in pairs]) if pairs else np.zeros((0, 3))
        who = np.concatenate([np.full(len(pairs[n][0]), k) for k, n in enumerate(pairs)]) if pairs else np.zeros(0, int)
        if len(src) > b.max_pairs:
            pick = np.sort(np.random.default_rng(0).choice(len(src), b.max_pairs, replace=False))
            src, tgt, who = src[pick], tgt[pick], who[pick]
        return robust_sim3(src, tgt, self.settings.sim3_max_error_m, what="block-reference point matches"), src, tgt, who

    def offsets(self, sim, n):
        """(m, deg) between the photo's block pose moved by ``sim`` and the pose its matches gave it."""
        Rs = np.asarray(sim.rotation.matrix())
        block = Pose.from_pycolmap(self.qrec.find_image_with_name(n).cam_from_world())
        moved = Pose.from_center(block.R @ Rs.T, np.asarray(sim * block.center))
        return moved.error_to(self.matched_pose[n])

    def agreeing(self, sim):
        offs = {n: self.offsets(sim, n) for n in self.pairs}
        ok = [n for n, (dm, dd) in offs.items() if dm <= self.b.agree_m and dd <= self.b.agree_deg]
        return ok, float(np.mean([offs[n][0] for n in ok])) if ok else np.inf

    def choose(self):
        """(the Sim(3) most matched photos agree with or None, how, the agreeing photos, point fit, its
        pair sources, error of the point fit)."""
        pairs, matched_pose = self.pairs, self.matched_pose
        try:
            f = self.fit()
            point_err = ""
        except RegistrationError as e:
            f, point_err = None, str(e)
        scale = None if f is None else float(f[0].tgt_from_src.scale)
        block = {n: Pose.from_pycolmap(self.qrec.find_image_with_name(n).cam_from_world()) for n in pairs}
        hyps = [("block-reference point pairs", f[0].tgt_from_src)] if f is not None else []
        for ij in itertools.islice(itertools.combinations(sorted(pairs), 2), 300):
            h = _sim3_from_poses([block[n] for n in ij], [matched_pose[n] for n in ij], scale)
            if h is not None:
                hyps.append(("photo poses", h))
        if not hyps:
            return None, "", [], f, point_err
        scored = [(self.agreeing(h), how, h) for how, h in hyps]
        (ok, _), how, sim = max(scored, key=lambda x: (len(x[0][0]), -x[0][1]))
        if len(ok) >= 2:   # refit on every agreeing photo
            h = _sim3_from_poses([block[n] for n in ok], [matched_pose[n] for n in ok], scale)
            if h is not None and len(self.agreeing(h)[0]) >= len(ok):
                how, sim, ok = "photo poses", h, self.agreeing(h)[0]
        return sim, how, ok, f, point_err

    def outcome(self, sim, how, ok, f) -> Bootstrap:
        """The placement by ``sim`` (found ``how``, agreed by the photos ``ok``; ``f`` the point fit)."""
        photos = self.photos
        fit3, src, who = (f[0], f[1], f[3]) if f is not None else (None, np.zeros((0, 3)), np.zeros(0, int))
        for k, n in enumerate(self.pairs):
            mine = who == k
            d_m, d_deg = self.offsets(sim, n)
            photos[n].update({"n_pairs": int(mine.sum()),
                              "n_sim3_inliers": int(fit3.inliers[mine].sum()) if fit3 is not None else 0,
                              "offset_m": float(d_m), "offset_deg": float(d_deg), "agrees": n in ok})
        return Bootstrap(sim, "", photos, int(len(src)), int(fit3.inliers.sum()) if fit3 is not None else 0,
                         float(fit3.rmse_inliers_m) if fit3 is not None else None, fit_from=how)


def _sim3_from_poses(block: list[Pose], ref: list[Pose], fallback_scale: float | None) -> pycolmap.Sim3d | None:
    """Sim(3) reference_from_block from photos' block poses and their poses in the reference frame:
    the rotation the chordal mean of R_ref^T R_block, scale and translation least squares on the
    centres (``fallback_scale`` where they span less than a metre, None without one)."""
    M = sum(r.R.T @ q.R for q, r in zip(block, ref))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    cs = np.array([q.center for q in block])
    cr = np.array([r.center for r in ref])
    a = (cs - cs.mean(0)) @ R.T
    d = cr - cr.mean(0)
    if len(block) >= 2 and np.linalg.norm(d, axis=1).max() >= 1.0 and (a * a).sum() > 0:
        scale = float((a * d).sum() / (a * a).sum())
    else:
        scale = fallback_scale
    if scale is None or not np.isfinite(scale) or scale <= 0:
        return None
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(R), cr.mean(0) - scale * R @ cs.mean(0))


