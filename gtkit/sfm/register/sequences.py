"""Placing each query sequence in the reference frame before the joint adjustment: by its clicked tie
points (:mod:`.clicked`), checked against its automatic matches where the clicks are few; else by its
automatic matches alone (:mod:`.bootstrap`); a sequence whose SfM made no model photo by photo
(:mod:`gtkit.sfm.resect`). A sequence that cannot be placed is an error that names why."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ...io.tiepoints import TiePoint
from ..geometry import RegistrationError
from ..resect import resect_sequence
from .bootstrap import Bootstrap
from .clicked import TieStatus, register_sequence, sim3_disagreement, weak_click_support
from .reference import ReferenceBlock

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


@dataclass
class Placed:
    """The sequences placed so far: each one's record, the placed blocks (transformed into the
    reference frame), their tie points' Sim(3) status, and the photos resected on their own."""
    report: dict[str, dict] = field(default_factory=dict)
    blocks: dict[str, pycolmap.Reconstruction] = field(default_factory=dict)
    statuses: dict[str, list[TieStatus]] = field(default_factory=dict)
    resected: dict[str, dict] = field(default_factory=dict)


def place_sequences(ref: ReferenceBlock, seq_dirs: dict[str, Path], tiepoints: list[TiePoint]) -> Placed:
    """Every sequence (``seq_dirs``: sequence -> its SfM model folder) placed, or its error recorded."""
    placed = Placed()
    for seq, d in seq_dirs.items():
        if not d.is_dir():
            place_photo_by_photo(ref, seq, d, tiepoints, placed)
        else:
            place_block(ref, seq, d, tiepoints, placed)
    return placed


def place_photo_by_photo(ref: ReferenceBlock, seq: str, d: Path, tiepoints: list[TiePoint], placed: Placed) -> None:
    """A sequence whose SfM made no model (e.g. photos held out of a flight, too far apart to match each
    other): each photo on its own, resected from automatic matches to the reference points."""
    ran = (d.parent / "block.json").is_file()
    qrec, no_block = ref.solo_block(seq) if ran else (None, "")
    res = resect_sequence(seq, qrec, d.parent / "block.json", ref.P.images, tiepoints, ref.place_clicks,
                          ref.settings.tie_max_px, ref.left_out_matcher(seq)) if qrec is not None else {}
    done = {n: r for n, r in res.items() if r["resected"]}
    if not done:
        why = ("no query-block model (run `gtkit sfm DIR --block queries`)" if not ran else
               f"its SfM made no model and its photos cannot be placed one by one: {no_block}" if qrec is None else
               "its SfM made no model and none of its photos matched the reference points on its own"
               + (f" ({next(iter(res.values())).get('auto_reason')})" if res else ""))
        placed.report[seq] = {"status": "error", "error": why, "needs_clicks": qrec is not None,
                              **({"left_out_by_sfm": res} if res else {})}
        log.error("sequence %s not registered: %s", seq, why)
        return
    placed.blocks[seq], placed.statuses[seq] = qrec, []
    placed.resected.update(done)
    placed.report[seq] = {"status": "registered", "registered_by": "single photos (its SfM made no model)",
                          "scale": 1.0, "n_tiepoints": 0, "n_sim3_inliers": 0, "sim3_rmse_m": None,
                          "left_out_by_sfm": res}
    log.info("sequence %s: no SfM model; %d of %d photos resected one by one from automatic matches",
             seq, len(done), len(res))


def place_by_clicks(ref: ReferenceBlock, seq: str, qrec: pycolmap.Reconstruction, tiepoints: list[TiePoint]
                    ) -> tuple[pycolmap.Sim3d | None, list[TieStatus], str, Bootstrap | None]:
    """(Sim(3), tie statuses, why not, the check by automatic matches where one was made) of a sequence
    placed by its clicks: no Sim(3) where they cannot place it, or where they are few (or all in one
    photo) and place it farther than ``bootstrap.agree_m`` from where its automatic matches agree to
    put it (one gross mistake among a few clicks moves the block)."""
    settings = ref.settings
    try:
        sim, st = register_sequence(seq, qrec, ref.rec, tiepoints, settings, ref.cache)
    except RegistrationError as e:
        return None, [], str(e), None
    weak = weak_click_support(st, settings.bootstrap)
    if not weak:
        return sim, st, "", None
    check = ref.place_without_clicks(seq, qrec)
    if check.sim is not None:
        shift = sim3_disagreement(sim, check.sim, qrec)
        if shift > settings.bootstrap.agree_m:
            return None, st, (f"its clicks ({weak}) place it {shift:.1f} m from where "
                              f"{check.record()['n_photos_agreeing']} of its photos' automatic matches agree to put "
                              "it: placed by the automatic matches (check its clicks)"), check
    return sim, st, "", check


def place_block(ref: ReferenceBlock, seq: str, d: Path, tiepoints: list[TiePoint], placed: Placed) -> None:
    """A sequence with an SfM model (``d``): placed by its clicks, else by its automatic matches; then the
    photos its SfM left out, resected from their clicks (adjusted with the rest later)."""
    qrec = pycolmap.Reconstruction(d)
    n_clicked = sum(1 for tp in tiepoints if tp.in_block(f"queries/{seq}/"))
    sim, st, why_not, check = place_by_clicks(ref, seq, qrec, tiepoints)
    boot = None
    if sim is None:
        clicks_why = why_not if n_clicked else "no clicked tie points"
        boot = check if check is not None and check.sim is not None else ref.place_without_clicks(seq, qrec)
        if boot.sim is None:
            err = (f"{clicks_why}; automatic matches: {boot.reason}; "
                   f"click 3 or more tie points in its photos (queries/{seq}/) and the reference photos "
                   "(`gtkit annotate DIR`)")
            placed.report[seq] = {"status": "error", "error": err, "needs_clicks": True,
                                  "clicks": clicks_why, "automatic": boot.record()}
            log.error("sequence %s not registered: %s", seq, err)
            return
        sim, st = boot.sim, []
        log.info("sequence %s: placed by automatic matches (%s): %d of %d photos agree, Sim(3) from %s",
                 seq, clicks_why, boot.record()["n_photos_agreeing"], len(boot.photos), boot.fit_from)
    qrec.transform(sim)
    placed.blocks[seq], placed.statuses[seq] = qrec, st
    if boot is None:
        placed.report[seq] = {"status": "registered", "registered_by": "clicked tie points", "scale": float(sim.scale),
                              "n_tiepoints": len(st), "n_sim3_inliers": sum(s.inlier for s in st),
                              "sim3_rmse_m": float(np.sqrt(np.mean([s.sim3_residual_m ** 2 for s in st if s.inlier])))}
    else:
        placed.report[seq] = {"status": "registered", "registered_by": "automatic matches", "scale": float(sim.scale),
                              "n_tiepoints": n_clicked, "n_sim3_inliers": 0, "sim3_rmse_m": None,
                              "clicks": clicks_why, "automatic": boot.record()}
    # photos the sequence's SfM left out: resected from their clicks, then adjusted with the rest
    res = resect_sequence(seq, qrec, d.parent / "block.json", ref.P.images, tiepoints, ref.place_clicks,
                          ref.settings.tie_max_px, ref.left_out_matcher(seq))
    if res:
        placed.report[seq]["left_out_by_sfm"] = res
        placed.resected.update({n: r for n, r in res.items() if r["resected"]})
