"""Capture: stereo sources, IMU sources, left/right pairing and IMU-to-frame time alignment."""
