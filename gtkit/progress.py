"""Progress bars for long steps, one style for every stage (tqdm on stderr, refreshed at most
every 2 s). ``GTKIT_PROGRESS=0`` turns them off (logs and CI)."""
from __future__ import annotations

import os


def progress_bar(total: int | None, desc: str, unit: str = "it", show: bool = True, iterable=None):
    """A tqdm bar; ``.update(n)`` and ``.close()`` (or iterate it when ``iterable`` is given)."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, leave=False, mininterval=2.0,
                disable=not show or os.environ.get("GTKIT_PROGRESS") == "0")
