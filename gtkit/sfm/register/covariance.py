"""The final joint BA's covariance, for every query photo the data determines, and the cause for those
it does not.

Ceres' covariance of the whole joint problem fails as a whole where any part of it is undetermined
("the Schur complement on pose/other parameters is rank deficient"): one sequence joined to the
reference by nothing (its automatic ties all dropped), a camera calibrated from too few photos, a
photo seeing too few points. Before issue 55 that left every photo of the project without a sigma,
the cause in the log only. Here, where the whole problem fails, each sequence's covariance is
computed on its own (the other query photos held, as the reference is: they share no parameters but
the few tie points two sequences both see, so the cross terms left out are small), and a sequence
whose own problem is still undetermined is named with the cause the record can state (its photos'
tie points). Its photos keep their poses but no sigma: "unverified" in the record, the GT report
and the exports, never counted as registered.
"""
from __future__ import annotations

import logging

import pycolmap

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


class PerSequenceCovariance:
    """pycolmap's ``BACovariance`` reading, one per sequence: each image's blocks from the problem its
    sequence was computed in (a cross covariance between two sequences is not known: KeyError)."""

    def __init__(self):
        self.of: dict[int, object] = {}   # image id -> the BACovariance holding it

    def get_cam_cov_from_world(self, iid: int):
        return self.of[iid].get_cam_cov_from_world(iid)

    def get_cam_cross_cov_from_world(self, a: int, b: int):
        if self.of[a] is not self.of[b]:
            raise KeyError(f"images {a} and {b} were not adjusted together")
        return self.of[a].get_cam_cross_cov_from_world(a, b)


def _estimate(rec, ba):
    try:
        return pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), rec, ba)
    except Exception as e:  # noqa: BLE001 - pycolmap raises for some degenerate problems; None is the answer
        log.warning("BA covariance failed: %s", e)
        return None


def joint_covariance(j, ba, problem_holding) -> tuple[object | None, dict[str, str]]:
    """(covariance of the joint model ``j`` after the adjuster ``ba`` solved it, {sequence: why it has
    none}). ``problem_holding(constant_image_ids) -> adjuster`` sets up the same problem with those
    query photos held too (not solved again: the covariance is taken at the solution)."""
    rec = j.rec
    cov = _estimate(rec, ba)
    by_seq: dict[str, list[int]] = {}
    for iid in rec.reg_image_ids():
        if iid not in j.ref_ids:
            by_seq.setdefault(rec.images[iid].name.split("/")[1], []).append(iid)
    if cov is not None or not by_seq:
        return cov, {}
    log.warning("the joint BA's covariance is undetermined as a whole; each sequence's taken on its own")
    out, failed = PerSequenceCovariance(), {}
    every = {i for ids in by_seq.values() for i in ids}
    for seq, ids in sorted(by_seq.items()):
        c = _estimate(rec, problem_holding(every - set(ids)))
        if c is None:
            failed[seq] = undetermined_words(j, ids)
            log.warning("sequence %s: no covariance (%s): its photos are unverified", seq, failed[seq])
            continue
        out.of.update({i: c for i in ids})
    return (out if out.of else None), failed


def undetermined_words(j, ids: list[int]) -> str:
    """Why a sequence's BA covariance is undetermined, from what ties it: its photos' tie points."""
    rec = j.rec
    ties = set(j.tie_pids.values())
    per_photo = [sum(1 for p in rec.images[i].points2D if p.has_point3D() and p.point3D_id in ties) for i in ids]
    if not any(per_photo):
        return "not tied to the reference: no tie point in the final BA, its pose rests on its placement alone"
    return (f"its poses are not determined by what ties them (tie points a photo: {min(per_photo)}-{max(per_photo)}; "
            "Ceres: rank-deficient normal equations)")
