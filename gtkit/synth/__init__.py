"""Sample projects: a procedurally generated site with known truth, photographed like UAVD4L.

``gtkit sample create DIR [--preset small|medium|large|tiny] [--seed N] [--gps-denied]`` calls
:func:`gtkit.synth.generate.create_sample`, which writes::

    DIR/project.toml          [crs] UTM zone of the site (small: EPSG:32650), origin; [sample] preset, seed
    DIR/images/reference/R<strip>_<station>_<N|F|B|L|R>.jpg   five-eye oblique photos (N = nadir,
                              F/B/L/R = 45 deg forward/back/left/right), RTK GPS in EXIF, DJI XMP angles
    DIR/images/queries/<seq>/<idx>_W.jpg, <idx>_Z.jpg   wide and zoom photos: noisy GPS (none with
                              --gps-denied), noisy DJI XMP gimbal/flight angles and altitudes; the zoom
                              photo carries its wide twin's gimbal record
    DIR/cameras.txt           intrinsics of every photo (name MODEL W H params; wide = RADIAL)
    DIR/gcp_list.txt          OpenDroneMap GCP file (CRS line, then E N H px py image gcpNN)
    DIR/tiepoints.json        simulated annotator clicks (gtkit.io.tiepoints; source "simulated")
    DIR/model/reference.obj (+ .mtl, reference_NNN.jpg, reference.obj.offset.json)
                              the reference mesh: decimated, noisy, baked texture with seams
    DIR/truth/poses.txt, intrinsics.txt   true pose/intrinsics of every photo
    DIR/truth/world.ply, world.json       true geometry; GLSL, lighting, settings to re-render it
    DIR/truth/targets.csv     car and person tracks (time, local xyz, CRS E/N/H, WGS84 lon/lat)
    DIR/truth/rig.json        zoom-from-wide rotation/offset, wide and zoom intrinsics
    DIR/truth/tiepoints_truth.json   true 3D of each tie point, which clicks are gross mistakes
    DIR/truth/shots.json      per photo: kind, sequence, time, manual shot or not, target followed

Modules, in data-flow order: settings (presets in ``sample_projects/*.toml``) -> world (true
scene) -> shading (its GLSL) -> targets (moving car / person) -> flights (camera poses) -> photos
(render + metadata) -> refmodel (the photogrammetry-like reference mesh, baked with
:mod:`gtkit.render.bake`) -> annotate (GCP clicks, tie points) -> generate (writes it all);
truth reads the truth back for evaluation code.
"""
