"""``gtkit export dataset SITE OUT``: the pseudo-GT as one folder a dataset builder can publish, in the
formats localization research reads (issue 56).

::

    OUT/
      DATASET.md  dataset.json      the datasheet (site, frame, sensors, provenance, accuracy, protocol)
      kapture/query/                kapture (written by the kapture package): sensors, rig, pseudo-GT
                                    trajectories, records_camera, records_gnss; the photos in
                                    sensors/records_data/ (linked, or copied with --copy)
      kapture/query_priors/         the GPS + gimbal priors as trajectories
      kapture/mapping/              reference photos + rendered database views and their depth maps
      colmap/queries/               COLMAP text model of the published query photos (pycolmap)
      hloc/pseudo_gt_poses.txt      name qw qx qy qz tx ty tz;  hloc/queries_with_intrinsics.txt
      pseudo_gt_uncertainty.txt     sigma and the full 6x6 covariance of every published pose
      kept_out.txt                  query photos kept out (unverified / refused / not registered), why
      plots/                        trajectories over the orthophoto, sigma per photo
      model/                        reference model + DSM (--with-model)

Modules: :mod:`.gt` (which poses are published, their sigma), :mod:`.kapture_tree`, :mod:`.formats`
(hloc, COLMAP, the sidecar), :mod:`.datasheet`, :mod:`.folder` (atomic folder, no-op re-export),
:mod:`.stage` (``run(project, out, DatasetSettings)``). Nothing here reads ``truth/``;
:mod:`gtkit.evaluate.results` scores a method's poses against what this writes.
"""
