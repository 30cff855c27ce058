"""The reference model from the photos: ``gtkit model build DIR`` (after ``gtkit sfm DIR --block reference``).

One module a step, in the order the stage runs them (:mod:`gtkit.model.build`):

- :mod:`~gtkit.model.views`    the georegistered reference block: undistorted pinhole views at a working
                               size, the scene depth range of each (sparse points), neighbour choice;
- :mod:`~gtkit.model.depth`    per-photo depth maps: semi-global matching (OpenCV SGBM) on pairs rectified
                               here, then the pairs' depths must agree (multi-view consistency);
- :mod:`~gtkit.model.fusion`   geometric consistency between photos' depth maps, fusion into a point
                               cloud (PLY + LAZ);
- :mod:`~gtkit.model.surface`  Poisson surface (Open3D), trimmed to where points support it,
                               simplified to a triangle budget (pymeshlab);
- :mod:`~gtkit.model.texture`  each face textured from the photo that sees it best (visibility from
                               gtkit's moderngl renderer);
- :mod:`~gtkit.model.compare`  height difference between two models' DSMs (GeoTIFF).
"""
