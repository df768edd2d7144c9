"""Camera path estimators (pure: frames and IMU samples in, poses out, no I/O).

``make_estimator(name, rig, ...)`` returns an object with
``process(frame, imu) -> PoseEstimate`` for on-board incremental use and the
module-level :func:`stereopath.device.estimation.base.run_estimator` for whole sequences.
"""
