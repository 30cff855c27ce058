"""Surveyor exports: DSM and orthophoto GeoTIFFs, the textured mesh in the project CRS, and
camera/target coordinates (CSV, GeoJSON, OpenDroneMap geo.txt).

Modules, each with one job:

``grid``         the raster grid (world frame, snapped to whole cells in the CRS)
``surface``      "surface samples" (a mesh rendered top-down, or a point cloud) -> height/RGB grid
``geotiff``      the one GeoTIFF writer (CRS, geotransform, nodata, tiles, DEFLATE, optional COG)
``dsm``          the DSM stage and :class:`gtkit.export.dsm.Dsm`, the reader other stages use
``gapfill``      DSM gaps inside the photos' ground footprint filled from their border (band 2 marks them)
``ortho``        the true-orthophoto stage
``seams``        the orthophoto from the photos: per-photo exposure gains, feathered seams, seam_difference
``mesh_export``  textured mesh as OBJ/PLY/GLB with the CRS + offset sidecar, optional decimation
``coordinates``  camera poses and targets out: CSV, GeoJSON, geo.txt
"""
