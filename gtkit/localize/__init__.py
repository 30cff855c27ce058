"""UAVLoc localization (UAVD4L §3): rendered database, prior-guided retrieval, matching,
lifting through rendered depth, gravity-guided PnP RANSAC.

Modules: ``grid`` (virtual viewpoints), ``database`` (render-db stage), ``features`` (local
features + matchers), ``descriptors`` (global descriptors), ``prior`` (rotation/GPS filters),
``lift`` (2D-3D), ``pnp`` (gravity-guided P3P RANSAC), ``localize`` (the stage),
``executors`` (serial / local processes / Dask).
"""
