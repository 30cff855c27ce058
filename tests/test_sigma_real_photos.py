"""The pseudo-GT's sigma on real photos (issue 48), beyond the split of ``test_real_heldout.py``:
the shared Brighton photos held out every 5th from the 1st (DJI_0018, 0023, 0028, 0033; DJI_0018
stays unregistered: its matches to the reference are too few), as shot and as a consumer camera
writes them (``consumer-gps``, seeds 1 and 2), ``gtkit run --until register`` as a user runs it, no
clicks, judged against the yardstick SfM of all 18 photos by ``benchmarks/bench_sigma_real.py``:
each held-out photo's error within 2 sqrt(sigma^2 + yardstick^2), the yardstick's noise its median
misfit on the photos both blocks share (measured, not assumed).

GTKIT_SLOW=1: 8 minutes on 2 loaded cores (a yardstick SfM and three held-out runs; passed
2026-12-06). Measured figures are in docs/benchmarks.md, "Sigma on real photos (issue 48)"."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import BRIGHTON, ROOT
from gtkit.cli import main as gtkit

SLOW = os.environ.get("GTKIT_SLOW") == "1"
pytestmark = [pytest.mark.skipif(not (BRIGHTON / "images").is_dir(), reason="shared Brighton photos not available"),
              pytest.mark.skipif(not SLOW, reason="GTKIT_SLOW=1: three held-out runs on real photos (~8 min loaded)")]
HELD = ("DJI_0018.JPG", "DJI_0023.JPG", "DJI_0028.JPG", "DJI_0033.JPG")   # every 5th from the 1st


def _held(base: Path, variant_seed: int | None) -> Path:
    ref, seq = base / "ref", base / "q" / "seq"
    ref.mkdir(parents=True)
    seq.mkdir(parents=True)
    for p in sorted((BRIGHTON / "images").glob("*.JPG")):
        (seq if p.name in HELD else ref).joinpath(p.name).symlink_to(p)
    copy = ["--copy"] if variant_seed is not None else []
    assert gtkit(["init", str(base / "HELD"), "--reference", str(ref), "--queries", str(seq)] + copy) == 0
    if variant_seed is not None:
        from gtkit.synth.variants import apply_variant

        apply_variant(base / "HELD", "consumer-gps", seed=variant_seed)
    run = subprocess.run([sys.executable, "-m", "gtkit.cli", "run", str(base / "HELD"), "--until", "register"],
                         cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert run.returncode in (0, 1), run.stderr[-2000:]
    return base / "HELD"


@pytest.mark.parametrize("variant_seed", [None, 1, 2], ids=["as-shot", "consumer-gps-1", "consumer-gps-2"])
def test_sigma_holds_on_real_photos_held_out_from_the_first(tmp_path_factory, yardstick, variant_seed):
    from benchmarks.bench_sigma_real import judge, shares

    held = _held(tmp_path_factory.mktemp("brighton_held"), variant_seed)
    res = judge(yardstick, held)
    s = shares(res)
    assert s["n"] >= 3, res                      # DJI_0018 may stay unregistered (known)
    assert s["within_median"] >= 0.9, res        # every registered photo held (3 of 3)
    # the terms are measured on this block: real photos' residuals move together in a cell
    terms = [r["terms"] for r in res["rows"] if r.get("terms")]
    assert all(t["residual_factor"] > 1.5 and t["reference_m"] > 0.01 for t in terms), terms
