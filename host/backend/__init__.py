"""The solver code that the live view and reprocessing share: stereo tracks, loop detection, GTSAM bundle
adjustment and pose graph, IMU factors."""
