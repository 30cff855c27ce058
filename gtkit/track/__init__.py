"""Hierarchical target tracking: the wide camera localizes, the zoom camera points, the target
ray is marched against the DSM (issue 8). Modules: rig (zoom-from-wide calibration), targets
(detections input), raycast (first DSM crossing), uncertainty (pose covariance -> ground point),
smoothing (tracks), tracker (the stage)."""
