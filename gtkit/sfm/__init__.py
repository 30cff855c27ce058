"""Structure from motion for the pseudo-GT pipeline (pycolmap): feature database, blocks
(reference and query sequences), georegistration, tie-point registration and joint BA."""
