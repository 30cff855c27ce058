"""Sample projects: a procedurally generated site with known truth, photographed like UAVD4L.

``create_sample(root, settings)`` (:mod:`gtkit.synth.generate`) writes a complete project folder.
Modules, in data-flow order: settings (presets) -> world (true scene) -> shading (its GLSL) ->
targets (moving car / person) -> flights (camera poses) -> photos (render + metadata) ->
refmodel (the photogrammetry-like reference mesh) -> annotate (GCP clicks, tie points).
"""
