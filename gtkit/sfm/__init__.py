"""Structure from motion for the pseudo-GT pipeline (pycolmap): feature database, blocks
(reference and query sequences), georegistration, tie-point registration and joint BA."""

import logging as _logging
import os as _os


def quiet_colmap() -> None:
    """COLMAP logs every image and iteration at INFO to stderr; keep its warnings and errors only,
    unless gtkit runs with --verbose (debug logging) or GTKIT_COLMAP_LOG=1 is set."""
    import pycolmap

    if _os.environ.get("GTKIT_COLMAP_LOG") == "1" or _logging.getLogger().isEnabledFor(_logging.DEBUG):
        return
    pycolmap.logging.minloglevel = 1  # 0 INFO, 1 WARNING, 2 ERROR
