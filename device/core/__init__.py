"""The pure core: geometry, frames, rig model, features, matching, two-view and stereo geometry (no I/O)."""
