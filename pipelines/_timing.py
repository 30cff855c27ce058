"""One helper the pipelines share: run a stage, log it, record its wall time."""
from __future__ import annotations

import logging
import time


def timed(times: dict, name: str, fn, *args, log: logging.Logger, **kwargs):
    """``fn(*args, **kwargs)``, logged as stage ``name``; its wall seconds go into ``times[name]``."""
    log.info("[%s] running ...", name)
    t = time.time()
    out = fn(*args, **kwargs)
    times[name] = round(time.time() - t, 1)
    log.info("[%s] done in %.1f s", name, times[name])
    return out
