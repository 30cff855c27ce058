"""Structure from motion for the pseudo-GT pipeline (pycolmap): feature database, blocks
(reference and query sequences), georegistration, tie-point registration and joint BA."""

import logging as _logging
import os as _os


def quiet_colmap() -> None:
    """COLMAP logs every image and iteration at INFO to stderr; keep its warnings and errors only,
    unless gtkit runs with --verbose (debug logging) or GTKIT_COLMAP_LOG=1 is set, or the output
    goes to a stage's log file (:mod:`gtkit.logs`), which then gets all of it."""
    import pycolmap

    from ..logs import current_log

    if _os.environ.get("GTKIT_COLMAP_LOG") == "1" or _logging.getLogger().isEnabledFor(_logging.DEBUG):
        return
    # 0 INFO, 1 WARNING, 2 ERROR; under gtkit.logs.quiet_terminal it all goes to the stage's log.txt
    pycolmap.logging.minloglevel = 0 if current_log() is not None else 1
