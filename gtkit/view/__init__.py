"""The 3D scene of a project (pyvista/VTK, offscreen): model, cameras, trajectories, GCPs, tracks."""
